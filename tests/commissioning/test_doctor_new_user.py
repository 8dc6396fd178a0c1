"""New-user audit of ``ucr doctor``: a bent segment's load is the bend's (a tendon the bend does
not wind in still warns), findings print as they are made and survive Ctrl-C (exit 130), and an
impossible ``--seconds`` is a usage error."""

from __future__ import annotations

import math

import pytest

from host import doctor
from host.doctor_telemetry import check_telemetry
from tests.commissioning.test_doctor import _configs, chain_and_link, wait_discover

# softrobot2's geometry, as its descriptor reports it
DESC = {
    "length": 0.316,
    "tendon_radius": 0.06,
    "spool_radius": 0.025,
    "tendon_angles": [0.0, 2.0943951023931953, 4.1887902047863905],
    "kappa_max": 3.313916301255056,  # a full bend winds a tendon in by 2.51 rad
}
PER_KAPPA = DESC["length"] * DESC["tendon_radius"] / DESC["spool_radius"]  # rad of spool per 1/m


def state(kappa: float, phi: float, excess: tuple[float, ...] = (0.0, 0.0, 0.0)) -> dict:
    """A STATE of this bend whose servos are wound in as the bend needs, plus ``excess`` rad."""
    angles = [
        PER_KAPPA * kappa * math.cos(phi - sig) + e
        for sig, e in zip(DESC["tendon_angles"], excess, strict=True)
    ]
    return {"kappa": kappa, "phi": phi, "servo_angles": angles}


BENT = state(2.8, 0.0)  # towards tendon 0: it is wound in, tendons 1 and 2 pay out


class _Telemetry:
    """A link whose segment reports these servo telemetry triples (PARAM 22)."""

    def __init__(self, tel: list[list[float]]) -> None:
        self.tel = tel

    def param_get(self, pos: int, pid: int, uid: str | None = None, timeout: float = 0.5):
        assert pid == doctor.P_SERVO_TELEMETRY
        return self.tel


def _loads(findings: list[doctor.Finding]) -> list[doctor.Finding]:
    return [f for f in findings if f.check == "load"]


def test_the_servo_holding_a_bend_is_not_reported_as_over_tensioned() -> None:
    link = _Telemetry([[12.0, 30.0, 0.9], [12.0, 30.0, 0.0], [12.0, 30.0, 0.0]])
    found = check_telemetry(link, 0, None, desc=DESC, state=BENT)
    assert not _loads(found), doctor.format_text(found)
    assert "holds the bend" in found[0].message and "kappa 2.80" in found[0].message


def test_a_loaded_tendon_the_bend_pays_out_is_still_over_tension() -> None:
    link = _Telemetry([[12.0, 30.0, 0.9], [12.0, 30.0, 0.9], [12.0, 30.0, 0.0]])
    found = _loads(check_telemetry(link, 0, None, desc=DESC, state=BENT))
    assert [f.level for f in found] == ["warning"]
    assert "servo 1 load 90%" in found[0].message and "pays its tendon out" in found[0].message


def test_a_slight_bend_does_not_excuse_a_servo_near_its_max_torque() -> None:
    link = _Telemetry([[12.0, 30.0, 0.9], [12.0, 30.0, 0.0], [12.0, 30.0, 0.0]])
    slight = state(0.15, 0.0)  # winds tendon 0 in by 0.11 rad: up to 84 %
    found = _loads(check_telemetry(link, 0, None, desc=DESC, state=slight))
    assert [f.level for f in found] == ["warning"]
    assert "servo 0 load 90%" in found[0].message and "more than the bend" in found[0].message


def test_a_straight_segment_under_load_is_over_tensioned_as_before() -> None:
    link = _Telemetry([[12.0, 30.0, 0.85], [12.0, 30.0, 0.1], [12.0, 30.0, 0.1]])
    for state in ({"kappa": 0.0, "phi": 0.0}, None):  # straight, or its pose unknown
        found = _loads(check_telemetry(link, 0, None, desc=DESC, state=state))
        assert [f.message for f in found] == ["servo 0 load 85% of max torque at rest"]


def _bent_config(kappa: float, phi: float, **extra: object) -> dict:
    """segment_1 powered on in the bend (kappa, phi): its servos where that bend puts them."""
    cfg = {**_configs()[0], **extra}
    ld = cfg["length"] * cfg["tendon_radius"] / cfg["spool_radius"]
    cfg["emulated_start"] = [
        s.get("zero_offset", 0.0) + s.get("direction", 1) * ld * kappa * math.cos(phi - sig)
        for s, sig in zip(cfg["servos"], cfg["tendon_angles"], strict=True)
    ]
    return cfg


def test_a_servo_wound_in_beyond_the_bend_it_measures_is_over_tension() -> None:
    # review: one servo wound 1.8 rad past taut at rest makes the segment measure a bend towards
    # its tendon (kappa 1.58); that "bend" excused the load, though the other tendons were not
    # paid out as a real bend needs
    wound = {"kappa": 1.58, "phi": 0.0, "servo_angles": [1.8, 0.0, 0.0]}
    link = _Telemetry([[12.0, 30.0, 0.9], [12.0, 30.0, 0.0], [12.0, 30.0, 0.0]])
    found = _loads(check_telemetry(link, 0, None, desc=DESC, state=wound))
    assert [f.level for f in found] == ["warning"], found
    assert "servo 0 load 90%" in found[0].message and "beyond what the bend" in found[0].message


@pytest.mark.parametrize("kappa", [0.7, 2.8, 3.3])
def test_a_servo_at_its_torque_limit_warns_whatever_the_bend(kappa: float) -> None:
    # review: the allowance grew past 100 % from a fifth of the full bend on
    link = _Telemetry([[12.0, 30.0, 1.0], [12.0, 30.0, 0.0], [12.0, 30.0, 0.0]])
    found = _loads(check_telemetry(link, 0, None, desc=DESC, state=state(kappa, 0.0)))
    assert [f.message.split(":")[-1] for f in found] == [" at its torque limit"], found


def test_a_bend_without_the_servos_angles_excuses_nothing() -> None:
    link = _Telemetry([[12.0, 30.0, 0.9], [12.0, 30.0, 0.0], [12.0, 30.0, 0.0]])
    found = _loads(check_telemetry(link, 0, None, desc=DESC, state={"kappa": 2.8, "phi": 0.0}))
    assert [f.message for f in found] == ["servo 0 load 90% of max torque at rest"]


def test_doctor_on_a_bent_emulated_segment_warns_only_about_a_caught_tendon() -> None:
    bent = _bent_config(2.4, 0.0)  # servo 0 winds 1.8 rad in: load 0.91 (0.5 per rad)
    # tendons 1 and 2 taut though the bend pays them out; servo 0 then at its torque limit
    caught = _bent_config(2.4, 0.0, emulated_pretension=2.6)
    wound = {**_configs()[0]}  # straight, servo 0 wound 1.8 rad past taut (review)
    z = [sv.get("zero_offset", 0.0) for sv in wound["servos"]]
    d = [sv.get("direction", 1) for sv in wound["servos"]]
    wound["emulated_start"] = [z[0] + d[0] * 1.8, z[1], z[2]]
    for cfg, want in ((bent, []), (caught, [0, 1, 2]), (wound, [0])):
        with chain_and_link(1, config_for=[cfg]) as (chain, link):
            wait_discover(link, 1)
            link.close()
            findings = doctor.run(chain.host_port, 921600, None, 0.0)
        warned = [int(f.message.split()[1]) for f in _loads(findings)]
        assert warned == want, doctor.format_text(findings)
        if cfg is bent:
            tel = [f for f in findings if f.check == "telemetry"]
            assert "0: 12.0 V 30 C load 0.91 (holds the bend)" in tel[0].message, tel
        assert [f.message for f in findings if f.check == "timing"] == ["not checked (--seconds 0)"]


def test_doctor_prints_findings_as_made_and_keeps_them_on_ctrl_c(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from tools.cli import main

    before_timing: list[str] = []

    def interrupted(link: object, n: int, seconds: float) -> doctor.Finding:
        before_timing.append(capsys.readouterr().out)  # what the user saw before the slow step
        raise KeyboardInterrupt

    monkeypatch.setattr(doctor, "check_timing", interrupted)
    with chain_and_link(1, config_for=_configs()[:1]) as (chain, link):
        wait_discover(link, 1)
        link.close()
        rc = main(["doctor", "--port", chain.host_port, "--seconds", "5"])
    out, err = capsys.readouterr()
    assert rc == 130
    assert "[ok  ] chain: 1 segment(s) answer" in before_timing[0]
    assert "position 1 servos" in before_timing[0]
    err_lines = [ln for ln in err.splitlines() if not ln.startswith("  ... ")]
    assert len(err_lines) == 1 and "interrupted (Ctrl-C)" in err_lines[0], err
    assert "0 error(s)" in err_lines[0] and "Traceback" not in err


@pytest.mark.parametrize("value", ["-1", "nan", "inf", "-inf", "x"])
def test_doctor_refuses_an_impossible_seconds_as_a_usage_error(
    value: str, capsys: pytest.CaptureFixture[str]
) -> None:
    from tools.cli import main

    with pytest.raises(SystemExit) as info:
        main(["doctor", "--port", "/dev/nonexistent-ucr", f"--seconds={value}"])
    assert info.value.code == 2
    assert "--seconds" in capsys.readouterr().err

"""Client CLI (`ucr status|watch|move|trajectory|controllers|teleop`): exit codes, one-line errors,
human output in degrees. Uses the in-memory facade from test_api_protocol.py behind a real API
server; the real daemon is exercised in test_api_e2e.py."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from host.api.server import ApiServer
from tools.cli import main as ucr

pytestmark = pytest.mark.timeout(60)
ROOT = Path(__file__).resolve().parents[2]

from daemon_helpers import free_url  # noqa: E402
from test_api_protocol import FacadeStub  # noqa: E402 - the in-memory facade


@pytest.fixture
def url(stub_url):
    return stub_url


def run(capsys, *argv) -> tuple[int, str, str]:
    rc = ucr(list(argv))
    out, err = capsys.readouterr()
    # the API server runs in this process: its audit lines (the daemon's stderr) are not the CLI's
    err = "".join(ln for ln in err.splitlines(True) if " AUDIT " not in ln)
    return rc, out, err


# ------------------------------------------------------------------ daemon not running
@pytest.mark.parametrize(
    "argv",
    [
        ["status"],
        ["watch", "--count", "1"],
        ["move", "--segment", "s1", "--kappa", "1", "--phi", "0", "--duration", "1"],
        ["controllers"],
        ["controllers", "switch", "--start", "ffc"],
        ["teleop", "--keyboard"],
    ],
)
def test_daemon_not_running_is_one_clear_line_and_exit_1(capsys, argv):
    url = free_url()
    rc, out, err = run(capsys, *argv, "--url", url)
    assert rc == 1
    assert err.startswith(
        f"ucr: cannot reach the daemon at {url} (--url): is `ucr daemon` running?"
    )
    assert err.count("\n") == 1 and "$UCR_URL" in err and "$UCR_TOKEN_FILE" in err


def test_no_traceback_from_a_real_process_when_daemon_is_down():
    url = free_url()
    proc = subprocess.run(
        [sys.executable, "-m", "tools.cli", "status", "--url", url],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert proc.returncode == 1
    assert "Traceback" not in proc.stderr
    assert proc.stderr.count("\n") == 1 and "is `ucr daemon` running?" in proc.stderr


def test_bad_url_and_wrong_token_are_one_line_errors(capsys, tmp_path):
    rc, _, err = run(capsys, "status", "--url", "http://nope")
    assert rc == 2 and "bad URL" in err and err.count("\n") == 1  # usage: exit 2
    stub = FacadeStub()
    srv = ApiServer(stub, "127.0.0.1", 0, token="s3cret-token-0123456").start()
    wrong, right = tmp_path / "wrong.token", tmp_path / "right.token"
    wrong.write_text("wrong-token-0123456789\n")
    right.write_text("s3cret-token-0123456\n")
    wrong.chmod(0o600)
    right.chmod(0o600)
    try:
        rc, _, err = run(capsys, "status", "--url", srv.url, "--token-file", str(wrong))
        assert rc == 1 and "wrong token" in err and err.count("\n") == 1
        rc, out, _ = run(capsys, "status", "--url", srv.url, "--token-file", str(right))
        assert rc == 0 and "s1" in out
    finally:
        srv.stop()
        stub.close()


# ------------------------------------------------------------------ commands against a server
def test_status_shows_segments_in_degrees(capsys, url):
    rc, out, _ = run(capsys, "status", "--url", url)
    assert rc == 0
    assert "daemon: connected" in out
    line = next(ln for ln in out.splitlines() if ln.strip().startswith("s1"))
    assert "2.000 1/m" in line and "90.0°" in line


def test_watch_prints_count_lines_of_joint_states(capsys, url):
    rc, out, _ = run(capsys, "watch", "--url", url, "--count", "3", "--rate", "50")
    assert rc == 0
    lines = out.strip().splitlines()
    assert len(lines) == 3 and all("s1 κ=" in ln and "φ=" in ln for ln in lines)


def test_move_waits_for_the_result_with_progress(capsys, url):
    rc, out, _ = run(
        capsys,
        "move",
        "--url",
        url,
        "--segment",
        "s1",
        "--kappa",
        "3",
        "--phi",
        "45",
        "--duration",
        "0.3",
    )
    assert rc == 0
    assert "accepted" in out and "progress" in out and "succeeded" in out


def test_move_refused_by_the_daemon_exits_1_with_its_reason(capsys, url):
    rc, _, err = run(
        capsys, "move", "--url", url, "--segment", "s1", "--kappa", "30", "--duration", "1"
    )
    assert rc == 1
    assert err.strip() == "ucr: rejected: kappa exceeds kappa_max 10 1/m (goal rejected)"


def test_move_checks_its_arguments_before_connecting(capsys):
    rc, _, err = run(capsys, "move", "--segment", "s1", "--kappa", "-1", "--url", free_url())
    assert rc == 2 and "--kappa must be >= 0" in err
    with pytest.raises(SystemExit) as ei:  # a usage error, before any connection
        run(capsys, "move", "--segment", "s1", "--kappa", "1", "--duration", "0")
    assert ei.value.code == 2 and "--duration" in capsys.readouterr().err


TRAJ_YAML = """\
controller: jtc
waypoints:
  - t: 0.2
    segments:
      s1: {kappa: 2.0, phi_deg: 90}
  - t: 0.4
    segments:
      s1: {kx: 0.0, ky: 0.0}
"""


def test_trajectory_file_is_checked_and_sent(capsys, url, tmp_path):
    f = tmp_path / "wave.yaml"
    f.write_text(TRAJ_YAML)
    rc, out, _ = run(capsys, "trajectory", str(f), "--check")
    assert rc == 0 and "2 waypoints over 0.4 s for s1: ok" in out
    rc, out, _ = run(capsys, "trajectory", str(f), "--url", url)
    assert rc == 0 and "succeeded" in out
    f.write_text(TRAJ_YAML.replace("s1:", "s9:"))
    rc, out, err = run(capsys, "trajectory", str(f), "--url", url)
    assert rc == 1 and "s9 not controlled by the daemon (controlled: s1)" in err


@pytest.mark.parametrize(
    ("text", "needle"),
    [
        ("waypoints: [{t: 1, segments: {s1: {kappa: -2}}}]", ":1: waypoint 1.segments.s1.kappa"),
        (
            "waypoints: [{t: 2, segments: {s1: {kappa: 1}}}, {t: 1, segments: {s1: {kappa: 1}}}]",
            "increase strictly",
        ),
        ("waypoints: [{t: 1, segments: {s1: {kappa: 1, phi: 0, phi_deg: 3}}}]", "not both"),
        ("speed: 3\nwaypoints: []", "unknown top-level key"),
        ("waypoints: [{t: 1, segments: {s1: {kappa: 1}}}", "not valid YAML"),
        ("- just text", "expected a mapping"),
    ],
)
def test_bad_trajectory_file_is_reported_with_file_and_waypoint(capsys, tmp_path, text, needle):
    f = tmp_path / "bad.yaml"
    f.write_text(text)
    rc, _, err = run(capsys, "trajectory", str(f), "--check")
    assert rc == 1
    assert str(f) in err and needle in err and err.count("\n") == 1


@pytest.mark.parametrize(
    ("name", "text", "where"),
    [
        ("t.yaml", "waypoints:\n  - {t: 1, segments: {s1: {kappa: 1}}\n  - {t: 2}\n", ":3:3:"),
        ("t.yaml", "waypoints: [\n", ":2:1:"),
        ("t.yaml", "waypoints:\n  t: 1: 2\n", ":2:7:"),
        ("t.json", '{"waypoints": [\n  {"t": 1,}\n]}\n', ":2:11:"),
    ],
)
def test_a_trajectory_file_that_does_not_parse_says_where(capsys, tmp_path, name, text, where):
    """Review 2026-11-27: a YAML syntax error said "not valid YAML: while parsing a flow node",
    no line: in a file of 1,000 waypoints the user had to find it alone."""
    f = tmp_path / name
    f.write_text(text)
    rc, _, err = run(capsys, "trajectory", str(f), "--check")
    assert rc == 1
    assert f"{f}{where} not valid {'JSON' if name.endswith('json') else 'YAML'}: " in err, err
    assert err.count("\n") == 1


def test_trajectory_json_file_and_missing_file(capsys, tmp_path):
    f = tmp_path / "t.json"
    f.write_text('[{"time_from_start": 1.0, "segments": {"s1": {"kappa": 1.0, "phi": 0.0}}}]')
    assert run(capsys, "trajectory", str(f), "--check")[0] == 0
    rc, _, err = run(capsys, "trajectory", str(tmp_path / "none.yaml"), "--check")
    assert rc == 1 and "cannot read" in err


@pytest.mark.parametrize("value", ["0", "-1", "nan", "inf", "soon"])
def test_a_timeout_that_cannot_work_is_a_usage_error(capsys, value):
    """Review 2026-11-26: --timeout 0 or -1 made the call fail at once, reported as "cannot
    reach the daemon: is `ucr daemon` running?"."""
    with pytest.raises(SystemExit) as ei:
        ucr(["status", "--timeout", value])
    assert ei.value.code == 2
    assert "--timeout" in capsys.readouterr().err


@pytest.mark.parametrize("option", ["--duration", "--timeout"])
@pytest.mark.parametrize("value", ["1e400", "inf", "0", "-1"])
def test_move_names_finiteness_in_its_seconds_bounds(capsys, option, value):
    """Audit of issue 12: `--duration 1e400` said "must be > 0 s" (infinity is > 0)."""
    with pytest.raises(SystemExit) as ei:
        ucr(["move", "--segment", "s1", "--kappa", "1", option, value, "--url", free_url()])
    assert ei.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err.endswith(f"argument {option}: must be a finite number of s > 0, got {value}"), err


def test_wss_to_a_daemon_without_tls_says_tls_failed(capsys, url):
    """Review 2026-11-26: wss:// against a plain ws:// daemon said "is `ucr daemon` running?"."""
    rc, _, err = run(capsys, "status", "--url", url.replace("ws://", "wss://"))
    assert rc == 1
    assert "TLS with the daemon" in err and "takes ws://" in err and "running?" not in err


def test_ctrl_c_ends_watch_and_teleop_with_130_and_teleop_stops_the_segments(
    capsys, url, tmp_path, monkeypatch
):
    """Review 2026-11-26: Ctrl-C in `ucr watch` and `ucr teleop` exited 0 (docs: 130), and
    teleop left the segments to the deadman without a word."""
    import host.client_cli as client_cli
    import host.teleop as teleop

    def interrupt(msg):
        raise KeyboardInterrupt

    monkeypatch.setattr(client_cli, "format_message", interrupt)
    assert run(capsys, "watch", "--url", url)[0] == 130

    sent: list[dict] = []

    def run_then_interrupt(self, source):
        self.send({"s1": (0.5, 0.0)})
        raise KeyboardInterrupt

    monkeypatch.setattr(teleop.Teleop, "run", run_then_interrupt)
    rec = tmp_path / "stick.jsonl"
    rec.write_text('{"t": 0.0, "rates": {"s1": [0.5, 0.0]}}\n')
    from host.api.client import Client

    real = Client.ffc_input
    monkeypatch.setattr(Client, "ffc_input", lambda c, rates: sent.append(rates) or real(c, rates))
    rc, _, err = run(capsys, "teleop", "--url", url, "--replay", str(rec))
    assert rc == 130
    assert sent[-1] == {"s1": (0.0, 0.0)} and "zero input sent" in err


@pytest.mark.parametrize("value", ["inf", "nan"])
def test_move_with_a_kappa_that_is_not_a_number_says_so(capsys, value):
    """Review 2026-11-26: --kappa inf / nan said "must be >= 0"."""
    rc, _, err = run(capsys, "move", "--segment", "s1", "--kappa", value)
    assert rc == 2 and "--kappa must be a finite number" in err


def test_yaml_numbers_with_an_exponent_are_numbers(capsys, tmp_path):
    """Review 2026-11-26: `t: 5e-1` was refused as "expected a number, got string" (PyYAML
    reads YAML 1.1, where an exponent needs a dot); the daemon's config file likewise."""
    f = tmp_path / "e.yaml"
    f.write_text("waypoints:\n- t: 5e-1\n  segments: {s1: {kappa: 1e0, phi: -2E-1}}\n")
    rc, out, err = run(capsys, "trajectory", str(f), "--check")
    assert rc == 0, err
    assert "1 waypoints over 0.5 s for s1: ok" in out
    from host.config import load_config

    cfg = tmp_path / "d.yaml"
    cfg.write_text("rate_hz: 5e1\n")
    assert load_config(cfg).rate_hz == 50.0


def test_controllers_list_and_switch(capsys, url):
    rc, out, _ = run(capsys, "controllers", "--url", url)
    assert rc == 0 and "jtc" in out and "active" in out
    assert run(capsys, "controllers", "--url", url, "list")[0] == 0
    assert run(capsys, "controllers", "list", "--url", url)[0] == 0
    rc, out, _ = run(
        capsys, "controllers", "switch", "--url", url, "--start", "ffc", "--stop", "jtc"
    )
    assert rc == 0
    rc, _, err = run(capsys, "controllers", "switch", "--url", url, "--start", "nope")
    assert rc == 1 and "unknown controller 'nope'" in err
    rc, _, err = run(capsys, "controllers", "switch", "--url", url)
    assert rc == 2


def test_move_to_an_unknown_segment_names_the_robots_bendables(capsys, url):
    """Audit of issue 12: `ucr move --segment segment_9` answered "trajectory point 0: …"."""
    rc, _, err = run(capsys, "move", "--url", url, "--segment", "segment_9", "--kappa", "1")
    assert rc == 1
    assert err.strip() == "ucr: unknown segment 'segment_9': stub's bendables are s1"
    assert "trajectory point" not in err


def test_move_to_a_segment_not_controlled_now_says_so(capsys, url, monkeypatch):
    topo = {"robot": "stub", "expected": ["s1", "s2"], "controlled": ["s1"]}
    monkeypatch.setattr(FacadeStub, "topology", lambda self: topo)
    rc, _, err = run(capsys, "move", "--url", url, "--segment", "s2", "--kappa", "1")
    assert rc == 1 and "segment 's2' is not controlled now (controlled: s1;" in err


def test_an_unknown_daemon_log_level_is_a_usage_error(capsys):
    # new-user audit: `ucr daemon --log-level foo` ran at INFO without a word
    with pytest.raises(SystemExit) as exc:
        ucr(["daemon", "--robot", "robots/softrobot3.ucrdf", "--log-level", "foo"])
    assert exc.value.code == 2
    assert "invalid choice" in capsys.readouterr().err


def test_a_command_sender_is_put_in_words_that_carry_no_control_character():
    """``ucr goal`` and ``ucr view`` name who sent a goal or a cFFC input as the daemon says
    (``from`` / ``input_from``); the client's own words come from any client (its User-Agent and
    on_behalf_of), so they are quoted as literals: no escape sequence reaches a terminal."""
    from host.api.client import sender_words

    assert sender_words(None) == "" and sender_words("x") == ""
    assert sender_words({"peer": "127.0.0.1:4", "client": "gamepad", "for": "stick js0"}) == (
        "API client 'gamepad' for 'stick js0' at 127.0.0.1:4"
    )
    assert sender_words({"client": 7}) == "API client '-'"
    evil = sender_words({"client": "\x1b[2Jx", "for": "a\nb", "peer": "p q\x07"})
    assert "\x1b" not in evil and "\n" not in evil and "\x07" not in evil, evil
    assert evil == r"API client '\x1b[2Jx' for 'a\nb' at 'p q\x07'"


def test_status_names_who_drives_a_manual_takeover():
    """`ucr status` said "manual control: ffc" whoever streamed it; it now adds who sent the
    cFFC's latest input (its input_from), asking controllers.list only during a takeover."""
    from host.api.client import ApiError
    from host.client_status import format_status, manual_senders

    class Client:
        asked = 0

        def controllers(self):
            Client.asked += 1
            sender = {"peer": "127.0.0.1:4", "client": "gamepad", "for": "stick js0"}
            return [{"name": "jtc", "type": "jtc"},
                    {"name": "ffc", "type": "ffc", "input_from": sender}]  # fmt: skip

    st = {"state": "connected", "manual_control": ["ffc"], "joint_states": {}}
    senders = manual_senders(Client(), st)
    assert senders == {"ffc": "API client 'gamepad' for 'stick js0' at 127.0.0.1:4"}
    text = "\n".join(format_status(st, None, senders))
    assert "manual control: ffc" in text
    assert "  ffc: latest input from API client 'gamepad' for 'stick js0' at 127.0.0.1:4" in text
    assert manual_senders(Client(), {"manual_control": []}) == {} and Client.asked == 1

    class Refusing:
        def controllers(self):
            raise ApiError("forbidden", "no")

    assert manual_senders(Refusing(), st) == {}  # the line just says less
    assert manual_senders(Client(), {"manual_control": "ffc"}) == {}  # not a list: nothing


def test_status_says_how_old_it_is_and_ucr_status_warns_when_the_daemon_sent_none_lately(
    capsys, stub, stub_server
):
    """Review 2026-11-28: the API answers ``status`` from the daemon's last snapshot; with the
    daemon frozen it went on answering that snapshot, and nothing told it from a fresh one."""
    import threading
    import time

    from host.api.client import connect

    url = stub_server.url
    with connect(url) as c:
        assert 0.0 <= c.status()["status_age_s"] < 1.0  # one every 50 ms
        rc, out, _ = run(capsys, "status", "--url", url)
        assert rc == 0 and " s old: the daemon has sent none since" not in out
        held = threading.Event()
        fresh = stub.status
        stub.status = lambda: held.wait(30) or fresh()  # the daemon's lock held: no snapshot
        try:
            time.sleep(1.5)
            age = c.status()["status_age_s"]
            rc, out, _ = run(capsys, "status", "--url", url)
        finally:
            held.set()
    assert age > 1.0
    assert rc == 0 and " s old: the daemon has sent none since (its process is frozen" in out

"""Teleop input sources and the ffc.input streaming policy (no daemon needed here; the run through
the API against the emulated chain is in test_api_e2e.py)."""

from __future__ import annotations

import io
import json
import os
import threading
import time
from types import SimpleNamespace

import pytest

from host.teleop import (
    GamepadSource,
    InputEvent,
    KeyboardSource,
    Recorder,
    ReplaySource,
    Teleop,
    TeleopError,
    normalise_axis,
    parse_keys,
    parse_recording,
)

evdev = pytest.importorskip(
    "evdev", reason="evdev (the 'gamepad' extra) is not installed: pip install -e '.[gamepad]'"
)
ecodes = evdev.ecodes

pytestmark = pytest.mark.timeout(30)


def write_lines(path, objs) -> str:
    path.write_text("".join(json.dumps(o) + "\n" for o in objs))
    return str(path)


class Sink:
    """Collects what Teleop sends, with time stamps."""

    def __init__(self) -> None:
        self.sent: list[tuple[float, dict]] = []

    def __call__(self, rates: dict) -> None:
        self.sent.append((time.monotonic(), dict(rates)))


# ------------------------------------------------------------------ recording format
@pytest.mark.parametrize(
    ("line", "needle"),
    [
        ("not json", "not JSON"),
        ('{"rates": {"a": [0, 0]}}', "'t'"),
        ('{"t": -1, "stop": true}', "'t'"),
        ('{"t": 0, "rates": {"a": [2, 0]}}', "within [-1, 1]"),
        ('{"t": 0, "rates": {"a": [0]}}', "within [-1, 1]"),
        ('{"t": 0, "rates": {}}', "must map"),
        ('{"t": 0, "jump": true}', "expected exactly one of"),
        ('{"t": 0, "stop": false}', "expected exactly one of"),
    ],
)
def test_bad_recording_line_is_reported_with_its_line_number(line, needle):
    with pytest.raises(TeleopError) as info:
        parse_recording(['{"t": 0, "stop": true}', line], "rec.jsonl")
    assert "rec.jsonl:2" in str(info.value) and needle in str(info.value)


def test_recording_going_back_in_time_is_refused():
    with pytest.raises(TeleopError, match="back in time"):
        parse_recording(['{"t": 1, "stop": true}', '{"t": 0.5, "stop": true}'])


# ------------------------------------------------------------------ streaming policy
def test_replay_streams_while_deflected_sends_one_zero_on_release_and_nothing_after_end(tmp_path):
    rec = write_lines(
        tmp_path / "r.jsonl",
        [
            {"t": 0.0, "rates": {"s1": [0.5, 0.0]}},
            {"t": 0.4, "stop": True},
            {"t": 0.7, "rates": {"s2": [0.0, -1.0]}},
            {"t": 1.0, "end": True},
        ],
    )
    sink = Sink()
    t0 = time.monotonic()
    result = Teleop(sink, rate_hz=50).run(ReplaySource(rec))
    assert result.reason == "end"
    first = [r for t, r in sink.sent if t - t0 < 0.39]
    assert all(r == {"s1": (0.5, 0.0)} for r in first)
    assert 14 <= len(first) <= 21  # ~50 Hz for 0.4 s
    zeros = [t for t, r in sink.sent if not any(x or y for x, y in r.values())]
    assert len(zeros) == 1 and result.zeros_sent == 1  # one stop on release, not a stream
    second = [r for t, r in sink.sent if t - t0 > 0.69]
    assert second and all(r == {"s1": (0.0, 0.0), "s2": (0.0, -1.0)} for r in second)
    # Input ended while deflected: no zero afterwards (the daemon's deadman stops the robot).
    assert sink.sent[-1][1]["s2"] == (0.0, -1.0)
    assert sink.sent[-1][0] - t0 < 1.1


def test_quit_sends_a_final_zero(tmp_path):
    rec = write_lines(
        tmp_path / "r.jsonl", [{"t": 0.0, "rates": {"s1": [0.0, 0.3]}}, {"t": 0.1, "quit": True}]
    )
    sink = Sink()
    result = Teleop(sink, rate_hz=50).run(ReplaySource(rec))
    assert result.reason == "quit"
    assert sink.sent[-1][1] == {"s1": (0.0, 0.0)}


def test_recorder_output_replays_to_the_same_events(tmp_path):
    rec = write_lines(
        tmp_path / "r.jsonl",
        [
            {"t": 0.0, "rates": {"s1": [0.25, -0.5]}},
            {"t": 0.05, "stop": True},
            {"t": 0.1, "end": True},
        ],
    )
    out = io.StringIO()
    Teleop(lambda r: None).run(Recorder(ReplaySource(rec), out))
    again = parse_recording(out.getvalue().splitlines())
    assert [e.kind for _, e in again] == ["rates", "stop", "end"]
    assert again[0][1].rates == {"s1": (0.25, -0.5)}


# ------------------------------------------------------------------ keyboard
def test_key_parsing_understands_arrows_and_letters():
    assert parse_keys(b"w\x1b[A\x1b[D 3q\x03") == ["w", "up", "left", "space", "3", "q", "ctrl-c"]


def test_keyboard_keys_deflect_selected_segment_then_release_after_hold_time():
    r, w = os.pipe()
    try:
        kb = KeyboardSource(["s1", "s2"], fd=r, hold_s=0.2, gain=0.5)
        os.write(w, b"2w")
        evs = kb.read(0.1)
        assert evs[-1].kind == "rates" and evs[-1].rates == {"s1": (0.0, 0.0), "s2": (0.0, 0.5)}
        os.write(w, b"\x1b[C")  # right arrow adds +x on the same segment
        assert kb.read(0.1)[-1].rates["s2"] == (0.5, 0.5)
        time.sleep(0.25)
        released = kb.read(0.0)
        assert released[-1].rates == {"s1": (0.0, 0.0), "s2": (0.0, 0.0)}
        os.write(w, b" ")
        assert kb.read(0.1)[0].kind == "stop"
        os.write(w, b"q")
        assert kb.read(0.1)[-1].kind == "quit"
        kb.close()
    finally:
        os.close(r)
        os.close(w)


# ------------------------------------------------------------------ gamepad mapping
def test_axis_normalisation_centre_deadzone_and_ends():
    assert normalise_axis(0, -32768, 32767, 0.1) == 0.0
    assert normalise_axis(2000, -32768, 32767, 0.1) == 0.0  # inside the deadzone
    assert normalise_axis(32767, -32768, 32767, 0.1) == pytest.approx(1.0)
    assert normalise_axis(-32768, -32768, 32767, 0.1) == pytest.approx(-1.0)
    assert normalise_axis(255, 0, 255, 0.1) == pytest.approx(1.0)
    assert 0.0 < normalise_axis(20000, -32768, 32767, 0.1) < 0.61


class FakeDevice:
    """An evdev-like device fed by the test (a pipe gives select() a real fd)."""

    def __init__(self) -> None:
        self.r, self.w = os.pipe()
        self.fd = self.r
        self.name = "Test Pad"
        self.pending: list = []
        info = SimpleNamespace(min=-32768, max=32767)
        self._caps = {
            ecodes.EV_ABS: [
                (c, info) for c in (ecodes.ABS_X, ecodes.ABS_Y, ecodes.ABS_RX, ecodes.ABS_RY)
            ]
        }

    def capabilities(self):
        return self._caps

    def feed(self, *events) -> None:
        self.pending.extend(evdev.InputEvent(0, 0, t, c, v) for t, c, v in events)
        os.write(self.w, b"x")

    def read(self):
        os.read(self.r, 64)
        out, self.pending = self.pending, []
        return out

    def close(self) -> None:
        os.close(self.r)
        os.close(self.w)


def test_gamepad_sticks_map_to_selected_segment_pair_and_buttons_select_and_hold():
    dev = FakeDevice()
    pad = GamepadSource(["s1", "s2", "s3"], device=dev)
    dev.feed((ecodes.EV_ABS, ecodes.ABS_X, 32767), (ecodes.EV_ABS, ecodes.ABS_RY, -32768))
    rates = pad.read(0.5)[-1].rates
    assert rates["s1"] == (pytest.approx(1.0), 0.0)  # left stick right -> +x on s1
    assert rates["s2"] == (0.0, pytest.approx(1.0))  # right stick up -> +y on s2
    assert rates["s3"] == (0.0, 0.0)
    dev.feed((ecodes.EV_KEY, ecodes.BTN_TR, 1))  # next pair: s2, s3
    rates = pad.read(0.5)[-1].rates
    assert rates["s2"][0] == pytest.approx(1.0) and rates["s3"][1] == pytest.approx(1.0)
    dev.feed((ecodes.EV_KEY, ecodes.BTN_SOUTH, 1))  # hold: everything reads zero
    assert all(v == (0.0, 0.0) for v in pad.read(0.5)[-1].rates.values())
    dev.feed((ecodes.EV_KEY, ecodes.BTN_START, 1))
    assert pad.read(0.5) == [InputEvent("quit")]
    pad.close()


# ------------------------------------------------------------------ refusals ridden through
class Refusing(Sink):
    """A send refused (``Unavailable``) while ``refuse`` is set, as the daemon refuses input
    while its chain is lost or being rebuilt."""

    def __init__(self) -> None:
        super().__init__()
        self.refuse = False
        self.refused: list[dict] = []
        self.log: list[tuple[str, dict]] = []

    def __call__(self, rates: dict) -> None:
        if self.refuse:
            self.refused.append(dict(rates))
            self.log.append(("refused", dict(rates)))
            raise Unavailable("unavailable: chain not available")
        self.log.append(("sent", dict(rates)))
        super().__call__(rates)


class Unavailable(Exception):
    pass


def test_a_transient_refusal_holds_the_stick_until_it_is_centred(tmp_path):
    """Review 2026-11-28: `ucr teleop` ended with an error at the first refusal of a daemon that
    lost its chain for a moment (a segment's power blip). Now a transient refusal is ridden
    through, and a stick still held when the daemon accepts input again moves nothing: it has to
    be centred first (re-arm), so the robot never resumes motion on its own."""
    rec = write_lines(
        tmp_path / "r.jsonl",
        [
            {"t": 0.0, "rates": {"s1": [0.5, 0.0]}},
            {"t": 0.6, "stop": True},  # centred: input goes through again
            {"t": 0.8, "rates": {"s1": [0.0, 0.4]}},
            {"t": 1.0, "end": True},
        ],
    )
    send, notes = Refusing(), []
    teleop = Teleop(
        send, rate_hz=50, transient=lambda e: isinstance(e, Unavailable), on_note=notes.append
    )
    t0 = time.monotonic()

    def refuse_between(a: float, b: float) -> None:
        while time.monotonic() - t0 < b:
            send.refuse = time.monotonic() - t0 >= a
            time.sleep(0.002)
        send.refuse = False

    th = threading.Thread(target=refuse_between, args=(0.1, 0.3), daemon=True)
    th.start()
    result = teleop.run(ReplaySource(rec))
    th.join()
    assert result.reason == "end" and result.refused >= 1 and send.refused
    assert all(r == {"s1": (0.5, 0.0)} for r in send.refused)  # refused while held
    last = max(i for i, (what, _) in enumerate(send.log) if what == "refused")
    after = [r for what, r in send.log[last + 1 :]]
    # the daemon accepts input again while the stick is still held: nothing is sent until the
    # release, whose one zero comes first; then the next deflection drives again (re-armed)
    assert after[0] == {"s1": (0.0, 0.0)}, after[:3]
    assert len(after) > 1 and all(r == {"s1": (0.0, 0.4)} for r in after[1:]), after
    assert len(notes) == 2 and "centre every stick" in notes[0] and "centred" in notes[1], notes
    assert "refused by the daemon" in result.summary()


def test_a_refusal_that_is_not_transient_ends_the_session(tmp_path):
    rec = write_lines(tmp_path / "r.jsonl", [{"t": 0.0, "rates": {"s1": [0.5, 0.0]}}])
    send = Refusing()
    send.refuse = True
    with pytest.raises(Unavailable):
        Teleop(send, rate_hz=50, transient=lambda e: False).run(ReplaySource(rec))
    with pytest.raises(Unavailable):  # no predicate: every exception ends it, as before
        Teleop(send, rate_hz=50).run(ReplaySource(rec))


def test_teleop_rides_through_unavailable_only():
    from host.api.client import ApiConnectionError, ApiError, ApiTimeoutError
    from host.client_common import refusal_is_transient

    assert refusal_is_transient(ApiError("unavailable", "chain not available (waiting: …)"))
    assert not refusal_is_transient(ApiError("rate_limited", "request budget used up"))
    assert not refusal_is_transient(ApiError("invalid_params", "unknown segment"))
    assert not refusal_is_transient(ApiConnectionError("the daemon closed the connection"))
    assert not refusal_is_transient(ApiTimeoutError("no reply in 5 s"))
    assert not refusal_is_transient(OSError("boom"))


def test_a_second_run_starts_centred_whatever_the_last_one_ended_with(tmp_path):
    """Review 2026-11-28: a Teleop run again (a script's second session) kept the deflection
    its last run ended with, and streamed it from the first tick with no input."""
    held = write_lines(
        tmp_path / "a.jsonl", [{"t": 0.0, "rates": {"s1": [0.5, 0.0]}}, {"t": 0.1, "end": True}]
    )
    idle = write_lines(tmp_path / "b.jsonl", [{"t": 0.3, "end": True}])
    sink = Sink()
    teleop = Teleop(sink, rate_hz=50)
    assert teleop.run(ReplaySource(held)).reason == "end"  # ended deflected (no zero owed)
    before = len(sink.sent)
    assert teleop.run(ReplaySource(idle)).reason == "end"
    assert sink.sent[before:] == []  # nothing moved: no input in this run

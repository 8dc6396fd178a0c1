"""``ucr calibrate`` without --script: a terminal UI (textual, the 'tui' extra) over a Session.

Keys: space or h holds at once (HOLD to the segment; the running step ends), i identify,
0-9 select a servo, + / - jog it in / out by the jog step, [ / ] halve / double the step,
r reverse its direction, d check every direction, t tension to the load threshold, s straight,
p persist, q quit (holding). Each step runs in a worker thread, one at a time; the UI stays
responsive so the hold key always works. Ctrl-C holds and quits too, with return code 130 (bound
here: textual 8 maps it to a "press ctrl+q to quit" prompt, which neither held nor quit).
"""

from __future__ import annotations

from typing import Any

from host.calibrate import CalibrationError, Session
from host.extras import require
from host.positions import label

require("textual", extra="tui")

from textual.app import App, ComposeResult  # noqa: E402 - after the extra check
from textual.binding import Binding  # noqa: E402
from textual.widgets import Footer, Header, RichLog, Static  # noqa: E402

JOG_MIN, JOG_MAX = 0.005, 0.2  # rad
INTERRUPTED = 130  # the return code after Ctrl-C (= host.calibrate_cli.INTERRUPTED)


class CalibrateApp(App):
    """The UI of one calibration session (``session.stop()`` is the hold key's action)."""

    TITLE = "ucr calibrate"
    BINDINGS = [
        ("space", "hold", "HOLD"),
        ("h", "hold", "hold"),
        ("i", "identify", "identify"),
        ("plus", "jog(1)", "jog in"),
        ("minus", "jog(-1)", "jog out"),
        ("left_square_bracket", "step(0.5)", "step/2"),
        ("right_square_bracket", "step(2)", "step*2"),
        ("r", "reverse", "reverse"),
        ("d", "directions", "check dirs"),
        ("t", "tension", "tension"),
        ("s", "straight", "straight"),
        ("p", "persist", "persist"),
        ("q", "quit", "quit"),
        Binding("ctrl+c", "interrupt", "quit", show=False, priority=True),
    ] + [(str(k), f"select({k})", "") for k in range(10)]

    def __init__(self, session: Session, *, threshold: float = 0.05, on_persist=None) -> None:
        super().__init__()
        self.session = session
        self.threshold = threshold
        self.on_persist = on_persist
        self.servo = 0
        self.jog_step = 0.02
        self.busy = False
        self.lines: list[str] = []
        self.result: Any = None
        #: why the last `persist` failed (None: none failed, or a later one succeeded); the CLI
        #: says it again on stderr at exit, where the UI's log is gone
        self.persist_error: str | None = None
        #: a HOLD that could not be sent (the port failed): the CLI exits 1 with it
        self.error: str | None = None
        session.say = self._say_from_worker

    def compose(self) -> ComposeResult:
        yield Header()
        yield Static(id="status")
        yield RichLog(id="log", wrap=True)
        yield Footer()

    def on_mount(self) -> None:
        self._status()
        self.say(
            f"{label(self.session.position)} ({self.session.uid}): space holds at once; "
            "i identify, d check directions, t tension, p persist"
        )

    # -- output ---------------------------------------------------------------------------------
    def say(self, line: str) -> None:
        self.lines.append(line)
        self.query_one("#log", RichLog).write(line)
        self._status()

    def _say_from_worker(self, line: str) -> None:
        self.call_from_thread(self.say, line)

    def _status(self) -> None:
        s = self.session
        zeros = "  ".join(
            f"{'>' if i == self.servo else ' '}{i}: {z:+.4f} rad {d:+d}"
            for i, (z, d) in enumerate(zip(s.zeros, s.dirs, strict=False))
        )
        state = "HELD" if s.stopped else ("running" if self.busy else "ready")
        self.query_one("#status", Static).update(
            f"[{state}] jog step {self.jog_step:.3f} rad   {zeros}"
        )

    # -- steps ----------------------------------------------------------------------------------
    def _run(self, name: str, fn) -> None:
        if self.busy:
            self.say(f"{name}: a step is running (space holds it)")
            return
        self.busy = True
        self.session.resume()  # a new step is an explicit command: motion may start again
        self._status()

        def work() -> None:
            try:
                out = fn()
                if name == "persist":
                    self.result = out
                    if self.on_persist is not None:
                        self.on_persist(out)
                    self.persist_error = None
                self.call_from_thread(self.say, f"{name}: done")
            except CalibrationError as exc:
                self._failed(name, str(exc))
                self.call_from_thread(self.say, f"{name}: {exc}")
            except Exception as exc:  # noqa: BLE001 - shown, never a traceback in the UI
                self._failed(name, str(exc))
                self.call_from_thread(self.say, f"{name}: failed: {exc}")
            finally:
                self.busy = False
                self.call_from_thread(self._status)

        self.run_worker(work, thread=True, exclusive=False, name=name)

    def _failed(self, name: str, why: str) -> None:
        if name == "persist":
            self.persist_error = why

    def _hold(self) -> str | None:
        """``session.stop()``; a port that failed (LinkError) is returned as what to say, not
        raised: raised in an action, textual ended the app with code 1 and a traceback, which
        the CLI took for a clean exit."""
        try:
            self.session.stop()
        except Exception as exc:  # noqa: BLE001 - the port failed: said, never a crash
            self.error = f"HOLD not sent ({exc}); its watchdog holds it"
            return self.error
        return None

    def action_hold(self) -> None:
        failed = self._hold()
        self.say(
            f"HOLD: {failed}" if failed else "HOLD: the segment holds (any step key starts again)"
        )

    def action_select(self, k: int) -> None:
        if k < self.session.n:
            self.servo = k
            self._status()

    def action_step(self, factor: float) -> None:
        self.jog_step = min(JOG_MAX, max(JOG_MIN, self.jog_step * factor))
        self._status()

    def action_jog(self, sign: int) -> None:
        i = self.servo
        delta = sign * self.jog_step * self.session.dirs[i]  # + winds the tendon in
        self._run("jog", lambda: self.session.jog(i, delta))

    def action_reverse(self) -> None:
        i = self.servo
        self._run("direction", lambda: self.session.set_direction(i, -self.session.dirs[i]))

    def action_identify(self) -> None:
        self._run("identify", self.session.identify)

    def action_directions(self) -> None:
        self._run("check-directions", self.session.check_directions)

    def action_tension(self) -> None:
        self._run("tension", lambda: self.session.tension(self.threshold))

    def action_straight(self) -> None:
        self._run("straight", lambda: self.session.move(0.0, 0.0))

    def action_persist(self) -> None:
        self._run("persist", self.session.persist)

    async def action_quit(self) -> None:
        """q: hold and quit; return code 1 when the HOLD could not be sent (``self.error``)."""
        failed = self._hold()
        self.exit(self.result, return_code=1 if failed else 0)

    async def action_interrupt(self) -> None:
        """Ctrl-C: hold and quit as q does, with the exit code of an interrupted command."""
        self._hold()
        self.exit(self.result, return_code=INTERRUPTED)

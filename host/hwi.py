"""Hardware interface (paper REQ 1): command and state interfaces per bendable, with lifecycle.

Interfaces are named ``<bendable>/kappa`` and ``<bendable>/phi`` as the U(C)RDF ``<ros2_control>``
block declares them (initial values, min/max from its params, see ``host.config.bendable_limits``).

Lifecycle, as ros2_control's hardware components:
``unconfigured`` --configure--> ``inactive`` --activate--> ``active``, and back with
``deactivate`` (active → inactive) and ``cleanup`` (inactive → unconfigured).
- state interfaces are readable from ``inactive`` on (configure reads the segments once);
- command interfaces are written to the segments only while ``active``. While inactive the cycle
  sends HEARTBEAT (feeds the segments' watchdogs, returns states) and never a setpoint.

A segment is only commanded once it has been measured since activation: until its first STATE,
its SYNC entry is a hold entry (None: the segment keeps its own setpoint), never a made-up (0, 0).

No motion without a command (docs/daemon.md "No motion without a command"), enforced here and
nowhere else: a segment whose STATE is missing for ``gap_cycles`` consecutive cycles loses its
command — its SYNC entries become hold entries, so it never follows a setpoint computed while
the host could not see it. When a valid STATE comes back, the HWI takes the measured pose as its
command (``first_measured`` lists it, and every active controller re-anchors there before it may
command it again): after a gap or a rejoin a segment holds where it is measured.

While the chain is shorter than its description, ``probe_extra`` asks the SYNC to wait for that
many positions beyond the known tip (their entries are hold entries): a segment that answers
there lands in ``extra_states``, and supervision rejoins it.
An interface without a command interface keeps the value measured at activation (a bendable
declaring only ``kappa`` keeps its measured phi), and a bendable with no command interface at all
always gets a hold entry. ``last_states`` keeps the last STATE of every segment across missed
cycles (and across a rebuild, through ``known``).

A segment that reports HOLD ignores setpoints until a SYNC with "resume": activation sets
``resume_pending`` (the first SYNCs resume), and it clears once no segment reports HOLD.

One bus exchange per cycle: ``write()`` sends one SYNC (setpoints of every segment, one frame) or a
HEARTBEAT and stores the STATE replies; ``read()`` at the start of the next cycle copies those
states into the state interfaces. So read → update → write costs one frame down and one round of
STATE frames up.

``pipeline`` (docs/daemon.md "Pipelining"): ``write()`` sends this cycle's SYNC and then collects
the STATEs of the previous cycle's SYNC, which had a whole period to arrive, instead of waiting
for this one's: a chain whose exchange takes longer than the reply window still gets every
STATE, at the price of one period more between a measurement and the setpoint computed from it.
Setpoints are applied in the order sent (FIFO links, rule 8.4 of docs/protocol.md). A probe
beyond the tip is pipelined like any SYNC; a HEARTBEAT (inactive) closes the open cycle without
waiting for its STATEs and runs unpipelined.
"""

from __future__ import annotations

import math
import time
from typing import Any

from host.controllers.base import RobotState
from host.limits import BendableLimits, clamp_phi

UNCONFIGURED, INACTIVE, ACTIVE = "unconfigured", "inactive", "active"


class LifecycleError(RuntimeError):
    """A lifecycle transition or interface access that the current state does not allow."""


class HardwareInterface:
    """The HWI of one chain. ``limits`` is chain-ordered: bendable i is segment position i.

    ``link`` is a :class:`host.link.ChainLink` (or anything with its ``sync``/``heartbeat``).
    """

    def __init__(
        self,
        limits: dict[str, BendableLimits],
        link: Any,
        reply_timeout: float = 0.02,
        known: dict[str, dict] | None = None,
        gap_cycles: int = 2,
        pipeline: bool = False,
    ):
        """``known``: last STATE per bendable from a previous HWI of this chain (a rebuild);
        ``gap_cycles``: consecutive cycles without a STATE after which a segment loses its
        command (held where measured when it answers again); ``pipeline``: collect each SYNC's
        STATEs one cycle later (module docstring)."""
        self.limits = limits
        self.names = list(limits)
        self.link = link
        self.reply_timeout = reply_timeout
        self.state = UNCONFIGURED
        self.command: dict[str, float] = {}
        self.state_values: dict[str, float] = {}
        for name, bl in limits.items():
            if "kappa" in bl.command_interfaces:
                self.command[f"{name}/kappa"] = bl.kappa_initial
            if "phi" in bl.command_interfaces:
                self.command[f"{name}/phi"] = bl.phi_initial
        self.raw_states: list[dict | None] = [None] * len(self.names)
        known = known or {}
        # last STATE received per position, kept while a segment misses cycles
        self.last_states: list[dict | None] = [known.get(n) for n in self.names]
        # (kappa 1/m, phi rad) measured at activation or at the first STATE after it; None =
        # not measured since activation: the segment gets a hold entry
        self.held: dict[str, tuple[float, float] | None] = dict.fromkeys(self.names)
        self.first_measured: list[str] = []  # measured for the first time in the last read()
        self.missing = [0] * len(self.names)  # consecutive cycles without a STATE, per position
        self.extra_states: list[dict] = []  # STATEs from positions beyond the known chain
        self.gap_cycles = max(1, int(gap_cycles))
        self.gaps = 0  # segments that lost their command after a gap (count)
        self.probe_extra = 0  # positions beyond the tip the next SYNC waits for (0 = none)
        self.exchange_s = 0.0  # how long the last exchange waited for its states (s)
        # how long after its reply time the last exchange's wait returned (s): the link's
        # ``wait_overrun_s``; None for a link that does not measure it (exchange_s says then)
        self.wait_overrun_s: float | None = None
        self.exchange_probed = False  # the last exchange waited for positions beyond the tip
        self.exchanges = 0
        self.resume_pending = False  # next SYNCs carry "resume" until no segment reports HOLD
        self._pending: list[dict | None] | None = None
        self.pipeline = bool(pipeline)
        self._inflight: Any = None  # the pipelined SYNC whose STATEs the next write() collects

    # -- lifecycle ---------------------------------------------------------------------------
    def configure(self) -> None:
        """unconfigured → inactive: read the segments once so state interfaces hold real values."""
        if self.state != UNCONFIGURED:
            raise LifecycleError(f"configure: HWI is {self.state}, expected {UNCONFIGURED}")
        self._pending = self.link.heartbeat(timeout=max(self.reply_timeout, 0.05))
        self.state = INACTIVE
        self.read()

    def activate(self) -> None:
        """inactive → active. Commands start at the measured state, so activation never jumps."""
        if self.state != INACTIVE:
            raise LifecycleError(f"activate: HWI is {self.state}, expected {INACTIVE}")
        self.first_measured = []
        for i, name in enumerate(self.names):
            st = self.raw_states[i]
            self.held[name] = None
            if st is not None:
                self._adopt_measured(name, st)
        self.resume_pending = True  # segments may be holding (HOLD before a rebuild): resume
        self.state = ACTIVE

    def _adopt_measured(self, name: str, st: dict) -> None:
        """Start commanding ``name`` at its measured state (activation never jumps)."""
        kappa, phi = float(st["kappa"]), float(st["phi"])
        self.held[name] = (kappa, phi)
        if f"{name}/kappa" in self.command:
            self.command[f"{name}/kappa"] = kappa
        if f"{name}/phi" in self.command:
            self.command[f"{name}/phi"] = phi

    def deactivate(self) -> None:
        """active → inactive: setpoints stop; the segments hold the last one (and heartbeats)."""
        if self.state != ACTIVE:
            raise LifecycleError(f"deactivate: HWI is {self.state}, expected {ACTIVE}")
        self.state = INACTIVE

    def cleanup(self) -> None:
        """inactive → unconfigured: forget the states."""
        if self.state != INACTIVE:
            raise LifecycleError(f"cleanup: HWI is {self.state}, expected {INACTIVE}")
        self.state_values.clear()
        self.raw_states = [None] * len(self.names)
        self.last_states = [None] * len(self.names)
        self.state = UNCONFIGURED

    # -- interfaces --------------------------------------------------------------------------
    def command_interface_names(self) -> list[str]:
        return list(self.command)

    def state_interface_names(self) -> list[str]:
        return [f"{n}/{i}" for n, bl in self.limits.items() for i in bl.state_interfaces]

    def get_state(self, interface: str) -> float:
        if self.state == UNCONFIGURED:
            raise LifecycleError("state interfaces are readable once the HWI is configured")
        if interface not in self.state_values:
            raise KeyError(
                f"no state interface {interface!r} (have: "
                f"{', '.join(self.state_interface_names())})"
            )
        return self.state_values[interface]

    def set_command(self, interface: str, value: float) -> None:
        """Write a command interface (clamped to its declared range; a phi outside a restricted
        range to the bound nearer around the circle, ``host.limits.clamp_phi``). Needs
        ``active``."""
        if self.state != ACTIVE:
            raise LifecycleError(f"command {interface!r} refused: HWI is {self.state}, not active")
        if interface not in self.command:
            raise KeyError(f"no command interface {interface!r}")
        if not math.isfinite(value):
            raise ValueError(f"command {interface!r}: value must be finite, got {value}")
        name, _, kind = interface.rpartition("/")
        bl = self.limits[name]
        if kind == "kappa":
            value = min(max(value, 0.0), bl.kappa_max)
        elif not bl.full_circle:  # the bound nearer around the circle: never a flip of the plane
            value = clamp_phi(value, bl.phi_min, bl.phi_max, prefer=self.command.get(interface))
        self.command[interface] = value

    def set_curvature(self, name: str, kx: float, ky: float) -> None:
        """Write both interfaces of a bendable from a curvature vector (phi held at kappa = 0)."""
        kappa = math.hypot(kx, ky)
        self.set_command(f"{name}/kappa", kappa)
        if f"{name}/phi" in self.command and kappa > 1e-9:
            self.set_command(f"{name}/phi", math.atan2(ky, kx))

    def setpoints(self) -> list[tuple[float, float] | None]:
        """(kappa 1/m, phi rad) per position from the command interfaces; an interface without
        a command interface keeps its measured value; None (hold) for a segment not measured
        since activation or with no command interface."""
        out: list[tuple[float, float] | None] = []
        for name in self.names:
            held = self.held.get(name)
            k_itf, p_itf = f"{name}/kappa", f"{name}/phi"
            if held is None or (k_itf not in self.command and p_itf not in self.command):
                out.append(None)
                continue
            out.append((self.command.get(k_itf, held[0]), self.command.get(p_itf, held[1])))
        return out

    # -- cycle -------------------------------------------------------------------------------
    def read(self) -> list[dict | None]:
        """Copy the STATEs of the last exchange into the state interfaces; returns them."""
        if self.state == UNCONFIGURED:
            raise LifecycleError("read: HWI is unconfigured")
        states = self._pending
        self._pending = None
        if states is None:
            return self.raw_states
        self.first_measured = []
        n = len(self.names)
        # only a probe asks beyond the tip (a HEARTBEAT may wait for every discovered segment)
        self.extra_states = [s for s in states[n:] if s is not None] if self.exchange_probed else []
        for i in range(n):
            st = states[i] if i < len(states) else None
            if st is None:
                self.missing[i] += 1
                self.raw_states[i] = None
                name = self.names[i]
                if self.missing[i] >= self.gap_cycles and self.held[name] is not None:
                    self.held[name] = None  # a gap: hold entries until measured again
                    self.gaps += 1
                continue
            self.missing[i] = 0
            self.raw_states[i] = st
            self.last_states[i] = st
            name = self.names[i]
            if self.state == ACTIVE and self.held[name] is None:
                self._adopt_measured(name, st)
                self.first_measured.append(name)
            self.state_values[f"{name}/kappa"] = float(st["kappa"])
            self.state_values[f"{name}/phi"] = float(st["phi"])
        if self.resume_pending and not any(
            st is not None and "HOLD" in st["status"] for st in self.raw_states
        ):
            self.resume_pending = False
        return self.raw_states

    def write(self) -> None:
        """One bus exchange: SYNC with the setpoints when active, else HEARTBEAT."""
        if self.state == UNCONFIGURED:
            raise LifecycleError("write: HWI is unconfigured")
        t0 = time.perf_counter()
        self.exchange_probed = False
        if self.state == ACTIVE:
            sp = self.setpoints()
            self.exchange_probed = self.probe_extra > 0
            if self.pipeline:
                self._write_pipelined(sp)
            elif self.probe_extra > 0:
                self._pending = self.link.sync(
                    sp,
                    timeout=self.reply_timeout,
                    resume=self.resume_pending,
                    expected=len(sp) + self.probe_extra,
                )
            else:
                self._pending = self.link.sync(
                    sp, timeout=self.reply_timeout, resume=self.resume_pending
                )
        else:
            self.close_pipeline()
            self._pending = self.link.heartbeat(timeout=self.reply_timeout)
        self.exchange_s = time.perf_counter() - t0
        self.wait_overrun_s = getattr(self.link, "wait_overrun_s", None)
        self.exchanges += 1

    def _write_pipelined(self, sp: list) -> None:
        """Send this cycle's SYNC, then collect the previous one's STATEs. With no cycle open
        (the pipeline starts) nothing is collected: ``read()`` keeps the last STATEs, which are
        as old as a pipelined cycle's always are. ``exchange_probed`` says whether the
        collected SYNC waited beyond the tip."""
        sent = self.link.sync_send(
            sp, resume=self.resume_pending, expected=len(sp) + self.probe_extra
        )
        previous, self._inflight = self._inflight, (sent, self.exchange_probed)
        if previous is None:
            self.exchange_probed = False
            return
        cycle, self.exchange_probed = previous
        self._pending = self.link.sync_collect(cycle, timeout=self.reply_timeout)

    def close_pipeline(self) -> None:
        """Close the pipelined cycle still open, if any: its STATEs are not waited for (any
        that come are counted by the link as unmatched)."""
        if self._inflight is not None:
            (inflight, _probed), self._inflight = self._inflight, None
            self.link.sync_abandon(inflight)


def robot_state_from(hwi: HardwareInterface, t: float) -> RobotState:
    """The controllers' view of the last exchange: fresh STATEs are ``valid``; a segment that
    missed this cycle keeps its last known values (``known``, not ``valid``)."""
    n = len(hwi.names)
    st = RobotState.zeros(hwi.names, t)
    for i in range(n):
        s = hwi.raw_states[i]
        fresh = s is not None
        if s is None:
            s = hwi.last_states[i]  # missed this cycle: the last known values, not fresh
            if s is None:
                continue  # never measured: zeros, known=False (the HWI sends hold entries)
        kappa, phi = s["kappa"] or 0.0, s["phi"] or 0.0
        kx = s["kx"] if s["kx"] is not None else kappa * math.cos(phi)
        ky = s["ky"] if s["ky"] is not None else kappa * math.sin(phi)
        st.kx[i], st.ky[i], st.kappa[i], st.phi[i] = kx, ky, kappa, phi
        st.valid[i], st.known[i] = fresh, True
        st.t_ms[i] = s.get("t_ms")
    return st

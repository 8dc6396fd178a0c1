"""Emulated servos for the unix port: finite speed, first-order response, travel limits, faults.

Each servo follows its target with time constant ``servo_tau`` (s), never faster than
``servo_speed`` (rad/s), and stops at its travel limits (the configured range around its zero).
Faults (injected by ``UCR_FAULTS`` or PARAM_SET ``faults``), spec ``"IDX:KIND[,IDX:KIND...]"``:

* ``stuck``: the servo stops moving but still answers (the segment detects a stall);
* ``disconnected``: no reply; its position is unknown (kept at the last value read);
* ``overload``: the servo reports overload in its status and does not move;
* ``raise``: reading the servos raises an exception (an exception inside the control tick);
* ``hang``: reading the servos never returns (a hung loop, for the hardware watchdog).

Config key ``emulated_start`` (list of raw angles in rad, one per servo; default the true zero
offsets) is where the servos are at power-on: far from zero, even outside their range, to test
the first-motion rules. Travel limits stop a servo moving outwards, never pull it inwards.
``emulated_zero`` / ``emulated_direction`` (servos/emu_telemetry.py) make the physical segment
differ from its configuration: what ``ucr calibrate`` has to find.
"""

from array import array

from fxp import mulq

from servos import FAULT_NO_REPLY, FAULT_NONE, FAULT_OVERLOAD, ServoBus

_KINDS = ("none", "stuck", "disconnected", "overload", "raise", "hang")


def parse_faults(spec, n):
    """``"0:stuck,2:overload"`` -> bytearray of kind indexes per servo; ValueError if malformed."""
    kinds = bytearray(n)
    if spec is None:
        return kinds
    spec = spec.strip()
    if spec in ("", "none"):
        return kinds
    for item in spec.split(","):
        parts = item.strip().split(":")
        if len(parts) != 2:
            raise ValueError("fault item %r: expected IDX:KIND" % (item,))
        try:
            idx = int(parts[0])
        except ValueError:
            raise ValueError("fault item %r: index is not an int" % (item,)) from None
        if not 0 <= idx < n:
            raise ValueError("fault item %r: servo index out of 0..%d" % (item, n - 1))
        kind = parts[1].strip()
        if kind not in _KINDS:
            raise ValueError("fault item %r: kind must be one of %s" % (item, ", ".join(_KINDS)))
        kinds[idx] = _KINDS.index(kind)
    return kinds


def format_faults(kinds):
    """Inverse of ``parse_faults`` (canonical text; "none" when no fault)."""
    items = []
    for i in range(len(kinds)):
        if kinds[i]:
            items.append("%d:%s" % (i, _KINDS[kinds[i]]))
    return ",".join(items) if items else "none"


class EmulatedBus(ServoBus):
    """``n`` simulated servos; physics advanced in ``poll`` from the elapsed time."""

    name = "emulated"

    def __init__(self, cfg):
        ServoBus.__init__(self, cfg.n)
        si = cfg.si
        n = cfg.n
        # the physical segment: where each tendon is straight and just taut (``emulated_zero``,
        # raw rad) and which raw sense winds it in (``emulated_direction``); by default exactly
        # what config.json says (a calibrated segment). Calibration tests set them apart.
        self.true_zero = array("i", cfg.zero)
        self.true_dir = array("b", cfg.direction)
        if si.get("emulated_zero") is not None or si.get("emulated_direction") is not None:
            from servos.emu_telemetry import physical

            physical(self, si)
        self.lo = array("i", [self.true_zero[i] + cfg.min_angle[i] for i in range(n)])
        self.hi = array("i", [self.true_zero[i] + cfg.max_angle[i] for i in range(n)])
        self.true_pos = array("i", self.true_zero)  # physical angle; at the true zero, or:
        start = si.get("emulated_start")
        if start is not None:
            for i in range(n):
                self.true_pos[i] = int(start[i] * 10000.0 + (0.5 if start[i] >= 0 else -0.5))
        for i in range(n):
            self.pos[i] = self.true_pos[i]
        self.target = array("i", self.true_pos)
        self.speed = max(1, int(si["servo_speed"] * 10.0 + 0.5))  # 1e-4 rad per ms
        tau_ms = si["servo_tau"] * 1000.0
        # first-order gain per ms in Q14 (tau = 0: reach the target at the speed limit)
        self.gain = 16384 if tau_ms < 1.0 else max(1, int(16384.0 / tau_ms + 0.5))
        self.kinds = bytearray(n)
        self.last_ms = None
        self.cfg = cfg
        if si.get("emulated_ids") is not None:
            from servos.emu_telemetry import wire_ids

            wire_ids(self, cfg, si["emulated_ids"])

    def telemetry(self, i):
        from servos.emu_telemetry import telemetry  # slow path; keeps this module small

        return telemetry(self, i)

    def set_faults(self, spec):
        self.kinds = parse_faults(spec, self.n)
        return format_faults(self.kinds)

    def faults_text(self):
        return format_faults(self.kinds)

    def _send(self, targets, now_ms):
        for i in range(self.n):
            self.target[i] = targets[i]

    def _release(self):
        for i in range(self.n):
            self.target[i] = self.true_pos[i]  # limp: stays where it is

    def _refresh(self, now_ms):
        for i in range(self.n):
            if self.kinds[i] == 4:
                raise RuntimeError("injected fault: servo %d read raised" % i)
            if self.kinds[i] == 5:
                while True:  # injected fault: a hung servo read (only a watchdog gets out)
                    pass
        last = self.last_ms
        self.last_ms = now_ms
        dt = 0 if last is None else (now_ms - last) & 0x3FFFFFFF
        if dt > 1000:
            dt = 1000
        alpha = dt * self.gain
        if alpha > 16384:
            alpha = 16384
        vmax = dt * self.speed
        for i in range(self.n):
            kind = self.kinds[i]
            p = self.true_pos[i]
            if kind == 0 and self.enabled and dt:
                err = self.target[i] - p
                step = mulq(err, alpha, 14)
                if step == 0 and err != 0:
                    step = 1 if err > 0 else -1
                if step > vmax:
                    step = vmax
                elif step < -vmax:
                    step = -vmax
                q = p + step
                if step < 0 and q < self.lo[i]:  # end stop: blocks outward motion only
                    q = self.lo[i] if p >= self.lo[i] else p
                elif step > 0 and q > self.hi[i]:
                    q = self.hi[i] if p <= self.hi[i] else p
                p = q
                self.true_pos[i] = p
            if kind == 2:  # disconnected: no reply, position unknown (last read stays)
                self.fault[i] = FAULT_NO_REPLY
                continue
            self.pos[i] = p
            self.fault[i] = FAULT_OVERLOAD if kind == 3 else FAULT_NONE
        self.known = True

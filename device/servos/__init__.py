"""Servo drivers: one class per family, same interface, picked by name (``make``).

A driver owns all servos of a segment (a bus). Angles are raw servo angles in 1e-4 rad (ints),
as the servo itself sees them (the MC applies zero offset and direction). Interface:

* ``command(targets, now_ms)``: send targets (array of n ints); the first call enables output.
* ``poll(now_ms)``: refresh ``pos`` (array of n ints) and ``fault`` (bytearray of fault codes).
* ``request(now_ms)``: called at the end of every cycle (bus drivers send their read request).
* ``feedback``: True when ``pos`` is measured, False when it is the last command (open loop).
* ``known``: True once ``pos`` holds a real position for every servo (bus drivers: a present
  position was read from each; open loop: the configured rest pose). The segment commands
  nothing before (docs/firmware.md, "First motion").
* ``saturated``: True when the last ``command`` could not be output exactly (a pulse or a step
  count clipped at its end): ``pos`` then holds what was achieved, and the segment reports CLAMPED.
* ``release()``: stop driving the servos (FAULT with ``fault_action`` "release").
* ``telemetry(i)``: (V, deg C, load fraction) of servo i, None if not reported (PARAM 22).
* ``set_faults(spec)``: fault injection (emulated driver only; others raise ValueError).

Drivers are imported lazily, so a board without ``machine`` never imports the PWM/bus drivers.
"""

try:
    from micropython import const
except ImportError:  # CPython

    def const(x):
        return x


FAULT_NONE = const(0)
FAULT_NO_REPLY = const(1)  # disconnected / read timeout
FAULT_STALL = const(2)  # commanded to move, did not move (detected by the segment)
FAULT_OVERLOAD = const(3)  # servo reports overload / overcurrent
FAULT_ERROR = const(4)  # other error flag from the servo (voltage, temperature, sensor)
FAULT_RANGE = const(5)  # measured outside its configured range (detected by the segment)

FAULT_NAMES = ("none", "no_reply", "stall", "overload", "error", "out_of_range")


class ServoBus:
    """Base of all drivers: positions and faults; backends implement ``_send`` and ``_refresh``."""

    feedback = True
    name = "base"

    def __init__(self, n):
        from array import array

        self.n = n
        self.pos = array("i", [0] * n)
        self.fault = bytearray(n)
        self.enabled = False
        self.known = False
        self.saturated = False

    def command(self, targets, now_ms):
        self.enabled = True
        self._send(targets, now_ms)

    def release(self):
        """Stop driving the servos (they go limp); the next ``command`` drives them again."""
        self.enabled = False
        self._release()

    def _release(self):
        pass

    def poll(self, now_ms):
        self._refresh(now_ms)

    def request(self, now_ms):
        """End of a cycle: ask the servos for fresh feedback (bus drivers); default nothing."""

    def telemetry(self, i):
        """(voltage V, temperature deg C, load fraction of max torque) of servo ``i``, or None
        when the servo does not report them (PWM, offline). Slow path: allocates."""
        return None

    def set_faults(self, spec):
        raise ValueError("fault injection is only available on the emulated driver")

    def _send(self, targets, now_ms):
        raise NotImplementedError

    def _refresh(self, now_ms):
        raise NotImplementedError


def make(name, cfg, hal):
    """Build the driver called ``name`` for configuration ``cfg`` on ``hal``."""
    if name == "emulated":
        from servos.emulated import EmulatedBus

        return EmulatedBus(cfg)
    if name == "pwm":
        from servos.pwm import PwmBus

        return PwmBus(cfg, hal)
    if name in ("feetech_sts", "feetech_scs"):
        from servos.feetech import FeetechBus

        return FeetechBus(cfg, hal, name == "feetech_scs")
    raise ValueError("unknown servo driver %r" % (name,))


class OfflineBus(ServoBus):
    """Stand-in when the configured driver cannot start: every servo reports NO_REPLY.

    The segment then stays in hold with SERVO_FAULT but keeps forwarding frames, so one broken
    segment never cuts the chain.
    """

    feedback = False
    name = "offline"

    def __init__(self, n, reason):
        ServoBus.__init__(self, n)
        self.reason = reason
        for i in range(n):
            self.fault[i] = FAULT_NO_REPLY

    def _send(self, targets, now_ms):
        pass

    def _refresh(self, now_ms):
        pass

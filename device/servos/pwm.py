"""Hobby PWM servos (ESP32, open loop): raw angle -> pulse width, 50 Hz.

Calibration (config key ``pwm``, all optional): ``pins`` (GPIO per servo, default 25, 26, 27),
``freq`` (Hz, 50), ``min_us``/``max_us`` (pulse at the ends of the travel, 500/2500),
``range`` (rad of travel between min_us and max_us, pi). Raw angle 0 is the centre pulse.
Position "feedback" is the last command as output (``feedback = False``: no stall or fault
detection). A hobby servo cannot say where it is, so at power-on it is assumed at its configured
rest pose (servo key ``rest_angle``, rad from zero, inside [min_angle, max_angle]; checked by
config.py and ``ucr check``): the first pulse goes there, and motion starts from it slew-limited.
No pulse is output before the first command, so the servos stay limp in the boot hold. After
``release`` (pulses off: FAULT with ``fault_action`` "release", Ctrl-C) a limp servo may be
moved by hand or by its tendon, so its last command says nothing any more: it is assumed at its
rest pose again, as at power-on (``_assume_rest``), and the next motion starts there.
A target beyond the pulse range is output at min_us/max_us: ``pos`` holds the angle actually
output and ``saturated`` is set, so the segment reports CLAMPED and the achieved curvature.
"""

from array import array

from servos import ServoBus

_DEFAULT = {"pins": [25, 26, 27], "freq": 50, "min_us": 500, "max_us": 2500, "range": 3.14159265}


class PwmBus(ServoBus):
    feedback = False
    name = "pwm"

    def __init__(self, cfg, hal):
        ServoBus.__init__(self, cfg.n)
        p = dict(_DEFAULT)
        if cfg.si.get("pwm"):
            p.update(cfg.si["pwm"])
        pins = p["pins"]
        if len(pins) < cfg.n:
            raise ValueError("pwm.pins lists %d pins for %d servos" % (len(pins), cfg.n))
        if not (0 < p["min_us"] < p["max_us"] < 20000) or p["range"] <= 0:
            raise ValueError("pwm calibration: need 0 < min_us < max_us < 20000 and range > 0")
        if p["max_us"] - p["min_us"] > 4000:
            raise ValueError("pwm calibration: max_us - min_us must be at most 4000")
        self.freq = int(p["freq"])
        self.centre_ns = int((p["min_us"] + p["max_us"]) * 500)
        self.min_ns = int(p["min_us"] * 1000)
        self.max_ns = int(p["max_us"] * 1000)
        ns_per_e4 = (p["max_us"] - p["min_us"]) * 1000.0 / (p["range"] * 10000.0)
        # ns = centre + raw * ns_per_e4 with the slope in 1/256 ns and raw first limited to half
        # the range: |raw * slope| <= (max_us - min_us) * 1000 / 2 * 256 <= 5.2e8 < 2**30
        self.half = int(p["range"] * 5000.0)
        self.k256 = int(ns_per_e4 * 256.0 + 0.5)
        self.pins = pins
        self.pwm = None
        self.hal = hal
        self.rest = array("i", [cfg.zero[i] + cfg.rest[i] for i in range(cfg.n)])
        self._assume_rest()
        self.known = True
        self.pulse_ns = array("i", [self.centre_ns] * cfg.n)

    def _outputs(self):
        """The PWM outputs, made at the first command (no pulses during the boot hold). A method
        of its own: a comprehension in ``_send`` would make ``self`` a closure cell there, a heap
        allocation on every command."""
        self.pwm = [self.hal.pwm(pin, self.freq) for pin in self.pins[: self.n]]

    def command(self, targets, now_ms):
        # ServoBus.command with _send in it (a call less per tick); attributes bound once
        self.enabled = True
        if self.pwm is None:
            self._outputs()
        h = self.half
        centre = self.centre_ns
        k256 = self.k256
        lo = self.min_ns
        hi = self.max_ns
        pulse = self.pulse_ns
        pwm = self.pwm
        pos = self.pos
        sat = False
        for i in range(self.n):
            raw = targets[i]
            if raw > h:
                raw = h
                sat = True
            elif raw < -h:
                raw = -h
                sat = True
            ns = centre + ((raw * k256 + 128) >> 8)
            if ns < lo:
                ns = lo
            elif ns > hi:
                ns = hi
            pulse[i] = ns
            pwm[i].duty_ns(ns)
            pos[i] = raw  # what the pulse asks for: the achieved angle
        self.saturated = sat

    def _send(self, targets, now_ms):
        self.command(targets, now_ms)  # (ServoBus's contract; command does it all)

    def poll(self, now_ms):
        pass  # open loop: pos is the last command, no faults observable (no _refresh call)

    def _assume_rest(self):
        """Where an undriven servo is assumed: its configured rest pose, inside [min, max]
        (docs/firmware.md "First motion"); at power-on and after every release."""
        for i in range(self.n):
            self.pos[i] = self.rest[i]

    def _release(self):
        if self.pwm is not None:
            for p in self.pwm:
                p.duty_ns(0)  # no pulses: the servos go limp
        self._assume_rest()  # the last command is no position any more

    def _refresh(self, now_ms):
        pass  # open loop: pos is the last command, no faults observable

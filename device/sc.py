"""Simple controllers (SC): one per servo, turning the MC's servo target into the servo command.

The strategy is a swappable object with ``step(target, cmd) -> new cmd`` (ints, 1e-4 rad):

* ``Direct``: command = target (the servo's own position loop does the work);
* ``PSlew``: command moves towards the target by gain * error per cycle: a soft approach.

Whatever the strategy, a command never moves more than the servo's speed allows per cycle
(``servo_speed`` rad/s * cycle time) from the previous one. The commands restart from the measured
positions after every hold, so motion always begins where the servos are: when a start or resume
finds them away from where the curvature model puts them (uneven power-up angles, a stuck servo),
they travel there at servo speed instead of jumping in one tick.

Chosen by config key ``sc`` and switchable at run time (PARAM_SET ``sc``). Allocation-free.
"""

from array import array

from fxp import mulq

STRATEGIES = ("direct", "p_slew")


class Direct:
    name = "direct"

    def step(self, target, cmd):
        return target


class PSlew:
    """cmd += clamp(gain * (target - cmd), +-max_step); gain Q14, max_step 1e-4 rad per cycle."""

    name = "p_slew"

    def __init__(self, gain, max_step):
        self.gain = max(1, min(16384, int(gain * 16384 + 0.5)))
        self.max_step = max(1, int(max_step))

    def step(self, target, cmd):
        err = target - cmd
        d = mulq(err, self.gain, 14)
        if d == 0 and err != 0:
            d = 1 if err > 0 else -1
        m = self.max_step
        if d > m:
            d = m
        elif d < -m:
            d = -m
        return cmd + d


class SimpleControllers:
    """The n SCs of a segment; ``cmd`` holds the last command per servo."""

    def __init__(self, n, name, gain, servo_speed, tick_ms):
        self.n = n
        self.cmd = array("i", [0] * n)
        self.gain = gain
        self.max_step = servo_speed * 10.0 * tick_ms  # rad/s -> 1e-4 rad per cycle
        self.step_limit = max(1, int(self.max_step))
        self.strategies = [None] * n
        self.set_strategy(name)

    def set_strategy(self, name):
        """Swap every servo's strategy (slow path); ValueError for an unknown name."""
        if name == "direct":
            s = [Direct() for _ in range(self.n)]
        elif name == "p_slew":
            s = [PSlew(self.gain, self.max_step) for _ in range(self.n)]
        else:
            raise ValueError("sc strategy must be one of %s" % ", ".join(STRATEGIES))
        self.strategies = s
        self.name = name

    def reset(self, positions):
        """Start from the given positions (after a hold)."""
        for i in range(self.n):
            self.cmd[i] = positions[i]

    def step(self, targets):
        lim = self.step_limit
        cmd = self.cmd
        direct = self.name == "direct"  # command = target: no strategy call per servo
        strategies = self.strategies
        for i in range(self.n):
            c = cmd[i]
            nc = targets[i] if direct else strategies[i].step(targets[i], c)
            if nc - c > lim:
                nc = c + lim
            elif c - nc > lim:
                nc = c - lim
            cmd[i] = nc
        return cmd

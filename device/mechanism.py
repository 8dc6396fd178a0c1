"""Mechanism controller (MC): curvature <-> tendon lengths <-> servo angles, in fixed point.

Forward: (kappa, phi) -> (kx, ky) = kappa (cos phi, sin phi) -> tendon lengths
l_i = l (1 - d (kx cos s_i + ky sin s_i)) -> spool angle -dl_i / r_spool -> servo target
zero_i + dir_i * angle_i, clamped to the servo's range. Backward: servo positions -> tendon lengths
-> (kx, ky) by the least-squares inverse of the n-tendon map (pseudo-inverse precomputed at boot)
-> kappa (projection on the atan2 direction) and phi (held when kappa is about zero).

Limits: |kappa| <= kappa_max, servo targets within range, and the curvature *vector* moves at most
kappa_rate_max * dt per cycle. A setpoint is reported as rate-clamped only when it asks for more
than kappa_rate_max allows since the previous setpoint (so a host stepping at 100 Hz within the
rate never trips it, although each step takes the 200 Hz limiter two ticks).
Units: curvature 1e-4 1/m, angles 1e-4 rad, lengths um (ints).
Nothing here allocates after ``__init__`` (arrays are preallocated; all ints stay below 2**30).
"""

try:
    from micropython import const
except ImportError:  # CPython

    def const(x):
        return x


from array import array

import fxp
from fxp import atan2_e4, cos_q20, mulq, sin_q20

CLAMP_KAPPA = const(1)  # LIMIT_CLAMPED detail bits (contract)
CLAMP_RATE = const(2)
CLAMP_SERVO = const(4)
_PHI_HOLD_EPS = const(10)  # 1e-3 1/m: below this measured kappa, phi keeps its last value
_RATE_WINDOW_MS = const(100)  # longest setpoint interval credited to the rate check
_MAX_DL_UM = const(1 << 23)  # largest tendon length change the fixed-point scheme allows
_KAPPA_WIRE = const(1 << 23)  # 1e-4 1/m: STATE's kappa is an int24 (docs/protocol.md)
RANGE_TOL = const(500)  # 0.05 rad: a servo measured this far outside its range is faulty
_MEAS_SLACK = const(10000)  # 1 rad: how far outside its range a measured joint angle is used


class Mechanism:
    """Fixed-point MC of one segment; ``cfg`` is a ``config.Config``, ``tick_ms`` the cycle time."""

    def __init__(self, cfg, tick_ms):
        import math

        si = cfg.si
        n = cfg.n
        self.n = n
        self.length_um = cfg.length_um
        self.kappa_max = cfg.kappa_max
        # slew step per cycle (1e-4 1/m), at least one unit
        self.tick_ms = tick_ms
        self.set_rate_max(cfg.rate_max)
        self.rate_excess = False  # the current target was requested faster than the rate allows
        ld = si["length"] * si["tendon_radius"]
        if ld * si["kappa_max"] * 1e6 > _MAX_DL_UM:
            raise ValueError("length * tendon_radius * kappa_max too large for fixed point")
        sig = [float(a) for a in si["tendon_angles"]]
        # tendon map: dl_i [um] = -(A_i kx + B_i ky), kx in 1e-4 1/m -> A_i = l d cos(s_i) * 100
        ca = [ld * 100.0 * math.cos(s) for s in sig]
        cb = [ld * 100.0 * math.sin(s) for s in sig]
        self.q_t = fxp.q_for(ca + cb)
        self.ta = array("i", [fxp.to_q(c, self.q_t) for c in ca])
        self.tb = array("i", [fxp.to_q(c, self.q_t) for c in cb])
        # least-squares inverse: P = (M^T M)^-1 M^T with rows M_i = (cos s_i, sin s_i)
        sxx = sum(math.cos(s) ** 2 for s in sig)
        syy = sum(math.sin(s) ** 2 for s in sig)
        sxy = sum(math.cos(s) * math.sin(s) for s in sig)
        det = sxx * syy - sxy * sxy
        if abs(det) < 1e-6:
            raise ValueError("tendon_angles are degenerate: curvature is not observable")
        px = [(syy * math.cos(s) - sxy * math.sin(s)) / det for s in sig]
        py = [(sxx * math.sin(s) - sxy * math.cos(s)) / det for s in sig]
        # kx [1e-4 1/m] = sum_i Px_i / (l d 100) * (-dl_i [um])
        kx = [p / (ld * 100.0) for p in px]
        ky = [p / (ld * 100.0) for p in py]
        try:
            self.q_i = fxp.q_for(kx + ky)
        except ValueError:
            raise ValueError(
                "length * tendon_radius = %.3g m^2 is too small for the fixed-point curvature "
                "map (needs >= %.2g m^2 for these tendon angles)"
                % (ld, max(abs(c) for c in kx + ky) * ld / ((1 << 21) >> 12))
            ) from None
        self.ix = array("i", [fxp.to_q(c, self.q_i) for c in kx])
        self.iy = array("i", [fxp.to_q(c, self.q_i) for c in ky])
        # spool: angle [1e-4 rad] = -dl [um] / (100 r); back: dl [um] = -angle * 100 r
        r = si["spool_radius"]
        self.q_s = fxp.q_for([1.0 / (100.0 * r)])
        self.spool_fwd = fxp.to_q(1.0 / (100.0 * r), self.q_s)
        self.q_b = fxp.q_for([100.0 * r])
        self.spool_back = fxp.to_q(100.0 * r, self.q_b)
        self.zero = array("i", cfg.zero)
        self.dir = array("b", cfg.direction)
        self.amin = array("i", cfg.min_angle)
        self.amax = array("i", cfg.max_angle)
        # measure() clamps each joint angle to its range +- _MEAS_SLACK, so a servo read far
        # outside it (a fault, reported by the segment) cannot overflow the integer path
        self.mlo = array("i", [a - _MEAS_SLACK for a in cfg.min_angle])
        self.mhi = array("i", [a + _MEAS_SLACK for a in cfg.max_angle])
        reach = max(max(-self.mlo[i], self.mhi[i]) for i in range(n))  # 1e-4 rad
        dl_um = reach * 100.0 * r
        k_worst = dl_um * max(sum(abs(c) for c in kx), sum(abs(c) for c in ky))
        # |(sx, sy)| <= sqrt(2) * k_worst: the measured curvature must fit STATE's int24 (what
        # the host is told; it wrapped, sign and all, beyond it) and fxp.mulq's input (< 2**24)
        if dl_um >= 1 << 23 or k_worst * 1.4143 >= _KAPPA_WIRE:
            raise ValueError(
                "servo travel (+-%.4g rad) too large for this geometry: the measured curvature "
                "could reach %.4g 1/m, beyond what STATE reports (%.4g 1/m)"
                % (reach * 1e-4, k_worst * 1.4143e-4, _KAPPA_WIRE * 1e-4)
            )
        # state (all ints / preallocated arrays)
        self.tx = 0  # target curvature vector after kappa clamp (1e-4 1/m)
        self.ty = 0
        self.cx = 0  # commanded curvature vector after the slew limit
        self.cy = 0
        self.servo_target = array("i", [0] * n)  # raw servo angles (1e-4 rad)
        self.tendon_cmd = array("i", [0] * n)  # commanded tendon lengths (um)
        self.tendon = array("i", [0] * n)  # measured tendon lengths (um)
        self.joint = array("i", [0] * n)  # measured spool angles dir*(raw-zero) (1e-4 rad)
        self.mx = 0  # measured curvature vector
        self.my = 0
        self.kappa = 0  # measured kappa, phi
        self.phi = 0

    def set_rate_max(self, rate):
        """kappa_rate_max in 1e-4 1/m per s: the slew step per tick and the setpoint rate check.

        The step is rate * tick in 1e-4 1/m: its whole part every tick, and the fraction (in
        thousandths) carried from tick to tick, so the slew never runs faster than the rate,
        however small (rounding it to whole units made 0.03 1/m/s slew at 0.04 and the config's
        0.001 at 0.02). ``step`` (rounded up) is the setpoint rate check's one-tick allowance."""
        per_tick = rate * self.tick_ms  # 1e-7 1/m: thousandths of a unit
        self.step_whole = per_tick // 1000
        self.step_frac = per_tick % 1000
        self.step_acc = 0
        self.step = self.step_whole + (1 if self.step_frac else 0)
        # rate check of setpoints: 1.25 * rate per ms in Q4 (1e-4 1/m / 16 per ms); with
        # dt <= 100 ms the product stays far below 2**30 for any accepted kappa_rate_max
        self.rate_q4 = (rate * 16 * 5) // 4000

    def set_kappa_max(self, kappa_max):
        """New curvature bound (1e-4 1/m), applied to the current target too: the commanded
        vector then slews down to it at the rate limit instead of staying beyond it."""
        self.kappa_max = kappa_max
        tx = self.tx
        ty = self.ty
        if tx or ty:
            psi = atan2_e4(ty, tx)
            c = cos_q20(psi)
            s = sin_q20(psi)
            if mulq(tx, c, 20) + mulq(ty, s, 20) > kappa_max:
                self.tx = mulq(kappa_max, c, 20)
                self.ty = mulq(kappa_max, s, 20)

    # ---- forward ---------------------------------------------------------------------------
    def set_target(self, kappa, phi, dt_ms=-1):
        """Take a (kappa, phi) setpoint (ints) arriving ``dt_ms`` after the previous one.

        Returns CLAMP_KAPPA if |kappa| was limited, and CLAMP_RATE if the curvature vector moved
        further than kappa_rate_max * dt_ms (+ one tick, + 25 %) from the previous target. Without
        ``dt_ms`` there is no rate judgement here: update() then flags every tick it limits.
        """
        flags = 0
        # bound everything before arithmetic: wire ints reach +-2**30, and 2**30 itself (or more)
        # is not a small int on a 32-bit MCU (it would allocate)
        if phi > 1000000000 or phi < -1000000000:
            phi = 0  # nonsense from the wire; kappa magnitude is bounded below
        if kappa > self.kappa_max:
            kappa = self.kappa_max
            flags = CLAMP_KAPPA
        elif kappa < -self.kappa_max:
            kappa = -self.kappa_max
            flags = CLAMP_KAPPA
        if kappa < 0:
            kappa = -kappa
            phi += fxp.ANGLE_PI
        tx = mulq(kappa, cos_q20(phi), 20)
        ty = mulq(kappa, sin_q20(phi), 20)
        if dt_ms < 0:
            self.tx = tx
            self.ty = ty
            self.rate_excess = True
            return flags
        if dt_ms > _RATE_WINDOW_MS:
            dt_ms = _RATE_WINDOW_MS
        allowed = self.step + ((self.rate_q4 * dt_ms) >> 4)  # one tick + 25 % slack for jitter
        dx = tx - self.tx
        dy = ty - self.ty
        if dx > allowed or dx < -allowed or dy > allowed or dy < -allowed:
            self.rate_excess = True  # beyond the box: certainly beyond the disc
        elif dx or dy:
            psi = atan2_e4(dy, dx)
            self.rate_excess = mulq(dx, cos_q20(psi), 20) + mulq(dy, sin_q20(psi), 20) > allowed
        self.tx = tx
        self.ty = ty
        if self.rate_excess:
            flags |= CLAMP_RATE
        return flags

    def update(self):
        """One cycle: slew (kx, ky) towards the target, compute servo targets; return clamp bits."""
        if _fast:
            return _fast.update(self)  # all of it in machine code
        flags = 0
        dx = self.tx - self.cx
        dy = self.ty - self.cy
        st = self.step_whole  # this tick's step: the whole part plus the carried fraction
        acc = self.step_acc + self.step_frac
        if acc >= 1000:
            acc -= 1000
            st += 1
        h = st >> 1
        if -h <= dx <= h and -h <= dy <= h:
            self.cx = self.tx
            self.cy = self.ty
            acc = 0  # at the target: nothing carried into the next move
        else:
            psi = atan2_e4(dy, dx)
            c = cos_q20(psi)
            s = sin_q20(psi)
            mag = mulq(dx, c, 20) + mulq(dy, s, 20)
            if mag <= st:
                self.cx = self.tx
                self.cy = self.ty
                acc = 0
            else:
                self.cx += mulq(st, c, 20)
                self.cy += mulq(st, s, 20)
                if self.rate_excess:
                    flags = CLAMP_RATE
        self.step_acc = acc
        if self.cx == self.tx and self.cy == self.ty:
            self.rate_excess = False
        return flags | self._servo_targets()

    def _servo_targets(self):
        if _fast:
            return _fast.servo_targets(self)  # the loop below in machine code
        flags = 0
        cx = self.cx
        cy = self.cy
        qt = self.q_t
        qs = self.q_s
        ta = self.ta
        tb = self.tb
        for i in range(self.n):
            dl = -(mulq(cx, ta[i], qt) + mulq(cy, tb[i], qt))
            self.tendon_cmd[i] = self.length_um + dl
            a = mulq(-dl, self.spool_fwd, qs)  # spool angle, + = tendon wound in
            rel = a if self.dir[i] > 0 else -a
            if rel < self.amin[i]:
                rel = self.amin[i]
                flags = CLAMP_SERVO
            elif rel > self.amax[i]:
                rel = self.amax[i]
                flags = CLAMP_SERVO
            self.servo_target[i] = self.zero[i] + rel
        return flags

    # ---- backward --------------------------------------------------------------------------
    def measure(self, positions):
        """Servo positions (raw, 1e-4 rad, array) -> tendon lengths, (kx, ky), kappa, phi."""
        if _fast:
            _fast.measure(self, positions)  # all of it in machine code
            return
        qb = self.q_b
        qi = self.q_i
        sx = 0
        sy = 0
        for i in range(self.n):
            rel = positions[i] - self.zero[i]
            if rel < self.mlo[i]:
                rel = self.mlo[i]
            elif rel > self.mhi[i]:
                rel = self.mhi[i]
            a = rel if self.dir[i] > 0 else -rel
            self.joint[i] = a
            dl = -mulq(a, self.spool_back, qb)
            self.tendon[i] = self.length_um + dl
            sx += mulq(-dl, self.ix[i], qi)
            sy += mulq(-dl, self.iy[i], qi)
        self.mx = sx
        self.my = sy
        if -_PHI_HOLD_EPS < sx < _PHI_HOLD_EPS and -_PHI_HOLD_EPS < sy < _PHI_HOLD_EPS:
            # about straight: kappa from the larger component, phi held
            ax = sx if sx >= 0 else -sx
            ay = sy if sy >= 0 else -sy
            self.kappa = ax if ax > ay else ay
            return
        phi = atan2_e4(sy, sx)
        self.kappa = mulq(sx, cos_q20(phi), 20) + mulq(sy, sin_q20(phi), 20)
        self.phi = phi

    def hold_here(self, positions):
        """Stop where the mechanism is: targets := measured servo positions and curvature.

        A servo read further outside its range [zero + min, zero + max] than ``RANGE_TOL`` (the
        segment calls that a fault: a servo pushed away, or one bad reply that passed its
        checksum) keeps its last target instead, clamped to the range: holding at the reading
        would command the servo there in one step (review 2026-11-26)."""
        self.measure(positions)
        self.tx = self.cx = self.mx
        self.ty = self.cy = self.my
        self.rate_excess = False
        self.step_acc = 0
        for i in range(self.n):
            lo = self.zero[i] + self.amin[i]
            hi = self.zero[i] + self.amax[i]
            p = positions[i]
            if p < lo - RANGE_TOL or p > hi + RANGE_TOL:
                p = self.servo_target[i]
                if p < lo:
                    p = lo
                elif p > hi:
                    p = hi
            self.servo_target[i] = p


# The per-servo loops in machine code where fxp uses fxp_fast (a native emitter): mech_fast.py,
# the same integers (tests/device/test_fast_paths.py); elsewhere the loops above.
_fast = None
if fxp.mulq is not fxp._plain[0]:
    try:
        import mech_fast as _fast
    except Exception:  # a MemoryError compiling it from source (`ucr flash --source`)
        _fast = None

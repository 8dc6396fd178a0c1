"""The configuration hash (DESCRIPTOR key 17, docs/protocol.md 0x89 CALIBRATION), on its own.

A small module on purpose: the segment computes the hash at its first DISCOVER, when the heap may
be tight, so it compiles only this. ``protocol/calibration.py`` re-exports both functions.
"""

from protocol.constants import DEFAULT_KAPPA_RATE_MAX

_HASH_MASK = 0x3FFFFFFF  # 30 bits: every wire int stays below 2**30
# The safety keys and the firmware's defaults for them (device/config.py DEFAULTS): hashed only
# where a configuration differs from the default, so one without them (as every configuration
# flashed before they existed) keeps its hash.
_SAFETY = (("watchdog_ms", 200), ("tick_ms", 5), ("hw_watchdog_ms", 0), ("fault_action", "hold"))


def _q(x, scale):
    """Round ``x * scale`` half away from zero (same result on float32 and float64 for values
    given to the scale's resolution, which is what the tools write)."""
    v = float(x) * scale
    return int(v + 0.5) if v >= 0 else -int(-v + 0.5)


def config_text(cfg):
    """Canonical text of the hashed part of a configuration dict (config.json keys, SI).

    Lengths in um, angles in 1e-4 rad, curvature in 1e-4 1/m; servos with the firmware's defaults
    filled in (id = index, zero 0, direction 1, range -pi..pi); then the safety keys (watchdog,
    tick, hardware watchdog in whole ms; fault action) that differ from the firmware's defaults."""
    rate = cfg.get("kappa_rate_max")
    if rate is None:
        rate = DEFAULT_KAPPA_RATE_MAX
    angles = cfg.get("tendon_angles") or []
    parts = [
        "l%d" % _q(cfg.get("length", 0.0), 1000000),
        "a" + ",".join(["%d" % _q(a, 10000) for a in angles]),
        "r%d" % _q(cfg.get("tendon_radius", 0.0), 1000000),
        "s%d" % _q(cfg.get("spool_radius", 0.0), 1000000),
        "k%d" % _q(cfg.get("kappa_max", 0.0), 10000),
        "v%d" % _q(rate, 10000),
        "d%s" % (cfg.get("servo_driver") or ""),
    ]
    servos = cfg.get("servos") or [{} for _ in angles]
    for i in range(len(servos)):
        s = servos[i]
        parts.append(
            "i%d,%d,%d,%d,%d"
            % (
                s.get("id", i),
                _q(s.get("zero_offset", 0.0), 10000),
                s.get("direction", 1),
                _q(s.get("min_angle", -3.141592653589793), 10000),
                _q(s.get("max_angle", 3.141592653589793), 10000),
            )
        )
    for key, default in _SAFETY:
        v = cfg.get(key)
        if v is not None and v != default:
            parts.append("%s=%s" % (key, v) if isinstance(v, str) else "%s=%d" % (key, _q(v, 1)))
    return ";".join(parts)


def config_hash(cfg):
    """30-bit FNV-1a of ``config_text(cfg)``."""
    h = 0x811C9DC5
    for b in config_text(cfg).encode():
        h = ((h ^ b) * 0x01000193) & 0xFFFFFFFF
    return h & _HASH_MASK

"""Telemetry of the emulated servos (PARAM 22), as a Feetech servo reports it.

Config keys (docs/firmware.md): ``emulated_voltage`` (V, default 12.0), ``emulated_temperature``
(deg C per servo, default 30.0), ``emulated_load_per_rad`` (default 0.5): the load, a fraction
of max torque, rises with tendon tension, i.e. with how far the servo is from its zero (rad).
``emulated_ids`` (the bus ids the emulated servos really have, a list) models a missing, wrong
or duplicate id: a configured servo whose id is absent from it, or present twice (two servos
answer at once: a garbled reply), never answers.
Its own module so that the driver compiled at boot stays small (slow path only).
"""


def telemetry(bus, i):
    """(voltage V, temperature deg C, load fraction capped at 1.0) of servo i; None if it is
    disconnected (no reply, nothing reported)."""
    if bus.kinds[i] == 2:
        return None
    si = bus.cfg.si
    v = _num(si, "emulated_voltage", 12.0)
    k = _num(si, "emulated_load_per_rad", 0.5)
    t = si.get("emulated_temperature")
    if t is None:
        t = [30.0] * bus.n
    if not isinstance(t, list) or len(t) != bus.n:
        raise ValueError("emulated_temperature must list one value (deg C) per servo")
    temp = _num({"t": t[i]}, "t", 30.0)
    load = abs(bus.true_pos[i] - bus.cfg.zero[i]) / 10000.0 * k
    return (v, temp, min(1.0, load))


def _num(si, key, default):
    """si[key] as a float (default if absent); ValueError unless a number -50..200."""
    v = si.get(key)
    if v is None:
        return default
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not -50 <= v <= 200:
        raise ValueError("%s: bad value %r" % (key, v))
    return float(v)


def wire_ids(bus, cfg, ids):
    """Mark each configured servo that cannot answer on a bus with these ``ids`` disconnected."""
    if not isinstance(ids, list) or len(ids) != bus.n:
        raise ValueError("emulated_ids must list one bus id per servo")
    for i in range(bus.n):
        if ids.count(cfg.servo_ids[i]) != 1:
            bus.kinds[i] = 2

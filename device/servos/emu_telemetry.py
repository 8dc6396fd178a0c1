"""Telemetry of the emulated servos (PARAM 22), as a Feetech servo reports it.

Config keys (docs/firmware.md): ``emulated_voltage`` (V, default 12.0), ``emulated_temperature``
(deg C per servo, default 30.0), ``emulated_load_per_rad`` (default 0.5): the load, a fraction
of max torque, rises with tendon tension: ``k * max(0, pull + emulated_pretension)`` where pull
(rad) is how far the servo has wound its tendon in from the physical zero (``emulated_zero``, raw
rad per servo, in the sense ``emulated_direction``; both default to config.json's calibration)
and ``emulated_pretension`` (rad, default 0) the tension it was built with. An unwound tendon
goes slack: no load. Each tendon is modelled on its own (a simplification: real tendons share
the backbone's bend), which is enough to find its direction and its taut point.
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
    pre = _num(si, "emulated_pretension", 0.0)
    pull = bus.true_dir[i] * (bus.true_pos[i] - bus.true_zero[i]) / 10000.0
    load = k * (pull + pre)
    return (v, temp, min(1.0, max(0.0, load)))


def physical(bus, si):
    """Set the physical zero (``emulated_zero``, rad) and winding sense (``emulated_direction``)
    of every servo; ValueError unless one value per servo."""
    z = si.get("emulated_zero")
    if z is not None:
        if not isinstance(z, list) or len(z) != bus.n:
            raise ValueError("emulated_zero must list one raw angle (rad) per servo")
        for i in range(bus.n):
            a = _num({"z": z[i]}, "z", 0.0)
            bus.true_zero[i] = int(a * 10000.0 + (0.5 if a >= 0 else -0.5))
    d = si.get("emulated_direction")
    if d is not None:
        if not isinstance(d, list) or len(d) != bus.n or any(x not in (1, -1) for x in d):
            raise ValueError("emulated_direction must list 1 or -1 per servo")
        for i in range(bus.n):
            bus.true_dir[i] = d[i]


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

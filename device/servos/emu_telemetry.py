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
    t = si.get("emulated_temperature")
    k = si.get("emulated_load_per_rad")
    load = abs(bus.true_pos[i] - bus.cfg.zero[i]) / 10000.0 * (0.5 if k is None else k)
    return (si.get("emulated_voltage") or 12.0, t[i] if t else 30.0, min(1.0, load))


def wire_ids(bus, cfg, ids):
    """Mark each configured servo that cannot answer on a bus with these ``ids`` disconnected."""
    if not isinstance(ids, list):
        raise ValueError("emulated_ids must be a list of bus ids")
    for i in range(bus.n):
        if ids.count(cfg.servo_ids[i]) != 1:
            bus.kinds[i] = 2

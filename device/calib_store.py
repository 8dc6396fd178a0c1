"""Slow path: the segment's stored calibration file (``calibration.json``), its own module.

Read at boot by ``config.load`` (``merge``) when the file exists, written by CALIBRATE persist
(``write_file``: temp file, then rename, so a power cut leaves the old file or the new one).
Kept apart from ``calib.py`` so each compiles in a small heap (docs/firmware.md, "Calibration").
"""

import os

from protocol import cal_core as cal

FILE = "calibration.json"
_TMP = "calibration.tmp"


def read_file(path=FILE):
    """The stored calibration as (zeros, dirs), None if there is none; ValueError if invalid."""
    import json

    try:
        with open(path) as f:
            text = f.read()
    except OSError:
        return None
    try:
        d = json.loads(text)
    except ValueError:
        raise ValueError("not JSON") from None
    if not isinstance(d, dict) or d.get("version") != cal.CAL_VERSION:
        raise ValueError("version must be %d" % cal.CAL_VERSION)
    servos = d.get("servos")
    if not isinstance(servos, list):
        raise ValueError("servos must be a list")
    zeros = []
    dirs = []
    for s in servos:
        if not isinstance(s, dict):
            raise ValueError("each servo must be an object")
        zeros.append(s.get("zero_offset"))
        dirs.append(s.get("direction"))
    why = cal.check_values(zeros, dirs, len(servos))
    if why:
        raise ValueError(why)
    return zeros, dirs


def check_shift(base, zeros):
    """None if no zero moves more than MAX_SHIFT rad from config.json's ``base``, else why."""
    for i in range(len(zeros)):
        if abs(zeros[i] - base[i]) > cal.MAX_SHIFT:
            return (
                "servo %d: zero offset %.4f rad is more than %.1f rad from config.json's %.4f"
                % (
                    i,
                    zeros[i],
                    cal.MAX_SHIFT,
                    base[i],
                )
            )
    return None


def merge(data, path=FILE):
    """Boot: put the stored calibration (if any) into config dict ``data``; return the zero
    offsets of config.json (the base a calibration may shift from) or None if no file.
    ValueError (the reason) if the file is invalid or does not fit this configuration."""
    got = read_file(path)
    if got is None:
        return None
    zeros, dirs = got
    servos = data.get("servos")
    n = len(data.get("tendon_angles") or [0, 0, 0])
    if servos is None:
        servos = [{"id": i} for i in range(n)]
    if not isinstance(servos, list) or len(servos) != len(zeros):
        raise ValueError("%d servos calibrated, config.json has %d" % (len(zeros), n))
    base = []
    out = []
    for i in range(len(zeros)):
        s = dict(servos[i]) if isinstance(servos[i], dict) else {}
        b = s.get("zero_offset", 0.0)
        base.append(b if isinstance(b, (int, float)) and not isinstance(b, bool) else 0.0)
        s["zero_offset"] = zeros[i]
        s["direction"] = dirs[i]
        out.append(s)
    why = check_shift(base, zeros)
    if why:
        raise ValueError(why)
    data["servos"] = out
    return base


def write_file(zeros, dirs, path=FILE, tmp=_TMP):
    """Store atomically: write and flush a temp file, then rename it over ``path``."""
    import json

    d = {
        "version": cal.CAL_VERSION,
        "servos": [{"zero_offset": zeros[i], "direction": dirs[i]} for i in range(len(zeros))],
    }
    with open(tmp, "w") as f:
        f.write(json.dumps(d))
        f.flush()
    try:
        os.rename(tmp, path)
    except OSError:  # FAT (unlike littlefs, POSIX) renames over no file: remove, then rename;
        os.remove(path)  # a power cut in between leaves the complete temp file, which the next
        os.rename(tmp, path)  # boot takes (load_config)


def load_config(config, driver, path="config.json"):
    """Boot (main.build), when calibration.json (or its temp file) exists: ``config.load``
    with the stored calibration merged in; an invalid calibration refuses the configuration
    (``error`` says why: the segment does not move). This module and protocol.cal_core are
    dropped afterwards."""
    import gc
    import json
    import sys

    where = path
    data = None
    try:
        names = os.listdir()
        if FILE not in names and _TMP in names:
            os.rename(_TMP, FILE)  # a replace interrupted after the remove (write_file)
        with open(path) as f:
            data = json.loads(f.read())
        if not isinstance(data, dict):
            raise ValueError("not a JSON object")
        where = FILE
        base = merge(data)
        where = path
        cfg = config.Config(data, driver)
        cfg.base_zero = base
        import mechanism

        mechanism.Mechanism(cfg, 5)  # geometry must fit the fixed-point scheme too
    except (OSError, ValueError, TypeError, KeyError, AttributeError) as e:
        # (AttributeError: a config.json that is JSON but not an object, e.g. a list)
        cfg = config.refused(data, driver, "%s rejected: %s" % (where, e))
    if sys.implementation.name == "micropython":
        for m in ("calib_store", "protocol.cal_core"):
            sys.modules.pop(m, None)
        import protocol

        if hasattr(protocol, "cal_core"):
            del protocol.cal_core
    gc.collect()
    return cfg

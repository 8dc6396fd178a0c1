"""Slow path: the segment's stored calibration (``calibration.json``) and CALIBRATE (0x09).

Loaded on demand only (a CALIBRATE request, or a boot that finds ``calibration.json``), so the
boot heap does not pay for it. A calibration is, per servo, the zero offset (rad) and direction
(docs/protocol.md, CALIBRATE). The file is written atomically (temp file, then rename) and read at
boot by ``config.load`` through ``merge``: an invalid file is refused with the reason and the
segment does not move (docs/firmware.md, "Calibration"); it never falls back to config.json's
values in place of a calibration it was given.

Changes apply only while the segment is not moving: motion then restarts from the measured
position through the one motion path (MC limits and slew, SC servo speed), whatever the offsets.
"""

import os

import calib_store as store
from mechanism import RANGE_TOL

from protocol import cal_core as cal
from protocol import cbor
from protocol.constants import (
    ERR_BAD_VALUE,
    ERR_IDENTITY_MISMATCH,
    ERR_MALFORMED,
    FLAG_BCAST,
    HEADER_LEN,
    T_CALIBRATE,
    T_CALIBRATION,
)


def running(seg):
    """(zeros rad, dirs) the segment runs now."""
    cfg = seg.cfg
    return [z / 10000.0 for z in cfg.zero], [int(d) for d in cfg.direction]


def config_hash(seg):
    """Hash of the running configuration (params.py caches it; ``apply`` resets the cache)."""
    import params

    return params._config_hash(seg)


def _e4(x):
    v = x * 10000.0
    return int(v + 0.5) if v >= 0 else -int(-v + 0.5)


def apply(seg, zeros, dirs):
    """Run calibration (``zeros`` rad, ``dirs``) now. Only while not moving: the targets become
    the measured positions, and the next motion starts there (MC/SC limits and slew)."""
    cfg = seg.cfg
    base = getattr(cfg, "base_zero", None)
    if base is None:
        base = [z / 10000.0 for z in cfg.zero]
        cfg.base_zero = base
    why = store.check_shift(base, zeros)
    if why:
        raise ValueError(why)
    mc = seg.mc
    for i in range(seg.n):
        z = _e4(zeros[i])
        d = dirs[i]
        cfg.zero[i] = z
        cfg.direction[i] = d
        mc.zero[i] = z
        mc.dir[i] = d
        seg.range_lo[i] = z + cfg.min_angle[i] - RANGE_TOL
        seg.range_hi[i] = z + cfg.max_angle[i] + RANGE_TOL
        s = cfg.si["servos"][i]
        s["zero_offset"] = z / 10000.0
        s["direction"] = d
    seg.cfg_hash = None
    cfg.hash = None  # recomputed for the new calibration (params._config_hash)
    seg.mc.hold_here(seg.bus.pos)
    seg.sc.reset(seg.mc.servo_target)


def _same_as_file(seg):
    try:
        got = store.read_file()
    except ValueError:
        return False
    if got is None:
        return False
    zeros, dirs = running(seg)
    for i in range(seg.n):
        if _e4(got[0][i]) != _e4(zeros[i]) or got[1][i] != dirs[i]:
            return False
    return True


def request(seg, flags, raw, pe, seq):
    """CALIBRATE: decode, check identity and state, act, answer CALIBRATION or ERROR. (Small
    functions: each compiles in the small free blocks of a running segment's heap.)"""
    try:
        got = _decode(seg, flags, raw, pe, seq)
        if got is None:
            return
        _act(seg, got[0], got[1], got[2])
        _answer(seg, seq)
    except Exception as e:  # noqa: BLE001 - any refusal is answered, never a FAULT (as params)
        seg._error(seq, ERR_BAD_VALUE, T_CALIBRATE, "%s" % (e,))


def _decode(seg, flags, raw, pe, seq):
    why = None
    if flags & FLAG_BCAST:
        why = "CALIBRATE must be addressed, not broadcast"
    else:
        try:
            got = cal.decode_calibrate(cbor.loads(raw, HEADER_LEN, pe))
        except ValueError as e:
            why = "CALIBRATE: %s" % (e,)
    if why is not None:
        seg.dropped += 1
        seg._error(seq, ERR_MALFORMED, T_CALIBRATE, why)
        return None
    uid = got[3]
    if uid is not None and uid.lower() != seg.uid:
        seg._error(
            seq, ERR_IDENTITY_MISMATCH, T_CALIBRATE, "identity mismatch: this segment is " + seg.uid
        )
        return None
    z = got[1]
    if got[0] == cal.ACTION_APPLY or got[0] == cal.ACTION_PERSIST:
        bad = len(z) != seg.n  # decode_calibrate: two lists of one length
    else:  # read, forget: keys 2 and 3 are not used; if given, they must still fit
        bad = z is not None and (not isinstance(z, list) or len(z) not in (0, seg.n))
    if bad:
        seg._error(
            seq, ERR_BAD_VALUE, T_CALIBRATE, "this segment has %d servos: one value each" % seg.n
        )
        return None
    return got


def _act(seg, action, zeros, dirs):
    if action == cal.ACTION_APPLY or action == cal.ACTION_PERSIST:
        if seg.moving:
            raise ValueError("moving: send HOLD first (calibration changes only in hold)")
        if seg.cfg.error:
            raise ValueError("configuration refused, nothing to calibrate: " + seg.cfg.error)
        apply(seg, zeros, dirs)
        if action == cal.ACTION_PERSIST:
            store.write_file(zeros, dirs)
    elif action == cal.ACTION_FORGET:
        try:
            os.remove(store.FILE)
        except OSError:
            pass


def _answer(seg, seq):
    z, d = running(seg)
    stored = _same_as_file(seg)
    p = cal.calibration_payload(z, d, stored, config_hash(seg), seg.cfg.si.get("board"))
    seg._reply(T_CALIBRATION, seq, p)

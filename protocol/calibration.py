"""CALIBRATE (0x09) / CALIBRATION (0x89) and the configuration hash (docs/protocol.md).

One source for both runtimes: the segment's slow path (``device/calib.py``) decodes requests and
builds answers with these functions, the host (``host/calibrate_link.py``, ``ucr doctor``) too.
A calibration is, per servo, the zero offset (rad, raw servo angle where the segment is straight)
and the direction (+1/-1: the raw sense that winds the tendon in). ``config_hash`` condenses the
configuration a segment runs (geometry, limits, servo ids and calibration) into a 30-bit number
(FNV-1a over fixed-point text) that the host computes from the U(C)RDF too: a stale flash shows as
a different hash even when only a zero offset differs. Allocates: never on the control cycle.
"""

from protocol.cal_core import (  # noqa: F401 - re-exported: this module is the whole API
    ACTION_APPLY,
    ACTION_FORGET,
    ACTION_PERSIST,
    ACTION_READ,
    ACTIONS,
    CAL_VERSION,
    KC_ACTION,
    KC_BOARD,
    KC_DIRECTION,
    KC_HASH,
    KC_STORED,
    KC_UID,
    KC_VERSION,
    KC_ZERO,
    MAX_SHIFT,
    calibration_payload,
    check_values,
    decode_calibrate,
)
from protocol.confighash import config_hash, config_text  # noqa: F401 - part of this API
from protocol.constants import FLAG_UP, T_CALIBRATE, T_CALIBRATION


def calibrate_payload(action, zeros=None, dirs=None, uid=None):
    """CALIBRATE payload; ``zeros``/``dirs`` required for apply and persist."""
    if action not in (ACTION_READ, ACTION_APPLY, ACTION_PERSIST, ACTION_FORGET):
        raise ValueError("action must be 0..3 (%s)" % ", ".join(ACTIONS))
    d = {KC_VERSION: CAL_VERSION, KC_ACTION: action}
    if action in (ACTION_APPLY, ACTION_PERSIST):
        why = check_values(zeros, dirs, len(zeros) if isinstance(zeros, list) else -1)
        if why:
            raise ValueError(why)
        d[KC_ZERO] = [float(z) for z in zeros]
        d[KC_DIRECTION] = [int(x) for x in dirs]
    if uid is not None:
        if not isinstance(uid, str):
            raise ValueError("uid must be text")
        d[KC_UID] = uid
    return d


def encode_calibrate(seq, position, action, zeros=None, dirs=None, uid=None):
    """CALIBRATE frame addressed to ``position`` (never broadcast: each segment has its own)."""
    from protocol.frame import encode_frame  # (not at import: the segment's boot heap)

    if not 0 <= position <= 255:
        raise ValueError("position must be 0..255")
    return encode_frame(
        0, position, T_CALIBRATE, seq & 0xFF, calibrate_payload(action, zeros, dirs, uid)
    )


def encode_calibration(seq, zeros, dirs, stored, chash):
    """CALIBRATION frame (UP, hop 0) answering CALIBRATE ``seq``."""
    from protocol.frame import encode_frame

    return encode_frame(
        FLAG_UP, 0, T_CALIBRATION, seq & 0xFF, calibration_payload(zeros, dirs, stored, chash)
    )


def decode_calibration(d):
    """CALIBRATION payload (decoded map) -> {version, zero_offsets, directions, stored,
    config_hash}; ValueError if malformed (bytes from a segment are untrusted)."""
    if not isinstance(d, dict) or d.get(KC_VERSION) != CAL_VERSION:
        raise ValueError("not a version %d CALIBRATION" % CAL_VERSION)
    zeros = d.get(KC_ZERO)
    dirs = d.get(KC_DIRECTION)
    why = check_values(zeros, dirs, len(zeros) if isinstance(zeros, list) else -1)
    if why:
        raise ValueError(why)
    stored = d.get(KC_STORED)
    chash = d.get(KC_HASH)
    if not isinstance(stored, bool) or (
        chash is not None and (isinstance(chash, bool) or not isinstance(chash, int))
    ):
        raise ValueError("CALIBRATION keys 4 (stored) / 5 (config_hash) malformed")
    board = d.get(KC_BOARD)
    if board is not None and not isinstance(board, str):
        raise ValueError("CALIBRATION key 6 (board) must be text")
    return {
        "board": board,
        "version": CAL_VERSION,
        "zero_offsets": [float(z) for z in zeros],
        "directions": list(dirs),
        "stored": stored,
        "config_hash": chash,
    }

"""CALIBRATE (0x09) / CALIBRATION (0x89) and the configuration hash (docs/protocol.md).

One source for both runtimes: the segment's slow path (``device/calib.py``) decodes requests and
builds answers with these functions, the host (``host/calibrate_link.py``, ``ucr doctor``) too.
A calibration is, per servo, the zero offset (rad, raw servo angle where the segment is straight)
and the direction (+1/-1: the raw sense that winds the tendon in). ``config_hash`` condenses the
configuration a segment runs (geometry, limits, servo ids and calibration) into a 30-bit number
(FNV-1a over fixed-point text) that the host computes from the U(C)RDF too: a stale flash shows as
a different hash even when only a zero offset differs. Allocates: never on the control cycle.
"""

from protocol.confighash import config_hash, config_text  # noqa: F401 - part of this API
from protocol.constants import FLAG_UP, T_CALIBRATE, T_CALIBRATION

CAL_VERSION = 1  # calibration format version (key 0 of both messages, and of calibration.json)

# CALIBRATE keys (host -> segment)
KC_VERSION = 0
KC_ACTION = 1
KC_ZERO = 2
KC_DIRECTION = 3
KC_UID = 15
# CALIBRATION keys (segment -> host); 0, 2, 3 as above
KC_STORED = 4  # bool: the running calibration is the one stored on the segment's flash
KC_HASH = 5  # uint: config_hash of the running configuration
KC_BOARD = 6  # text: the board profile the segment runs as (protocol/boards.py), optional

ACTION_READ = 0  # answer the running calibration, change nothing
ACTION_APPLY = 1  # run the given calibration now (RAM only; lost at reboot)
ACTION_PERSIST = 2  # apply, then store it on the segment (calibration.json, atomic)
ACTION_FORGET = 3  # delete the stored calibration (config.json's values from the next boot)
ACTIONS = ("read", "apply", "persist", "forget")

#: a calibration may move a zero offset at most this far (rad) from config.json's value
MAX_SHIFT = 1.0

_HASH_MASK = 0x3FFFFFFF  # 30 bits: every wire int stays below 2**30 (as confighash.py)


def _is_num(v):
    return not isinstance(v, bool) and isinstance(v, (int, float)) and v - v == 0


def check_values(zeros, dirs, n):
    """None if ``zeros`` (rad) and ``dirs`` (+1/-1) are a calibration of ``n`` servos, else why."""
    if not isinstance(zeros, list) or len(zeros) != n:
        return "zero offsets must list one angle (rad) per servo (%d)" % n
    if not isinstance(dirs, list) or len(dirs) != n:
        return "directions must list one of 1, -1 per servo (%d)" % n
    for i in range(n):
        if not _is_num(zeros[i]) or not -50.0 <= zeros[i] <= 50.0:
            return "servo %d: zero offset %r is not an angle within +-50 rad" % (i, zeros[i])
        if isinstance(dirs[i], bool) or dirs[i] not in (1, -1):
            return "servo %d: direction %r is not 1 or -1" % (i, dirs[i])
    return None


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


def decode_calibrate(d):
    """CALIBRATE payload (decoded CBOR map) -> (action, zeros, dirs, uid); ValueError if bad."""
    if not isinstance(d, dict):
        raise ValueError("payload is not a map")
    for k in d:
        if not isinstance(k, int) or isinstance(k, bool):
            raise ValueError("keys must be ints")
    if d.get(KC_VERSION) != CAL_VERSION:
        raise ValueError(
            "calibration version %r unsupported (this segment: %d)" % (d.get(0), CAL_VERSION)
        )
    action = d.get(KC_ACTION)
    if isinstance(action, bool) or action not in (0, 1, 2, 3):
        raise ValueError("key 1 (action) must be 0..3")
    uid = d.get(KC_UID)
    if uid is not None and not isinstance(uid, str):
        raise ValueError("key 15 (uid) must be text")
    zeros = d.get(KC_ZERO)
    dirs = d.get(KC_DIRECTION)
    if action in (ACTION_APPLY, ACTION_PERSIST):
        why = check_values(zeros, dirs, len(zeros) if isinstance(zeros, list) else -1)
        if why:
            raise ValueError(why)
    return action, zeros, dirs, uid


def calibration_payload(zeros, dirs, stored, chash, board=None):
    """CALIBRATION payload: the running calibration, whether it is stored, the config hash,
    the board profile (optional)."""
    d = {
        KC_VERSION: CAL_VERSION,
        KC_ZERO: [float(z) for z in zeros],
        KC_DIRECTION: [int(x) for x in dirs],
        KC_STORED: bool(stored),
        KC_HASH: chash & _HASH_MASK,
    }
    if board is not None:
        d[KC_BOARD] = board
    return d


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
    if not isinstance(stored, bool) or isinstance(chash, bool) or not isinstance(chash, int):
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

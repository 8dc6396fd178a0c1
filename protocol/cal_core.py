"""CALIBRATE / CALIBRATION: what a segment needs of them (its slow path), nothing more.

Kept small on purpose: a segment compiles it on its first CALIBRATE, when its heap may be
fragmented (device/calib.py). ``protocol/calibration.py`` re-exports all of it with the host's
builders and parsers; docs/protocol.md specifies the messages.
"""

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

_HASH_MASK = 0x3FFFFFFF  # 30 bits: every wire int stays below 2**30


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
    }
    if chash is not None:  # None: the segment had no heap to compute it
        d[KC_HASH] = chash & _HASH_MASK
    if board is not None:
        d[KC_BOARD] = board
    return d

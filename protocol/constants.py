"""Numbers of the segment link protocol (docs/protocol.md, docs/architecture.md "Link protocol").

Runs unchanged on MicroPython and CPython. Every value here is part of the wire contract:
add new names, never change or reuse a value.
"""

try:
    from micropython import const
except ImportError:  # CPython

    def const(x):
        return x


# --- version -------------------------------------------------------------------------------
VERSION = const(2)  # protocol version carried in header byte 0
VERSION_MIN = const(2)  # oldest version this implementation speaks (v1: docs/protocol.md §14)
VERSION_MAX = const(2)  # newest version this implementation speaks

# --- frame layout --------------------------------------------------------------------------
HEADER_LEN = const(5)  # ver, flags, hop, type, seq
CRC_LEN = const(2)  # CRC-16/CCITT-FALSE, big-endian
TRAILER_LEN = const(3)  # version 2: a 0x00 pad, then the CRC (the pad bounds cut-through's tail)
MIN_FRAME = const(8)  # header + pad + crc, empty payload
MAX_FRAME = const(250)  # max raw frame (header + payload + pad + crc), bytes
MAX_PAYLOAD = const(242)  # MAX_FRAME - HEADER_LEN - TRAILER_LEN
LEGACY_VERSION = const(1)  # version-1 frames have no pad (read only to refuse them)
MAX_ENCODED = const(252)  # COBS(MAX_FRAME) (+1 overhead byte below 254) + 0x00 delimiter
DELIMITER = const(0)  # frame delimiter byte on the wire

# header byte offsets
H_VER = const(0)
H_FLAGS = const(1)
H_HOP = const(2)
H_TYPE = const(3)
H_SEQ = const(4)

# --- flags (header byte 1) -----------------------------------------------------------------
FLAG_UP = const(0x01)  # travels towards the host
FLAG_BCAST = const(0x02)  # broadcast: every segment processes it
FLAG_LOCAL = const(0x04)  # link-local: consumed by the neighbour, never forwarded
FLAGS_KNOWN = const(0x07)  # bits defined in version 1; others must be 0

# --- message types (header byte 3) ---------------------------------------------------------
T_DISCOVER = const(0x01)  # host -> bcast, {} ; every segment answers DESCRIPTOR
T_SYNC = const(0x02)  # host -> bcast, {0: cycle, 1: packed setpoints (bytes), 2: resume?}
T_HEARTBEAT = const(0x03)  # host -> bcast, {0: cycle}
T_PARAM_GET = const(0x04)  # host -> addressed, {0: param_id, 15: uid?}
T_PARAM_SET = const(0x05)  # host -> addressed, {0: param_id, 1: value, 15: uid?}
T_HOLD = const(0x06)  # host -> bcast or addressed, {}
T_ALIVE = const(0x07)  # segment -> upstream neighbour, LOCAL, {}
T_CLEAR_FAULT = const(0x08)  # host -> bcast or addressed, {15: uid?}; ends FAULT (-> HOLD)
T_CALIBRATE = const(0x09)  # host -> addressed, protocol/calibration.py: read/apply/persist zeros
T_DESCRIPTOR = const(0x81)  # up
T_STATE = const(0x83)  # up
T_PARAM_VALUE = const(0x84)  # up
T_CALIBRATION = const(0x89)  # up, answers CALIBRATE (protocol/calibration.py)
T_EVENT = const(0x85)  # up, unsolicited
T_ERROR = const(0xFF)  # up

TYPE_NAMES = {
    0x01: "DISCOVER",
    0x02: "SYNC",
    0x03: "HEARTBEAT",
    0x04: "PARAM_GET",
    0x05: "PARAM_SET",
    0x06: "HOLD",
    0x07: "ALIVE",
    0x08: "CLEAR_FAULT",
    0x09: "CALIBRATE",
    0x81: "DESCRIPTOR",
    0x83: "STATE",
    0x84: "PARAM_VALUE",
    0x85: "EVENT",
    0x89: "CALIBRATION",
    0xFF: "ERROR",
}

# --- CBOR map keys ---------------------------------------------------------------------------
# SYNC / HEARTBEAT
K_CYCLE = const(0)
K_SETPOINTS = const(1)
K_RESUME = const(2)
# PARAM_GET / PARAM_SET / PARAM_VALUE
K_PARAM_ID = const(0)
K_VALUE = const(1)
K_UID = const(15)
# STATE (version 2): {0: packed report (bytes)}; the byte layout below
KS_REPORT = const(0)

# --- packed layouts inside CBOR byte strings (version 2, all fields big-endian) --------------
# SYNC key 1: one SP_LEN-byte entry per position: kappa int24 (1e-4 1/m), phi int16 (1e-4 rad);
# the entry SP_HOLD_BYTES (kappa = -2**23, phi = 0) holds that segment's current setpoint.
SP_LEN = const(5)
SP_KAPPA_MIN = const(-0x7FFFFF)  # int24 range without the hold marker
SP_KAPPA_MAX = const(0x7FFFFF)
SP_HOLD = const(-0x800000)
# STATE key 0: STATE_FIXED bytes (cycle u32, t_ms u32, kappa i24, phi i16, status u8, position
# u8; offsets in protocol/device.py), then one int16 servo angle (1e-3 rad) per servo
STATE_FIXED = const(15)
SERVO_SCALE = const(1000)  # 1 STATE servo-angle unit = 1e-3 rad
# EVENT
KE_CODE = const(0)
KE_DETAIL = const(1)
KE_T_MS = const(2)
KE_TEXT = const(3)  # optional short text (FAULT: the reason)
# ERROR
KR_CODE = const(0)
KR_TYPE = const(1)
KR_TEXT = const(2)
# DESCRIPTOR
KD_UID = const(0)
KD_FW_VERSION = const(1)
KD_PROTOCOL_VERSION = const(2)
KD_MODEL = const(3)
KD_LENGTH = const(4)
KD_TENDON_ANGLES = const(5)
KD_TENDON_RADIUS = const(6)
KD_SPOOL_RADIUS = const(7)
KD_KAPPA_MAX = const(8)
KD_KAPPA_RATE_MAX = const(9)
KD_MASS = const(10)
KD_BACKBONE_RADIUS = const(11)
KD_NAME = const(12)
KD_SERVO_DRIVER = const(13)
KD_WATCHDOG_MS = const(14)
KD_DOWNSTREAM_PRESENT = const(15)
KD_CONFIG_ERROR = const(16)  # why the segment refused its config.json ("" if it did not)
KD_CONFIG_HASH = const(17)  # protocol/calibration.py config_hash of what the segment runs

# descriptor key -> host-side name (docs/architecture.md), in key order
DESCRIPTOR_KEYS = (
    "uid",
    "fw_version",
    "protocol_version",
    "model",
    "length",
    "tendon_angles",
    "tendon_radius",
    "spool_radius",
    "kappa_max",
    "kappa_rate_max",
    "mass",
    "backbone_radius",
    "name",
    "servo_driver",
    "watchdog_ms",
    "downstream_present",
    "config_error",
    "config_hash",
)

# --- event codes -----------------------------------------------------------------------------
EV_DOWNSTREAM_UP = const(1)
EV_DOWNSTREAM_DOWN = const(2)
EV_WATCHDOG_TRIPPED = const(3)
EV_WATCHDOG_CLEARED = const(4)
EV_SERVO_FAULT = const(5)  # detail = servo index
EV_LIMIT_CLAMPED = const(6)  # detail: bit0 kappa, bit1 rate, bit2 servo range
EV_BOOT = const(7)
EV_FAULT = const(8)  # detail = fault code (FAULT_*), key 3 = short text
EV_FAULT_CLEARED = const(9)  # detail = the fault code that was cleared

EVENT_NAMES = {
    1: "DOWNSTREAM_UP",
    2: "DOWNSTREAM_DOWN",
    3: "WATCHDOG_TRIPPED",
    4: "WATCHDOG_CLEARED",
    5: "SERVO_FAULT",
    6: "LIMIT_CLAMPED",
    7: "BOOT",
    8: "FAULT",
    9: "FAULT_CLEARED",
}

# FAULT codes (EVENT FAULT detail, PARAM fault): why a segment entered its FAULT state
FAULT_TICK = const(1)  # an exception in the control tick
FAULT_FRAME = const(2)  # an exception while handling received frames
FAULT_WDT_RESET = const(3)  # the board was reset by its hardware watchdog (machine.WDT)

FAULT_NAMES = {1: "TICK_EXCEPTION", 2: "FRAME_EXCEPTION", 3: "WDT_RESET"}

# LIMIT_CLAMPED detail bits
CLAMP_KAPPA = const(0x01)
CLAMP_RATE = const(0x02)
CLAMP_SERVO = const(0x04)

# --- error codes -----------------------------------------------------------------------------
ERR_UNKNOWN_TYPE = const(1)
ERR_BAD_VALUE = const(2)
ERR_UNSUPPORTED_VERSION = const(3)
ERR_UNKNOWN_PARAM = const(4)
ERR_MALFORMED = const(5)
ERR_IDENTITY_MISMATCH = const(6)

ERROR_NAMES = {
    1: "UNKNOWN_TYPE",
    2: "BAD_VALUE",
    3: "UNSUPPORTED_VERSION",
    4: "UNKNOWN_PARAM",
    5: "MALFORMED",
    6: "IDENTITY_MISMATCH",
}

# --- STATE status bits -----------------------------------------------------------------------
ST_HOLD = const(0x01)
ST_WATCHDOG = const(0x02)
ST_SERVO_FAULT = const(0x04)
ST_CLAMPED = const(0x08)
ST_DOWNSTREAM = const(0x10)
ST_UNCONFIGURED = const(0x20)
ST_FAULT = const(0x40)  # in FAULT: servos held (or released); only CLEAR_FAULT ends it

STATUS_NAMES = (
    (0x01, "HOLD"),
    (0x02, "WATCHDOG"),
    (0x04, "SERVO_FAULT"),
    (0x08, "CLAMPED"),
    (0x10, "DOWNSTREAM"),
    (0x20, "UNCONFIGURED"),
    (0x40, "FAULT"),
)

# --- fixed-point scales (cyclic messages carry ints) -----------------------------------------
KAPPA_SCALE = const(10000)  # 1 wire unit = 1e-4 1/m (kappa, kx, ky)
ANGLE_SCALE = const(10000)  # 1 wire unit = 1e-4 rad (phi, servo angles)
LENGTH_SCALE = const(1000000)  # 1 wire unit = 1e-6 m (tendon lengths)
INT_LIMIT = const(0x40000000)  # every wire int n satisfies -INT_LIMIT < n < INT_LIMIT
TIME_WRAP = const(0x40000000)  # t_ms wraps modulo 2**30

# --- timing (ms) -----------------------------------------------------------------------------
ALIVE_SILENCE_MS = const(50)  # a segment sends ALIVE upstream after this much upstream silence
DOWNSTREAM_TIMEOUT_MS = const(150)  # neighbour marked absent after this much silence
EVENT_MIN_INTERVAL_MS = const(20)  # min spacing of unsolicited EVENTs from one segment
REPLY_DEADLINE_MS = const(5)  # a segment starts its reply within this after the request's end

# --- defaults shared by the spec, the host and the segments ------------------------------------
# Curvature rate limit (1/m/s) when a U(C)RDF <limits> gives no kappa_rate_max: the host plans
# with it (host/limits.py), the segment configuration carries it (ucrdf/checks.py) and an
# unconfigured segment slews at it (device/config.py). One value, so the two sides never disagree.
DEFAULT_KAPPA_RATE_MAX = 10.0

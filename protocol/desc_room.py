"""Room in a segment's DESCRIPTOR frame: one rule for the firmware, ``ucr check`` and ``ucr flash``.

A segment answers DISCOVER with one DESCRIPTOR frame (docs/protocol.md 0x81), at most
MAX_PAYLOAD bytes of payload. Its size depends on the configuration's texts (name, model,
servo_driver, uid) and tendon count. ``device/config.py`` refuses a configuration whose DESCRIPTOR
would not fit with ``ERR_MIN`` bytes of config_error (``problem``), and cuts config_error to the
room left (``room``, at most 40 bytes); ``ucr check`` and ``ucr flash`` run that validation
(``ucrdf.checks.firmware_refusal``), so they refuse the same configurations. The segment loads
this module only while it validates its configuration, then drops it.
"""

ERR_MIN = 16  # bytes of config_error every DESCRIPTOR has room for
_MAX_PAYLOAD = 242  # protocol/constants.py MAX_PAYLOAD (not imported: the segment's boot heap)
# map head, 18 keys, protocol_version, 7 floats (9 bytes each), the tendon list's head,
# watchdog_ms (<= 60000), downstream_present, config_hash (< 2**30), config_error's head (< 256)
_FIXED = 1 + 18 + 1 + 7 * 9 + 1 + 3 + 1 + 5 + 2


def text_len(s):
    """Bytes of text ``s`` in CBOR: head and UTF-8."""
    n = len(s.encode())
    return n + (1 if n < 24 else 2 if n < 256 else 3 if n < 65536 else 5)


def room(cfg, fw_version):
    """Bytes of config_error text the DESCRIPTOR of configuration ``cfg`` (config.json keys, SI)
    has room for in the worst case: every float as float64, the uid 12 characters unless
    ``uid_override``. Negative: it does not fit even without one."""
    n = _MAX_PAYLOAD - _FIXED - 9 * len(cfg["tendon_angles"])
    for t in (cfg.get("uid_override") or "0" * 12, fw_version, cfg["model"], cfg["name"]):
        n -= text_len(t)
    return n - text_len(cfg["servo_driver"])


def problem(cfg, fw_version):
    """None if the DESCRIPTOR of ``cfg`` fits a frame with ERR_MIN bytes of config_error, else
    why, with the longest name that fits."""
    t = room(cfg, fw_version) - ERR_MIN
    if t >= 0:
        return None
    t += text_len(cfg["name"])  # the most the name's text (head included) may take
    return (
        "name of %d bytes too long for the DESCRIPTOR frame: at most %d with %d tendons and "
        "servo_driver %s"
        % (
            len(cfg["name"].encode()),
            max(0, t - 1 if t < 25 else t - 2),
            len(cfg["tendon_angles"]),
            cfg["servo_driver"],
        )
    )

"""One default, one source (issue 19): a robot file without kappa_rate_max is planned by the host
at the same rate its segments slew at."""

from __future__ import annotations

import math
import re
from pathlib import Path

from host.limits import bendable_limits
from protocol import constants as C
from tools.mpvm import run_code
from tools.segment_config import config_for
from ucrdf.parser import parse_string

ROBOT_FILE = Path(__file__).resolve().parent.parent / "robots" / "softrobot2.ucrdf"


def test_host_segment_config_and_firmware_share_the_kappa_rate_default():
    text = re.sub(r'\s+kappa_rate_max="[^"]*"', "", ROBOT_FILE.read_text())
    assert "kappa_rate_max" not in text
    robot = parse_string(text)
    name = next(iter(robot.bendables))
    host_rate = bendable_limits(robot)[name].kappa_rate_max
    seg_rate = config_for(robot, name)["kappa_rate_max"]
    out = run_code(
        "import config\nc = config.Config(None)\nprint('@@', c.si['kappa_rate_max'])\n",
    )
    fw_rate = float(out.split("@@", 1)[1])
    assert host_rate == seg_rate == fw_rate == C.DEFAULT_KAPPA_RATE_MAX
    assert math.isfinite(host_rate) and host_rate > 0


def test_ucr_check_and_the_firmware_share_the_tick_and_watchdog_defaults():
    """ucr check judges a robot file without tick_ms / watchdog_ms by the values its segments run
    (ucrdf.checks SEGMENT_MS_PARAMS; the firmware's config.py DEFAULTS, a runtime of its own)."""
    from ucrdf.checks import SEGMENT_MS_PARAMS

    out = run_code(
        "import config\nc = config.Config(None)\n"
        "print('@@', c.si['tick_ms'], c.si['watchdog_ms'])\n"
    )
    tick, dog = (int(x) for x in out.split("@@", 1)[1].split())
    assert (tick, dog) == (SEGMENT_MS_PARAMS["tick_ms"][3], SEGMENT_MS_PARAMS["watchdog_ms"][3])


def test_the_configuration_hash_leaves_out_exactly_the_firmwares_safety_defaults():
    """protocol/confighash.py hashes watchdog_ms, tick_ms, hw_watchdog_ms and fault_action only
    where they differ from the defaults the firmware runs (so a config.json without them hashes
    as before): its table must be the firmware's DEFAULTS, or a segment running all defaults
    would hash differently from the host's reading of the same robot file."""
    from protocol.confighash import _SAFETY
    from ucrdf.checks import SEGMENT_MS_PARAMS

    keys = [k for k, _ in _SAFETY]
    out = run_code(
        "import config\nc = config.Config(None)\n"
        f"print('@@', ' '.join(str(c.si[k]) for k in {keys!r}))\n"
    )
    firmware = out.split("@@", 1)[1].split()
    assert firmware == [str(v) for _, v in _SAFETY]
    for key, default in _SAFETY:
        if key in SEGMENT_MS_PARAMS:
            assert SEGMENT_MS_PARAMS[key][3] == default, key

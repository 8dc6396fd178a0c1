"""Precompiled firmware (tools/mpy.py): what `ucr flash` deploys is what the emulator runs.

Issue 18: a segment that compiled its modules from source at import had no contiguous heap left
for the calibration module once it had run for a while (CALIBRATE answered "no heap"); the
firmware now goes to boards, and into the emulator, as .mpy files.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from tools import mpy as mpy_tools
from tools.emulator import populate_segment_dir
from tools.flash import BoardInfo, build_files
from tools.mpvm import REPO, implementation_mpy


@pytest.fixture
def fresh_cache(monkeypatch, tmp_path):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    return tmp_path / "cache" / "ucr" / "mpy"


def test_the_emulator_lays_out_what_flash_deploys(tmp_path, fresh_cache):
    seg = tmp_path / "seg"
    populate_segment_dir(seg, config={"uid": "x"})
    laid_out = {
        p.relative_to(seg).as_posix(): p.read_bytes() for p in seg.rglob("*") if p.is_file()
    }
    vm = BoardInfo("micropython", "linux", implementation_mpy(), "vm")
    flashed = dict(build_files({"uid": "x"}, info=vm, log=lambda _line: None))
    assert laid_out == flashed
    assert laid_out["main.py"].startswith(b'"""') or b"def " in laid_out["main.py"]
    modules = [p for p in laid_out if p.endswith((".py", ".mpy"))]
    assert [p for p in modules if p.endswith(".py")] == ["main.py"]
    assert "calib.mpy" in laid_out and "protocol/relay.mpy" in laid_out
    assert all(laid_out[p][:1] == b"M" for p in modules if p.endswith(".mpy"))  # .mpy header


def test_source_layout_on_request_and_no_stale_twin_shadows_a_module(tmp_path, fresh_cache):
    seg = tmp_path / "seg"
    populate_segment_dir(seg, mpy=False)
    assert (seg / "calib.py").exists() and not (seg / "calib.mpy").exists()
    # the same directory repopulated precompiled: MicroPython would import a left-over
    # calib.py before calib.mpy, so the source twin must be gone
    populate_segment_dir(seg)
    assert (seg / "calib.mpy").exists() and not (seg / "calib.py").exists()
    populate_segment_dir(seg, mpy=False)
    assert (seg / "calib.py").exists() and not (seg / "calib.mpy").exists()


def test_compiled_modules_are_cached_by_content(tmp_path, fresh_cache, monkeypatch):
    calls: list[str] = []
    real = mpy_tools.compile_mpy

    def counting(src, dst, *, arch):
        calls.append(Path(src).name)
        real(src, dst, arch=arch)

    monkeypatch.setattr(mpy_tools, "compile_mpy", counting)
    src = tmp_path / "mod.py"
    src.write_text("X = 1\n")
    mpy = implementation_mpy()
    first = mpy_tools.compile_sources([("mod.py", src)], mpy=mpy, log=print)
    again = mpy_tools.compile_sources([("mod.py", src)], mpy=mpy, log=print)
    assert first == again and calls == ["mod.py"]
    src.write_text("X = 2\n")  # changed source: compiled again, never a stale .mpy
    changed = mpy_tools.compile_sources([("mod.py", src)], mpy=mpy, log=print)
    assert changed != first and calls == ["mod.py", "mod.py"]


def test_a_module_that_does_not_compile_is_a_clear_error(tmp_path, fresh_cache):
    bad = tmp_path / "bad.py"
    bad.write_text("def broken(:\n")
    with pytest.raises(mpy_tools.MpyError, match="mpy-cross failed on .*bad.py"):
        mpy_tools.compile_sources([("bad.py", bad)], mpy=implementation_mpy(), log=print)


def test_flash_and_the_emulator_default_to_precompiled():
    import inspect

    from tools import flash

    assert inspect.signature(flash.flash).parameters["mpy"].default is True
    assert inspect.signature(populate_segment_dir).parameters["mpy"].default is True
    assert (REPO / "device" / "calib.py").exists()


def test_a_segment_flashed_as_source_boots_in_the_boards_heap_and_runs_a_cycle():
    """`ucr flash --source` (the fallback where .mpy cannot be used): the segment compiles every
    module on its own heap at boot, the ESP32's heap budget, and still boots, answers DISCOVER
    and turns a SYNC into a STATE. (The firmware tests run the precompiled firmware, as a board
    does; this is the source path's own test.) With a robot's configuration, as `ucr flash`
    writes it: before main.build compiled segment.py ahead of loading it, the source firmware
    ran out of heap configured and booted only unconfigured (review 2026-11-26)."""
    import time

    from host.link import ChainLink
    from tools.emulator import EmulatedChain
    from tools.segment_config import config_for
    from ucrdf.parser import load

    cfg = config_for(load(str(REPO / "robots" / "softrobot3.ucrdf")), "segment_1")
    with (
        EmulatedChain(1, mpy=False, config_for=[cfg]) as chain,
        ChainLink(chain.host_port) as link,
    ):
        end = time.monotonic() + 60
        descs: list = []
        while not descs:
            out = chain.repl_output(0)
            assert time.monotonic() < end and "MemoryError" not in out, out[-2000:]
            try:
                descs = link.discover(timeout=1.0)
            except OSError:
                time.sleep(0.2)
        seg = chain.segment_dir(0)
        assert (seg / "segment.py").exists() and not (seg / "segment.mpy").exists()
        states = link.sync([(0.5, 0.0)], timeout=2.0)
        assert states[0] is not None and states[0]["cycle"] >= 0
        assert "MemoryError" not in chain.repl_output(0), chain.repl_output(0)

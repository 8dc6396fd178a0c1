"""Board figures for bench_firmware.py: the firmware under each board's timing model.

* heap free after boot per board: the real ``main.build()`` on the VM with the board's heap budget
  (64-bit VM objects: an ESP32 has more left than this);
* wait overshoot (tick jitter the wait adds): the HAL's ``wait(3)`` return time minus its deadline,
  with no input, at random phases of the RTOS tick; CPU factor 1 to isolate the wait policy;
* per-hop forwarding latency: a SYNC written to a running firmware process's upstream pty until
  it leaves its downstream pty, at random phases, the full model (RTOS tick + CPU factor).

Each with the model off, and on with the firmware's wait before issue 11 (one ``ipoll(ms)``)
and after (device/waiting.py).
"""

from __future__ import annotations

import json
import os
import pty
import random
import select
import statistics
import subprocess
import tempfile
import time
import tty
from pathlib import Path

from protocol import boards
from protocol import messages as M
from tools import mpvm
from tools.emulator.chain import populate_segment_dir
from tools.emulator.timing import cpu_factor

REPO = mpvm.REPO
POLICIES = (("model off", {}), ("model on, old wait", {"UCR_NAIVE_WAIT": "1"}), ("model on", {}))
#: Forwarding also with the model's holds spinning (UCR_SPIN_HOLD, device/hal_unix.py): how much
#: of "model on" is this host's slowness after each sleep, multiplied by the factor.
FORWARDING_POLICIES = (*POLICIES, ("model on, holds spinning", {"UCR_SPIN_HOLD": "1"}))

_BOOT = """
import gc, main
hal, seg = main.build()
gc.collect()
print('@@', gc.mem_free(), gc.mem_alloc(), repr(seg.cfg.error))
"""

_WAIT = """
import time, random, json, hal_unix, config
cfg = config.Config({'watchdog_ms': 60000})
hal = hal_unix.Hal(cfg.si['pins'])
over = []
for i in range(%d):
    time.sleep_us(random.getrandbits(14) %% 10000)
    hal._busy_from = time.ticks_us()  # the bench's own pause is not firmware compute
    t0 = time.ticks_us()
    hal.wait(3)
    over.append(time.ticks_diff(time.ticks_us(), t0) - 3000)
print('@@' + json.dumps(over))
"""


def _seg_dir(tmp: Path, config: dict | None) -> Path:
    """A segment's files as ``ucr flash`` writes them (modules precompiled, main.py as source)."""
    seg = tmp / "seg"
    populate_segment_dir(seg, config=config)
    return seg


def _env(seg: Path, extra: dict[str, str]) -> dict[str, str]:
    env = dict(os.environ, MICROPYPATH=f".frozen:{seg}", UCR_UID="b0a4d0000001")
    for k in (
        "UCR_BOARD",
        "UCR_TIMING",
        "UCR_CPU_FACTOR",
        "UCR_NAIVE_WAIT",
        "UCR_SPIN_HOLD",
        "UCR_FAULTS",
    ):
        env.pop(k, None)
    env.update(extra)
    return env


def heap_after_boot() -> list[tuple[str, str]]:
    """(board, text) for every ESP32 board profile."""
    out = []
    for name in sorted(b for b in boards.BOARDS if b != "unix"):
        heap = boards.BOARDS[name]["heap"]
        with tempfile.TemporaryDirectory(prefix="ucr-bench-") as tmp:
            seg = _seg_dir(Path(tmp), {"board": name, "servo_driver": "pwm"})
            proc = subprocess.run(
                [mpvm.micropython_binary(), "-X", f"heapsize={heap}", "-c", _BOOT],
                cwd=seg,
                env=_env(seg, {}),
                capture_output=True,
                text=True,
                timeout=60,
            )
        line = next((x for x in proc.stdout.splitlines() if x.startswith("@@")), None)
        if line is None:
            out.append((name, f"boot failed: {proc.stderr.strip().splitlines()[-1:]}"))
            continue
        free, used, error = line[3:].split(" ", 2)
        if error != "None":
            out.append((name, f"refused at boot: {error.strip()[1:-1]}"))
        else:
            out.append((name, f"{int(free):7d} B free, {int(used):7d} B used of {heap} B"))
    return out


def _pcts(xs: list[float]) -> tuple[float, float]:
    xs = sorted(xs)
    return statistics.median(xs), xs[min(len(xs) - 1, int(0.99 * len(xs)))]


def wait_overshoot(n: int) -> list[tuple[str, float, float]]:
    """(policy, p50 us, p99 us) of the HAL wait's overshoot past its deadline."""
    rows = []
    for label, extra in POLICIES:
        env = {"UCR_TIMING": "1", "UCR_CPU_FACTOR": "1", **extra} if "on" in label else {}
        master, slave = pty.openpty()
        tty.setraw(master)
        try:
            env.update(UCR_UP_PORT=os.ttyname(slave), UCR_BOARD="esp32")
            with tempfile.TemporaryDirectory(prefix="ucr-bench-") as tmp:
                seg = _seg_dir(Path(tmp), None)
                proc = subprocess.run(
                    [mpvm.micropython_binary(), "-X", "heapsize=160k", "-c", _WAIT % n],
                    cwd=seg,
                    env=_env(seg, env),
                    capture_output=True,
                    text=True,
                    timeout=120,
                )
        finally:
            os.close(master)
            os.close(slave)
        line = next((x for x in proc.stdout.splitlines() if x.startswith("@@")), None)
        if line is None:
            raise RuntimeError(f"wait bench failed: {proc.stdout}{proc.stderr}")
        p50, p99 = _pcts(json.loads(line[2:]))
        rows.append((label, p50, p99))
    return rows


def _read_frame(fd: int, deadline: float) -> float | None:
    """Time the next whole frame (0x00-terminated) arrives on ``fd``, or None."""
    buf = b""
    while time.monotonic() < deadline:
        r, _, _ = select.select([fd], [], [], 0.05)
        if r:
            buf += os.read(fd, 512)
            if b"\x00" in buf:
                return time.perf_counter()
    return None


def forwarding(n: int, board: str = "esp32") -> tuple[float, list[tuple[str, float, float, int]]]:
    """(cpu factor, [(policy, p50 ms, p99 ms, lost)]) of the per-hop SYNC forwarding latency."""
    factor = cpu_factor(board)
    rows = []
    for label, extra in FORWARDING_POLICIES:
        env = dict(extra)
        if "on" in label:
            env.update(UCR_TIMING="1", UCR_CPU_FACTOR=f"{factor:.2f}")
        (um, us), (dm, ds) = pty.openpty(), pty.openpty()
        for fd in (um, dm):
            tty.setraw(fd)
        env.update(UCR_UP_PORT=os.ttyname(us), UCR_DOWN_PORT=os.ttyname(ds), UCR_BOARD=board)
        lat, lost = [], 0
        with tempfile.TemporaryDirectory(prefix="ucr-bench-") as tmp:
            seg = _seg_dir(Path(tmp), {"watchdog_ms": 60000})
            proc = subprocess.Popen(
                [mpvm.micropython_binary(), "-X", "heapsize=160k", "main.py"],
                cwd=seg,
                env=_env(seg, env),
                stdin=subprocess.DEVNULL,
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
            )
            try:
                time.sleep(1.5)  # boot
                sync = M.encode_sync(1, 1, [(0.5, 0.1)])
                for i in range(n + 5):
                    time.sleep(0.03 + random.random() * 0.02)  # random phase, below the watchdog
                    while select.select([dm], [], [], 0)[0]:
                        os.read(dm, 4096)  # drop ALIVE/earlier bytes
                    t0 = time.perf_counter()
                    os.write(um, sync)
                    t1 = _read_frame(dm, time.monotonic() + 1.0)
                    if i < 5:
                        continue  # warm-up
                    if t1 is None:
                        lost += 1
                    else:
                        lat.append((t1 - t0) * 1e3)
                    while select.select([um], [], [], 0)[0]:
                        os.read(um, 4096)  # STATE answers
            finally:
                proc.kill()
                proc.wait()
                for fd in (um, us, dm, ds):
                    os.close(fd)
        p50, p99 = _pcts(lat) if lat else (float("nan"), float("nan"))
        rows.append((label, p50, p99, lost))
    return factor, rows

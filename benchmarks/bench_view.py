"""View benchmark: scene update rate (3 and 8 segments), daemon->page latency, and what an open
view does to the control loop's jitter. Headless Chromium (Debian's /usr/bin/chromium) is the page.

    .venv/bin/python benchmarks/bench_view.py [--seconds 5]

1. Update rate: an offline view whose configuration changes at 200 Hz (every segment moving), with
   a page open; figures: scene pushes/s by the view and state samples/s that reach the page's DOM
   (goal >= 30 Hz).
2. Live, on the real daemon and an emulated 3-segment chain: daemon->page latency p50/p99 (daemon
   sample time -> the page's DOM showing it; same machine, wall clock), and the loop's jitter p99
   with the view closed vs open (goal ratio <= 1.1).
Prints figures; asserts nothing (the machine may be shared and noisy).
"""

# ruff: noqa: PLC0415 - heavy imports (daemon, emulator, browser) only when the benchmark runs
from __future__ import annotations

import argparse
import math
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
ARGS = ["--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--no-sandbox"]

# Records (wall ms when the page showed it, daemon sample wall ms) for every new "sample:" text.
OBSERVER = """
window.__samples = [];
new MutationObserver(() => {
  for (const el of document.querySelectorAll('p')) {
    const m = /^sample: ([0-9.]+)$/.exec(el.textContent);
    if (m && el.dataset.seen !== m[1]) {
      el.dataset.seen = m[1];
      window.__samples.push([performance.timeOrigin + performance.now(), parseFloat(m[1])]);
    }
  }
}).observe(document, {subtree: true, childList: true, characterData: true});
"""


def _pct(values: list[float], q: float) -> float:
    s = sorted(values)
    return s[min(len(s) - 1, int(q * len(s)))] if s else math.nan


def robot_file(n: int, tmp: Path) -> Path:
    """softrobot3's segment, n times, as a U(C)RDF file."""
    from tools.segment_config import config_for
    from ucrdf.compose import robot_from_descriptors
    from ucrdf.parser import load
    from ucrdf.writer import dump

    if n == 3:
        return ROOT / "robots" / "softrobot3.ucrdf"
    base = config_for(load(ROOT / "robots" / "softrobot3.ucrdf"), "segment_1")
    descs = [{**base, "name": f"segment_{i + 1}", "uid": f"{i:012x}"} for i in range(n)]
    path = tmp / f"robot{n}.ucrdf"
    dump(robot_from_descriptors(descs, f"robot{n}"), path)
    return path


def page_samples(page, seconds: float) -> list[list[float]]:
    page.evaluate("window.__samples = []")
    time.sleep(seconds)
    return page.evaluate("window.__samples")


def update_rate(browser, n: int, seconds: float, tmp: Path) -> None:
    from view.app import ViewApp
    from view.source import OfflineSource

    src = OfflineSource(robot_file(n, tmp)).start()
    app = ViewApp(src, port=0, rate_hz=200.0).start()
    stop = threading.Event()

    def wiggle() -> None:  # every segment moves, 200 Hz
        t0 = time.monotonic()
        while not stop.wait(0.005):
            t = time.monotonic() - t0
            for i, name in enumerate(src.snap.expected):
                src.set_target(name, 1.5 + math.sin(t + i), math.cos(0.5 * t + i))

    th = threading.Thread(target=wiggle, daemon=True)
    th.start()
    ctx = browser.new_context(viewport={"width": 1000, "height": 700})
    page = ctx.new_page()
    page.add_init_script(OBSERVER)
    page.goto(app.url)
    page.get_by_text(f"tubes: {n}").wait_for(timeout=60000)
    time.sleep(1.0)
    p0 = app.pushes
    samples = page_samples(page, seconds)
    pushes = (app.pushes - p0) / seconds
    ctx.close()
    stop.set()
    app.stop()
    lat = [a - b for a, b in samples]
    shown = len(samples) / seconds
    print(
        f"update rate, {n} segments: view pushes {pushes:.1f} Hz, page shows {shown:.1f} samples/s"
        f" (goal >= 30); slider->page p50 {_pct(lat, 0.5):.1f} ms, p99 {_pct(lat, 0.99):.1f} ms",
        flush=True,
    )


def live(browser, seconds: float) -> None:
    from host.api.server import ApiServer
    from host.daemon import Daemon, DaemonError
    from tools.emulator import EmulatedChain
    from tools.segment_config import configs
    from ucrdf.parser import load
    from view.app import ViewApp
    from view.source import LiveSource

    robot = load(ROOT / "robots" / "softrobot3.ucrdf")
    chain = EmulatedChain(3, config_for=configs(robot))
    daemon = srv = app = None
    try:
        deadline = time.monotonic() + 20
        while True:
            try:
                daemon = Daemon(robot, port=chain.host_port).start()
                break
            except DaemonError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.2)
        srv = ApiServer(daemon, "127.0.0.1", 0).start()

        def jitter() -> float:
            daemon.loop.stats.reset()
            time.sleep(seconds)
            return daemon.loop_stats()["jitter_us"]["p99"]

        # a slow wave keeps joint states changing (every push carries news)
        wave = [
            {"time_from_start": 2.0 * (k + 1),
             "segments": {n: {"kappa": 1.5 * (k % 2), "phi": 0.5 * k} for n in robot.bendables}}
            for k in range(int(4 * seconds) + 8)
        ]  # fmt: skip
        daemon.send_trajectory(wave)
        time.sleep(1.0)
        closed = jitter()
        app = ViewApp(LiveSource(srv.url, None).start(), port=0).start()
        ctx = browser.new_context(viewport={"width": 1000, "height": 700})
        page = ctx.new_page()
        page.add_init_script(OBSERVER)
        page.goto(app.url)
        page.get_by_text("tubes: 3").wait_for(timeout=60000)
        time.sleep(1.0)
        p0 = app.pushes
        samples = page_samples(page, seconds)
        rate = (app.pushes - p0) / seconds
        opened = jitter()
        lat = [a - b for a, b in samples]
        print(
            f"live, 3 segments: view pushes {rate:.1f} Hz, page shows {len(samples) / seconds:.1f} "
            f"samples/s; daemon->page latency p50 {_pct(lat, 0.5):.1f} ms, p99 "
            f"{_pct(lat, 0.99):.1f} ms (n={len(lat)})",
            flush=True,
        )
        print(
            f"loop jitter p99: view closed {closed:.0f} us, view open {opened:.0f} us, "
            f"ratio {opened / closed:.2f} (goal <= 1.1)",
            flush=True,
        )
        ctx.close()
    finally:
        if app is not None:
            app.stop()
        if srv is not None:
            srv.stop()
        if daemon is not None:
            daemon.stop()
        chain.close()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--chromium", default="/usr/bin/chromium")
    args = ap.parse_args()
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p, tempfile.TemporaryDirectory() as tmp:
        browser = p.chromium.launch(executable_path=args.chromium, args=ARGS)
        for n in (3, 8):
            update_rate(browser, n, args.seconds, Path(tmp))
        live(browser, args.seconds)
        browser.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())

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
import re
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
VIEWPORT = {"width": 640, "height": 480}
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


def count_frames(page) -> list[int]:
    """Counter of WebSocket frames the page receives (attach before it connects)."""
    frames = [0]

    def on_ws(ws) -> None:
        ws.on("framereceived", lambda _f: frames.__setitem__(0, frames[0] + 1))

    page.on("websocket", on_ws)
    return frames


def page_samples(page, frames: list[int], seconds: float) -> tuple[list[list[float]], float]:
    """(samples the DOM showed, WebSocket frames/s the page received) over ``seconds``."""
    frames[0] = 0
    page.evaluate("window.__samples = []")
    t0 = time.monotonic()
    while time.monotonic() - t0 < seconds:
        page.wait_for_timeout(100)  # lets Playwright dispatch the frame events
    return page.evaluate("window.__samples"), frames[0] / seconds


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
    ctx = browser.new_context(viewport=VIEWPORT)
    page = ctx.new_page()
    page.add_init_script(OBSERVER)
    frames = count_frames(page)
    page.goto(app.url)
    page.get_by_text(f"tubes: {n}").wait_for(timeout=60000)
    time.sleep(1.0)
    p0 = app.pushes
    samples, ws_rate = page_samples(page, frames, seconds)
    pushes = (app.pushes - p0) / seconds
    ctx.close()
    stop.set()
    app.stop()
    lat = [a - b for a, b in samples]
    shown = len(samples) / seconds
    print(
        f"update rate, {n} segments: view pushes {pushes:.1f} Hz (goal >= 30), page receives "
        f"{ws_rate:.1f} WebSocket messages/s, its DOM shows {shown:.1f} samples/s (software GL); "
        f"slider->DOM p50 {_pct(lat, 0.5):.1f} ms, p99 {_pct(lat, 0.99):.1f} ms",
        flush=True,
    )


def live(browser, seconds: float) -> None:
    from tools.rig import EmulatedRig
    from view.launch import start_view_process

    rig = EmulatedRig(ROOT / "robots" / "softrobot3.ucrdf", boot_timeout_s=20)
    robot, daemon, srv, view = rig.robot, rig.daemon, rig.srv, None
    try:

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
        view = start_view_process(srv.url)
        time.sleep(1.0)
        no_page = jitter()
        ctx = browser.new_context(viewport=VIEWPORT)
        page = ctx.new_page()
        page.add_init_script(OBSERVER)
        frames = count_frames(page)
        page.goto(view.url)
        page.get_by_text("tubes: 3").wait_for(timeout=60000)
        time.sleep(1.0)
        samples, ws_rate = page_samples(page, frames, seconds)
        facts = page.get_by_text("tubes: 3").first.text_content() or ""
        m = re.search(r"update (\d+) Hz", facts)
        opened = jitter()
        ctx.close()
        closed_again = jitter()
        lat = [a - b for a, b in samples]
        print(
            f"live, 3 segments (view in its own process): view pushes {m.group(1) if m else '?'} "
            f"Hz, page receives {ws_rate:.1f} WebSocket messages/s, its DOM shows "
            f"{len(samples) / seconds:.1f} samples/s; daemon->DOM latency p50 "
            f"{_pct(lat, 0.5):.1f} ms, p99 {_pct(lat, 0.99):.1f} ms (n={len(lat)})",
            flush=True,
        )
        base = max(closed, closed_again)
        print(
            f"loop jitter p99: view closed {closed:.0f} / {closed_again:.0f} us; view process "
            f"running, no page {no_page:.0f} us, ratio {no_page / base:.2f} (goal <= 1.1); view + "
            f"page open {opened:.0f} us, ratio {opened / base:.2f} (the browser on this machine)",
            flush=True,
        )
    finally:
        if view is not None:
            view.stop()
        rig.close()


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

"""View benchmark: scene update rate (3 and 8 segments), daemon->page latency, and what an open
view does to the control loop's jitter. Headless Chromium (Debian's /usr/bin/chromium) is the page.

    .venv/bin/python benchmarks/bench_view.py [--seconds 5] [--runs 3] [--daemon-nice -5]
        [--rt-priority N] [--view-rate HZ] [--overload S [--busy 2] [--pages 2]]
        [--figures FILE]

1. Update rate: an offline view whose configuration changes at 200 Hz (every segment moving), with
   a page open; figures: scene pushes/s by the view and state samples/s that reach the page's DOM
   (goal >= 30 Hz).
2. Live, on the real daemon and an emulated 3-segment chain: daemon->page latency p50/p99 (daemon
   sample time -> the page's DOM showing it; same machine, wall clock), and the loop's jitter p99
   with the view closed vs open (goal ratio <= 1.1).
3. With ``--overload S``: the live view for S seconds with ``--busy`` processes spinning and
   ``--pages`` pages open (a machine with more to do than it can): how late the pages show the
   daemon's samples, and whether a late sample waited in a queue or for the page's next frame
   (each gap > 250 ms between two animation frames is recorded).
Prints figures (saved with ``--figures`` for tools/docfigures.py); asserts nothing (the
machine may be shared and noisy).
"""

# ruff: noqa: PLC0415 - heavy imports (daemon, emulator, browser) only when the benchmark runs
from __future__ import annotations

import argparse
import math
import os
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
// Pauses of the page's drawing: [start, end] wall ms of every gap > 250 ms between two
// animation frames (a frame not drawn: the page shows what it showed before).
window.__pauses = [];
(function () {
  let last = performance.timeOrigin + performance.now();
  const frame = () => {
    const now = performance.timeOrigin + performance.now();
    if (now - last > 250) window.__pauses.push([last, now]);
    last = now;
    requestAnimationFrame(frame);
  };
  requestAnimationFrame(frame);
})();
"""


def staleness(samples: list[list[float]], end_ms: float) -> float:
    """Longest time (ms) the page's DOM went on showing one sample: from that sample's daemon
    time until the page showed the next one (or ``end_ms``, wall ms, for the last)."""
    if not samples:
        return math.nan
    shown = [*samples[1:], [end_ms, math.nan]]
    return max(nxt[0] - cur[1] for cur, nxt in zip(samples, shown, strict=True))


def _pct(values: list[float], q: float) -> float:
    s = sorted(values)
    return s[min(len(s) - 1, int(q * len(s)))] if s else math.nan


def _lat_cell(lat: list[float]) -> str:
    """p50 / p99 of a latency list for the figures, or why there is none."""
    if not lat:
        return "none: no sample reached the page's DOM"
    return f"{_pct(lat, 0.5):.0f} / {_pct(lat, 0.99):.0f} ms (n = {len(lat)})"


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
    got, n = page.evaluate("window.__samples"), frames[0]
    return got, n / (time.monotonic() - t0)


def update_rate(browser, n: int, seconds: float, tmp: Path) -> list[str]:
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
    p0, t0 = app.pushes, time.monotonic()
    samples, ws_rate = page_samples(page, frames, seconds)
    pushes = (app.pushes - p0) / (time.monotonic() - t0)
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
    return [
        str(n), f"{pushes:.0f} Hz", f"{ws_rate:.0f} /s", f"{shown:.1f} /s",
        _lat_cell(lat),
    ]  # fmt: skip


def _cpu_s(pid: int | None) -> float:
    """CPU time (s, user + system) a process used so far; 0 if unknown."""
    if pid is None:
        return 0.0
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _p99(daemon, seconds: float, pids: dict[str, int | None]) -> tuple[float, float, dict]:
    """(loop jitter p99 us over ``seconds``, 1-min load average at the end, CPU ms/s of each
    process in ``pids``)."""
    before = {k: _cpu_s(p) for k, p in pids.items()}
    daemon.loop.stats.reset()
    time.sleep(seconds)
    cpu = {k: (_cpu_s(p) - before[k]) * 1e3 / seconds for k, p in pids.items()}
    return daemon.loop_stats()["jitter_us"]["p99"], os.getloadavg()[0], cpu


def _start_niced(fn, nice: int):
    """Run ``fn`` in a thread whose nice value is ``nice`` (Linux: per thread; the threads and
    processes it starts inherit it), as the systemd unit's Nice= does for the daemon."""
    out: list = []

    def run() -> None:
        if nice:
            os.setpriority(os.PRIO_PROCESS, 0, nice)
        out.append(fn())

    t = threading.Thread(target=run)
    t.start()
    t.join()
    return out[0]


def _median(values: list[float]) -> float:
    s = sorted(values)
    return s[len(s) // 2] if s else math.nan


def _worst_catch_up(catch_up: list[float]) -> str:
    """The table cell for the slowest catch-up after a pause (NaN: no fresh sample after it)."""
    if not catch_up:
        return "no pause > 1 s"
    if any(math.isnan(c) for c in catch_up):
        return "none shown after a pause"
    return f"{max(catch_up) / 1e3:.1f} s"


def overloaded(browser, page, url: str, stress: tuple[float, int, int]) -> list[list[str]]:
    """The page (and ``pages - 1`` more) while ``busy`` processes spin on this machine's cores
    for ``seconds``: how late the samples the pages show are, and whether the pages were
    waiting for a frame (drawing nothing) or queueing what they had not drawn."""
    import subprocess

    seconds, busy, pages = stress
    more = []
    for _ in range(pages - 1):
        c = browser.new_context(viewport=VIEWPORT)
        pg = c.new_page()
        pg.add_init_script(OBSERVER)
        pg.goto(url)
        pg.get_by_text("tubes: 3").wait_for(timeout=60000)
        more.append((c, pg))
    everyone = [page] + [pg for _, pg in more]
    spin = "while True: pass"
    hogs = [subprocess.Popen([sys.executable, "-c", spin]) for _ in range(busy)]
    rows = []
    try:
        for pg in everyone:
            pg.evaluate("window.__samples = []; window.__pauses = []")
        t0 = time.monotonic()
        while time.monotonic() - t0 < seconds:
            page.wait_for_timeout(500)
    finally:
        for h in hogs:
            h.kill()
            h.wait()
    for i, pg in enumerate(everyone):
        samples, pauses, end = pg.evaluate(
            "[window.__samples, window.__pauses, performance.timeOrigin + performance.now()]"
        )
        lat = [a - b for a, b in samples]
        stale = staleness(samples, end)
        longest = max((b - a for a, b in pauses), default=0.0)
        catch_up = [
            next((shown - b for shown, t in samples if shown >= b and shown - t < 500), math.nan)
            for a, b in pauses
            if b - a > 1000
        ]  # after each pause > 1 s: until the page shows a sample less than 0.5 s old
        print(
            f"overloaded ({busy} busy processes, {pages} pages, {seconds:g} s), page {i + 1}: "
            f"{len(samples)} samples shown, daemon->DOM p50 {_pct(lat, 0.5):.0f} ms, max "
            f"{max(lat, default=math.nan):.0f} ms; the page went on showing one sample for up "
            f"to {stale:.0f} ms; longest pause between two animation frames {longest:.0f} ms "
            f"({len(pauses)} pauses > 250 ms); after each pause > 1 s, a fresh sample (< 0.5 s "
            f"old) shown {', '.join(f'{c:.0f}' for c in catch_up) or '-'} ms later",
            flush=True,
        )
        rows.append([
            f"page {i + 1} of {pages}", f"{len(samples)}", _lat_cell(lat),
            f"{stale / 1e3:.1f} s", f"{longest / 1e3:.1f} s ({len(pauses)})",
            _worst_catch_up(catch_up),
        ])  # fmt: skip
    for c, _ in more:
        c.close()
    return rows


def live(
    browser,
    seconds: float,
    runs: int,
    in_process: bool,
    daemon_nice: int,
    rt_priority: int = 0,
    stress: tuple[float, int, int] = (0.0, 0, 1),
    view_rate: float | None = None,
) -> dict:
    from host.api.process import start_api_process
    from host.api.server import ApiServer
    from host.daemon import Daemon, DaemonError
    from tools.emulator import EmulatedChain
    from tools.segment_config import configs
    from ucrdf.parser import load
    from view.launch import start_view_process

    robot = load(ROOT / "robots" / "softrobot3.ucrdf")
    chain = EmulatedChain(3, config_for=configs(robot))
    daemon = api = view = None
    try:

        def start_daemon():
            deadline = time.monotonic() + 20
            while True:
                try:
                    return Daemon(
                        robot, port=chain.host_port, realtime_priority=rt_priority
                    ).start()
                except DaemonError:
                    if time.monotonic() > deadline:
                        raise
                    time.sleep(0.2)

        # as the systemd unit runs it (Nice=-5; the emulated segments stay at 0 like separate
        # boards); the API in a process of its own, as `ucr daemon` starts it (API_NICE above
        # the daemon), or with --api-in-process a thread sharing the loop's interpreter lock
        daemon = _start_niced(start_daemon, daemon_nice)
        if in_process:
            api = ApiServer(daemon, "127.0.0.1", 0).start()
        else:
            api = _start_niced(lambda: start_api_process(daemon, "127.0.0.1", 0), daemon_nice)
        where = "a thread of the daemon" if in_process else "its own process (as ucr daemon)"
        where += f", daemon nice {daemon_nice}"
        sched = daemon.loop_stats()["scheduling"].get("control loop", "normal")
        where += f", loop thread {sched}"
        api_pid = None if in_process else api.pid

        # a slow wave keeps joint states changing (every push carries news)
        total = runs * 3 * seconds + 4 * seconds + stress[0] + 60
        wave = [
            {"time_from_start": 2.0 * (k + 1),
             "segments": {n: {"kappa": 1.5 * (k % 2), "phi": 0.5 * k} for n in robot.bendables}}
            for k in range(int(total / 2) + 8)
        ]  # fmt: skip
        daemon.send_trajectory(wave)
        time.sleep(1.0)
        view = start_view_process(api.url, rate_hz=view_rate)
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
        stalls = overloaded(browser, page, view.url, stress) if stress[0] > 0 else []
        ctx.close()
        lat = [a - b for a, b in samples]
        print(
            f"live, 3 segments (view in its own process, API in {where}): view pushes "
            f"{m.group(1) if m else '?'} Hz, page receives {ws_rate:.1f} WebSocket messages/s, "
            f"its DOM shows {len(samples) / seconds:.1f} samples/s; daemon->DOM latency p50 "
            f"{_pct(lat, 0.5):.1f} ms, p99 {_pct(lat, 0.99):.1f} ms (n={len(lat)})",
            flush=True,
        )
        out = {
            "where": where,
            "live": [m.group(1) + " Hz" if m else "?", f"{ws_rate:.0f} /s", _lat_cell(lat)],
            "runs": [],
            "stalls": stalls,
        }  # fmt: skip
        view.stop()
        view = None
        # jitter: closed / view process (no page) / view + page, alternating, `runs` times
        phases: dict[str, list[tuple]] = {"closed": [], "view": [], "page": []}
        for r in range(runs):
            phases["closed"].append(_p99(daemon, seconds, {"api": api_pid}))
            view = start_view_process(api.url, rate_hz=view_rate)
            pids = {"api": api_pid, "view": view.proc.pid}
            time.sleep(1.0)
            phases["view"].append(_p99(daemon, seconds, pids))
            ctx = browser.new_context(viewport=VIEWPORT)
            page = ctx.new_page()
            page.goto(view.url)
            page.get_by_text("tubes: 3").wait_for(timeout=60000)
            phases["page"].append(_p99(daemon, seconds, pids))
            ctx.close()
            view.stop()
            view = None
            c, v, pg = phases["closed"][-1], phases["view"][-1], phases["page"][-1]
            out["runs"].append([
                f"run {r + 1}", f"{c[0]:.0f} µs", f"{v[0]:.0f} µs", f"{pg[0]:.0f} µs",
                f"{c[1]:.1f} / {v[1]:.1f} / {pg[1]:.1f}",
            ])  # fmt: skip
            print(
                f"  run {r + 1}: loop jitter p99 closed {c[0]:.0f} us, view process {v[0]:.0f} "
                f"us, view + page {pg[0]:.0f} us (load average {c[1]:.1f} / {v[1]:.1f} / "
                f"{pg[1]:.1f}); CPU ms/s: API {c[2]['api']:.0f} / {v[2]['api']:.0f} / "
                f"{pg[2]['api']:.0f}, view - / {v[2]['view']:.0f} / {pg[2]['view']:.0f}",
                flush=True,
            )
        phases = {k: [(x[0], x[1]) for x in v] for k, v in phases.items()}
        closed = _median([v for v, _ in phases["closed"]])
        viewed = _median([v for v, _ in phases["view"]])
        paged = _median([v for v, _ in phases["page"]])
        print(
            f"loop jitter p99, median of {runs} (API in {where}): closed {closed:.0f} us; view "
            f"process, no page {viewed:.0f} us, ratio {viewed / closed:.2f} (goal <= 1.1); "
            f"view + headless Chromium page on this machine {paged:.0f} us, ratio "
            f"{paged / closed:.2f}; cores {os.cpu_count()}",
            flush=True,
        )
        out["runs"].append([
            f"median of {runs}", f"{closed:.0f} µs",
            f"{viewed:.0f} µs (ratio {viewed / closed:.2f})",
            f"{paged:.0f} µs (ratio {paged / closed:.2f})", "",
        ])  # fmt: skip
        out["topology_changes"] = daemon.status()["topology_changes"]
        return out
    finally:
        if view is not None:
            view.stop()
        if api is not None:
            api.stop()
        if daemon is not None:
            daemon.stop()
        chain.close()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--chromium", default="/usr/bin/chromium")
    ap.add_argument("--runs", type=int, default=3, help="alternating jitter runs (3)")
    ap.add_argument("--api-in-process", action="store_true", help="API as a daemon thread")
    ap.add_argument("--skip-rate", action="store_true", help="only the live part")
    ap.add_argument("--browser-nice", type=int, default=0, help="run Chromium at this nice")
    ap.add_argument(
        "--daemon-nice", type=int, default=0, help="the daemon nice (the systemd unit: -5)"
    )
    ap.add_argument(
        "--rt-priority", type=int, default=0, metavar="N",
        help="SCHED_FIFO priority of the daemon's loop and link reader (the unit: 10; 0: normal)",
    )  # fmt: skip
    ap.add_argument(
        "--overload", type=float, default=0.0, metavar="S",
        help="then S seconds with --busy processes spinning and --pages pages open (0: skip)",
    )  # fmt: skip
    ap.add_argument("--busy", type=int, default=2, help="spinning processes of --overload (2)")
    ap.add_argument(
        "--view-rate", type=float, metavar="HZ", help="the live view's --rate (its default: 40)"
    )
    ap.add_argument("--pages", type=int, default=2, help="pages open during --overload (2)")
    ap.add_argument("--figures", metavar="FILE", help="save the tables the docs quote (JSON)")
    args = ap.parse_args()
    from benchmarks.figures import Figures

    figs = Figures.from_argv("bench_view")
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p, tempfile.TemporaryDirectory() as tmp:
        exe = args.chromium
        if args.browser_nice:  # the page's CPU below everything else (a stand-in for a laptop)
            exe = str(Path(tmp) / "chromium-niced")
            script = f'#!/bin/sh\nexec nice -n {args.browser_nice} {args.chromium} "$@"\n'
            Path(exe).write_text(script)
            os.chmod(exe, 0o755)
        browser = p.chromium.launch(executable_path=exe, args=ARGS)
        rates = []
        if not args.skip_rate:
            for n in (3, 8):
                rates.append(update_rate(browser, n, args.seconds, Path(tmp)))
        got = live(
            browser, args.seconds, args.runs, args.api_in_process, args.daemon_nice,
            args.rt_priority, (args.overload, args.busy, args.pages), args.view_rate,
        )  # fmt: skip
        browser.close()
    if figs is not None:
        gl = "headless Chromium with software WebGL (SwiftShader) on the same machine"
        if rates:
            figs.table(
                "rate",
                ["segments", "view pushes (goal ≥ 30 Hz)", "page receives", "page DOM shows",
                 "slider → DOM p50 / p99"],
                note=f"offline view, every segment moving at 200 Hz; {gl}; {args.seconds:g} s",
            )  # fmt: skip
            for row in rates:
                figs.row("rate", row)
        figs.table(
            "live",
            ["view pushes", "page receives", "daemon → page DOM latency p50 / p99"],
            note=f"live, 3 emulated segments; API in {got['where']}; {gl}",
        )
        figs.row("live", got["live"])
        if got["stalls"]:
            figs.table(
                "overload",
                ["page", "samples shown", "daemon → page DOM latency p50 / p99",
                 "longest showing one sample", "longest pause between two frames (> 250 ms)",
                 "a pause > 1 s over → a fresh sample shown (worst)"],
                note=f"live, 3 emulated segments, then {args.overload:g} s with {args.busy} "
                f"processes spinning and {args.pages} pages open; {gl}",
            )  # fmt: skip
            for row in got["stalls"]:
                figs.row("overload", row)
        figs.table(
            "jitter",
            ["loop jitter p99", "view closed", "view process, no page (goal ratio ≤ 1.1)",
             "view + page on this machine", "1-min load closed / view / page"],
            note=f"alternating phases of {args.seconds:g} s; API in {got['where']}; {gl}; "
            f"topology changes during the run (segments starved of CPU, seen as lost): "
            f"{got['topology_changes']}",
        )  # fmt: skip
        for row in got["runs"]:
            figs.row("jitter", row)
        figs.save()
    return 0


if __name__ == "__main__":
    sys.exit(main())

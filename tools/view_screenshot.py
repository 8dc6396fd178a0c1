"""Screenshot of `ucr view` on the running demo, for the README (docs/img/view.png).

    .venv/bin/python tools/view_screenshot.py [--out docs/img/view.png] [--after 4]
        [--timeout 120] [--what page|canvas]

Starts `ucr demo --forever` (emulated chain, daemon, API and the view in its own process), opens
the view's URL in headless Chromium (Debian's /usr/bin/chromium, software WebGL), bends the robot
into a pose through the demo's API, photographs the page and stops the demo.

It photographs only a healthy view: before the photograph it waits (``--ok-timeout``, 60 s) for
the page to show every segment ``ok`` and an update rate of at least ``--min-rate`` (20 Hz), and
otherwise fails saying what the page showed (a loaded machine gives "fault" segments and a few Hz:
not a picture for the README).

Under load a software-rendering Chromium may take long to produce a frame: each photograph may
take ``--timeout`` seconds (0: no limit), is tried again on the same page (not by restarting the
demo), and if the whole page still cannot be photographed the 3D canvas alone is (said on stderr).
"""

from __future__ import annotations

import argparse
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
ARGS = ["--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--no-sandbox"]


POSE = {
    "segment_1": {"kappa": 1.6, "phi": 0.0},
    "segment_2": {"kappa": 2.4, "phi": 2.0},
    "segment_3": {"kappa": 3.0, "phi": -1.2},
}


def pose(api_url: str, seconds: float) -> None:
    """Bend the demo robot into a pose through its API (after the demo's own script)."""
    from host.api.client import connect  # noqa: PLC0415

    with connect(api_url) as c:
        if c.status()["manual_control"]:
            c.hand_back()
        c.send_trajectory([{"time_from_start": seconds, "segments": POSE}])


def _state_line(text: str) -> str:
    """The page's ``tubes: … · update N Hz · … status: …`` figures, on one line."""
    m = re.search(r"tubes:.*?status:[^\n]*", text, re.S)
    return " ".join((m.group(0) if m else text[:200]).split())


def view_ok(text: str, segments: int, min_rate: float) -> bool:
    """Whether the page's text shows ``segments`` segments all ``ok`` and an update rate of at
    least ``min_rate`` Hz."""
    rate = re.search(r"update (\d+(?:\.\d+)?) Hz", text)
    status = re.search(r"status: ([^\n]*)", text)
    if rate is None or status is None or float(rate.group(1)) < min_rate:
        return False
    states = re.findall(r":\s*(\w+)", status.group(1))
    return len(states) == segments and all(s == "ok" for s in states)


def wait_ok(page, segments: int, min_rate: float, timeout_s: float, step_s: float = 0.5) -> str:
    """Wait until the page shows a healthy view (:func:`view_ok`); its figures, or RuntimeError
    saying what it showed instead."""
    end = time.monotonic() + timeout_s
    text = ""
    while True:
        text = page.inner_text("body")
        if view_ok(text, segments, min_rate):
            return _state_line(text)
        if time.monotonic() >= end:
            raise RuntimeError(
                f"the view did not show {segments} segments ok at >= {min_rate:g} Hz within "
                f"{timeout_s:g} s (a loaded machine?); it showed: {_state_line(text)!r}"
            )
        time.sleep(step_s)


#: Photographs of the page tried before falling back to the canvas alone.
SHOTS = 2


def photograph(page, out: str, timeout_s: float, what: str = "page", shots: int = SHOTS) -> str:
    """Write a PNG of the page (``what="page"``: the panel and the scene, as the README shows)
    or of its 3D canvas alone to ``out``; returns what was photographed. Each try may take
    ``timeout_s`` (0: no limit). When the page cannot be photographed in ``shots`` tries, the
    canvas alone is (an element screenshot: the part Chromium still renders under load)."""
    from playwright.sync_api import TimeoutError as PlaywrightTimeout  # noqa: PLC0415

    ms = max(0.0, timeout_s) * 1000.0
    if what == "page":
        for attempt in range(1, shots + 1):
            try:
                page.screenshot(path=out, timeout=ms, animations="disabled", caret="hide")
                return "page"
            except PlaywrightTimeout as exc:
                first = str(exc).splitlines()[0] if str(exc) else "timeout"
                said = f"page screenshot {attempt}/{shots} timed out ({timeout_s:g} s): {first}"
                print(f"view_screenshot: {said}", file=sys.stderr)
        print("view_screenshot: photographing the 3D canvas alone", file=sys.stderr)
    page.locator("canvas").first.screenshot(path=out, timeout=ms)
    return "canvas"


def main(argv: list[str] | None = None) -> int:
    """Up to three attempts: on a loaded machine the demo's own trajectory may abort (path
    tolerance), which ends the demo and its view."""
    for attempt in (1, 2, 3):
        try:
            return shoot(argv)
        except Exception as exc:  # noqa: BLE001 - reported, then retried
            print(f"view_screenshot: attempt {attempt} failed: {exc}", file=sys.stderr)
    return 1


def options(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(ROOT / "docs" / "img" / "view.png"))
    ap.add_argument("--after", type=float, default=2.5, help="s to move into the pose")
    ap.add_argument("--chromium", default="/usr/bin/chromium")
    ap.add_argument(
        "--timeout", type=float, default=120.0,
        help="s each screenshot may take (0: no limit; default 120)",
    )  # fmt: skip
    ap.add_argument(
        "--what", choices=("page", "canvas"), default="page",
        help="the whole page (panel and scene, as in the README) or the 3D canvas alone",
    )  # fmt: skip
    ap.add_argument(
        "--min-rate", type=float, default=20.0,
        help="update rate (Hz) the page must show before it is photographed (20)",
    )  # fmt: skip
    ap.add_argument(
        "--ok-timeout", type=float, default=60.0,
        help="s to wait for every segment ok and --min-rate (60), else fail",
    )  # fmt: skip
    return ap.parse_args(argv)


def shoot(argv: list[str] | None = None) -> int:
    args = options(argv)
    from playwright.sync_api import sync_playwright  # noqa: PLC0415 - dev tool

    demo = subprocess.Popen(
        [sys.executable, "-m", "tools.cli", "demo", "--forever", "--quiet-log"],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    url: list[str] = []
    log: list[str] = []
    api: list[str] = []

    def read() -> None:
        assert demo.stdout is not None
        for line in demo.stdout:
            log.append(line.rstrip())
            if line.startswith("view on ") and not url:
                url.append(line.split()[2])
            elif line.startswith("API on ") and not api:
                api.append(line.split()[2])

    threading.Thread(target=read, daemon=True).start()
    try:
        end = time.monotonic() + 120
        while not url and demo.poll() is None and time.monotonic() < end:
            time.sleep(0.1)
        if not url:
            raise RuntimeError("the demo printed no view URL")
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=args.chromium, args=ARGS)
            page = browser.new_page(viewport={"width": 1280, "height": 760})
            page.goto(url[0])
            page.get_by_text("tubes:").wait_for(timeout=60000)
            # pose only once the demo's own script is over (it would refuse to share the robot)
            end = time.monotonic() + 120
            while "== running until Ctrl-C" not in log and time.monotonic() < end:
                time.sleep(0.2)
            page.get_by_text("tubes: 3").wait_for(timeout=30000)
            pose(api[0], args.after)
            time.sleep(1.0)
            said = wait_ok(page, len(POSE), args.min_rate, args.ok_timeout)
            print(f"view_screenshot: {said}", file=sys.stderr)
            # the "software WebGL" notice of headless Chromium is not part of the view
            page.evaluate(
                "document.querySelectorAll('[class*=Notification-root]').forEach(e => e.remove())"
            )
            Path(args.out).parent.mkdir(parents=True, exist_ok=True)
            shot = photograph(page, args.out, args.timeout, args.what)
            browser.close()
        print(f"wrote {args.out} ({shot})")
        return 0
    except Exception:
        print("view_screenshot: the demo said:", *log[-4:], sep="\n  ", file=sys.stderr)
        raise
    finally:
        demo.send_signal(signal.SIGINT)
        try:
            demo.wait(20)
        except subprocess.TimeoutExpired:
            demo.kill()


if __name__ == "__main__":
    sys.exit(main())

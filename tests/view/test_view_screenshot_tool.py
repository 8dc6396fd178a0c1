"""tools/view_screenshot.py (the README's picture of the view): under load Chromium's page
screenshot timed out at Playwright's fixed 30 s on every attempt, with no option to change it.
Now the time is an option, a timed-out screenshot is tried again on the same page, and the 3D
canvas alone is photographed as a last resort (it still rendered when the page did not)."""

from __future__ import annotations

import pytest

pytestmark = pytest.mark.timeout(120)
PNG = b"\x89PNG\r\n\x1a\n"


def test_the_screenshot_timeout_is_an_option_and_a_timed_out_page_falls_back(tmp_path, capsys):
    pytest.importorskip("playwright", reason="playwright is not installed")
    from playwright.sync_api import TimeoutError as PlaywrightTimeout

    from tools import view_screenshot as tool

    assert tool.options([]).timeout == 120.0 and tool.options([]).what == "page"
    opts = tool.options(["--timeout", "0", "--what", "canvas"])
    assert opts.timeout == 0.0 and opts.what == "canvas"
    calls: list[tuple[str, float]] = []

    class Canvas:
        def screenshot(self, path: str, timeout: float) -> None:
            calls.append(("canvas", timeout))
            with open(path, "wb") as f:
                f.write(PNG)

    class Locator:
        first = Canvas()

    class LoadedPage:  # a page Chromium renders no frame of in time
        def screenshot(self, path: str, timeout: float, **kw) -> None:
            calls.append(("page", timeout))
            raise PlaywrightTimeout(f"Timeout {timeout:.0f}ms exceeded.")

        def locator(self, selector: str) -> Locator:
            assert selector == "canvas"
            return Locator()

    out = tmp_path / "view.png"
    assert tool.photograph(LoadedPage(), str(out), 45.0) == "canvas"
    assert calls == [("page", 45000.0), ("page", 45000.0), ("canvas", 45000.0)]
    assert out.read_bytes() == PNG
    assert "photographing the 3D canvas alone" in capsys.readouterr().err


def test_the_screenshot_tool_photographs_a_real_page(browser, tmp_path):
    from tools import view_screenshot as tool

    page = browser.new_page(viewport={"width": 320, "height": 200})
    try:
        page.set_content("<p>tubes: 3</p><canvas width='80' height='60'></canvas>")
        out = tmp_path / "page.png"
        assert tool.photograph(page, str(out), 60.0) == "page"
        assert out.read_bytes().startswith(PNG)
        assert tool.photograph(page, str(out), 60.0, what="canvas") == "canvas"
        assert out.read_bytes().startswith(PNG)
    finally:
        page.close()

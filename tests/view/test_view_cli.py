"""`ucr view` on the terminal: a port in use and an offline FILE that is missing, not a file or
broken say so in one line (or show the file's check errors), never serve as if all were fine."""

from __future__ import annotations

import shutil
import socket
import subprocess
import sys
import time

import pytest

pytest.importorskip("viser", reason="the view extra (viser) is not installed")

from view_helpers import ROBOT, ROOT, wait_for  # noqa: E402

pytestmark = pytest.mark.timeout(180)


def _view(*argv: str, timeout: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "tools.cli", "view", *argv], cwd=ROOT,
                          capture_output=True, text=True, timeout=timeout)  # fmt: skip


def test_a_port_in_use_is_named_as_such():
    """Defect: "viser started 2 guarded web servers instead of 1 (its internals changed…)"."""
    from view.app import ViewApp
    from view.source import OfflineSource

    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        with pytest.raises(OSError, match=f"^port {port} already in use$"):
            ViewApp(OfflineSource(ROBOT), port=port)
        res = _view(str(ROBOT), "--offline", "--port", str(port))
    assert res.returncode == 1 and "Traceback" not in res.stderr, res.stderr
    assert res.stderr.strip().splitlines() == [
        f"ucr: cannot serve the view on 127.0.0.1:{port}: port {port} already in use"
    ]


@pytest.mark.parametrize("kind", ["missing", "directory"])
def test_offline_on_a_path_that_is_not_a_file_is_one_line(tmp_path, kind):
    """Defect: the URL was printed and the page served as if the file were fine."""
    path = tmp_path / "nothing.ucrdf"
    if kind == "directory":
        path.mkdir()
    res = _view(str(path), "--offline", "--port", "0")
    assert res.returncode == 1 and "Traceback" not in res.stderr, res.stderr
    what = "no such file" if kind == "missing" else "not a file"
    assert res.stderr.strip().splitlines() == [f"ucr: {path}: {what}" + (
        " (a directory)" if kind == "directory" else "")]  # fmt: skip
    assert "http://" not in res.stdout


def test_offline_on_a_broken_file_prints_its_check_errors_and_reloads_on_save(tmp_path):
    """Defect: a file that does not parse showed its errors on the page only; the terminal said
    nothing. The authoring aid stays: it serves anyway and picks the fixed file up on save."""
    path = tmp_path / "robot.ucrdf"
    path.write_text("this is not XML\n")
    proc = subprocess.Popen(
        [sys.executable, "-m", "tools.cli", "view", str(path), "--offline", "--port", "0"],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    err: list[str] = []
    try:
        import threading

        threading.Thread(target=lambda: err.extend(proc.stderr), daemon=True).start()
        assert wait_for(lambda: any("check error" in e for e in err), 60), err
        assert any(e.startswith(f"{path}:1: XML syntax error") for e in err), err
        time.sleep(0.5)
        shutil.copy(ROBOT, path)  # fixed: the running view loads it
        assert wait_for(lambda: any(e.strip() == f"ucr view: {path} loads again" for e in err),
                        30), err  # fmt: skip
        assert proc.poll() is None  # still serving
    finally:
        proc.terminate()
        proc.communicate(timeout=30)
    assert not any("Traceback" in e for e in err), err


def test_the_offline_source_reports_check_errors_when_they_change(tmp_path):
    from view.source import OfflineSource

    path = tmp_path / "robot.ucrdf"
    shutil.copy(ROBOT, path)
    seen: list[list[str]] = []
    src = OfflineSource(path, poll_s=0.05, on_errors=seen.append).start()
    try:
        assert seen == []  # a good file: nothing to say
        # (a poll can land between an editor's truncate and write: an empty file is one more
        # change, reported as such; only the state after each save is asserted)
        path.write_text("<robot")
        assert wait_for(lambda: bool(seen) and "Couldn't find end" in " ".join(seen[-1]), 10)
        assert seen[-1][0].startswith(f"{path}:"), seen
        shutil.copy(ROBOT, path)
        assert wait_for(lambda: seen[-1] == [], 10), seen
    finally:
        src.stop()

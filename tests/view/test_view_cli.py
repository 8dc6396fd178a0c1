"""`ucr view` on the terminal: a port in use and an offline FILE that is missing, not a file or
broken say so in one line (or show the file's check errors), never serve as if all were fine."""

from __future__ import annotations

import errno
import re
import shutil
import signal
import socket
import subprocess
import sys
import time

import pytest

from tests.cli_run import run_ucr

pytest.importorskip("viser", reason="the view extra (viser) is not installed")

from view_helpers import ROBOT, ROOT, wait_for  # noqa: E402

pytestmark = pytest.mark.timeout(180)


def _view(*argv: str, timeout: float = 60) -> subprocess.CompletedProcess:
    return run_ucr("view", *argv, timeout=timeout)


def test_a_port_in_use_is_named_as_such():
    """Defect: "viser started 2 guarded web servers instead of 1 (its internals changed…)"."""
    from view.app import ViewApp
    from view.source import OfflineSource

    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        said = (f"cannot listen on 127.0.0.1:{port}: address already in use (another program "
                "uses the port: --port P, or 0 for any free port)")  # fmt: skip
        with pytest.raises(OSError, match=re.escape(said)):
            ViewApp(OfflineSource(ROBOT), port=port)
        res = _view(str(ROBOT), "--offline", "--port", str(port))
    assert res.returncode == 1 and "Traceback" not in res.stderr, res.stderr
    assert res.stderr.strip().splitlines() == [f"ucr: cannot serve the view: {said}"]


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


@pytest.mark.parametrize(("sig", "code"), [(signal.SIGINT, 130), (signal.SIGTERM, 0)])
def test_ctrl_c_exits_130_and_sigterm_0_both_closing_the_view(sig, code):
    """Defect: SIGTERM (the demo stops its view so) killed the view without closing it, exit
    -15; Ctrl-C left through a KeyboardInterrupt. The rule of every ucr command: 0 after
    SIGTERM, 130 after Ctrl-C, the view closed either way (docs/view.md)."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "tools.cli", "view", str(ROBOT), "--offline", "--port", "0"],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        assert line.startswith("ucr view: http://127.0.0.1:"), line
        port = int(line.split(":")[3].split("/")[0])
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == code, err
    assert "Traceback" not in err, err
    with socket.socket() as s:  # closed: its port is free again
        s.bind(("127.0.0.1", port))


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


@pytest.mark.parametrize("kind", ["readable by others", "too short"])
def test_a_token_file_is_checked_as_every_client_checks_it(tmp_path, kind):
    """Defect: `ucr view --token-file` read any file (read_text, no mode check); docs/api.md
    says token files are 0600 and `ucr status` & co refuse others (host.api.auth.read_token_file).
    Same check, same one line as `ucr status`, before any connection is tried."""
    path = tmp_path / "api.token"
    path.write_text("a-good-long-token-value-0123456789\n" if kind != "too short" else "short\n")
    path.chmod(0o644 if kind == "readable by others" else 0o600)
    url = "ws://127.0.0.1:9"  # nothing listens: a token that passed would get "cannot reach"
    view = _view("--url", url, "--token-file", str(path), "--port", "0")
    status = subprocess.run([sys.executable, "-m", "tools.cli", "status", "--url", url,
                             "--token-file", str(path)], cwd=ROOT, capture_output=True,
                            text=True, timeout=60)  # fmt: skip
    assert view.returncode == status.returncode == 1, (view.stderr, status.stderr)
    assert view.stderr.strip().splitlines() == status.stderr.strip().splitlines(), view.stderr
    assert str(path) in view.stderr and "http://" not in view.stdout
    if kind == "readable by others":
        assert "mode 0644" in view.stderr and f"chmod 600 {path}" in view.stderr


@pytest.fixture
def silent_daemon():
    """A WebSocket server that accepts the handshake and never answers: a daemon too slow."""
    import threading

    from websockets.sync.server import serve

    def handler(ws):
        for _ in ws:
            pass

    with serve(handler, "127.0.0.1", 0) as srv:
        threading.Thread(target=srv.serve_forever, daemon=True).start()
        yield f"ws://127.0.0.1:{srv.socket.getsockname()[1]}"
        srv.shutdown()


def test_a_daemon_that_does_not_answer_in_time_is_one_line(silent_daemon):
    """Defect: the API client's timeout error (a TimeoutError, not a ConnectionError) was not
    caught: a slow daemon gave a traceback. Now one line, as `ucr status` says it."""
    res = _view("--url", silent_daemon, "--port", "0")  # the default reply timeout, 5 s
    assert res.returncode == 1 and "Traceback" not in res.stderr, res.stderr
    assert res.stderr.strip().splitlines() == ["ucr: timeout: no reply to 'topology' within 5 s"]
    assert "http://" not in res.stdout


def test_with_a_file_a_daemon_too_slow_falls_back_to_the_file(silent_daemon):
    """As for an unreachable daemon: offline on FILE, saying why (--timeout: reply timeout)."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "tools.cli", "view", str(ROBOT), "--url", silent_daemon,
         "--timeout", "0.5", "--port", "0"],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        assert line.startswith("ucr view: http://127.0.0.1:") and "(offline;" in line, line
    finally:
        proc.terminate()
        _, err = proc.communicate(timeout=30)
    said = "the daemon does not answer (timeout: no reply to 'topology' within 0.5 s)"
    assert f"ucr view: {said}; offline on" in err
    assert "Traceback" not in err, err


@pytest.mark.parametrize("mode", [["--offline"], ["--url", "http://127.0.0.1:9"]])
def test_a_port_out_of_range_is_a_usage_error(mode):
    """Defect: viser's thread died (OverflowError: a traceback) and the view hung until Ctrl-C."""
    res = _view(str(ROBOT), *mode, "--port", "70000", timeout=30)
    assert res.returncode == 2 and "Traceback" not in res.stderr, res.stderr
    assert "argument --port: must be a port 0..65535" in res.stderr
    assert "http://" not in res.stdout


def test_an_address_not_on_this_machine_is_one_line():
    """Defect: "serving on 192.0.2.55 (not loopback)…", then nothing: viser retried ports
    forever and its constructor never returned."""
    res = _view(str(ROBOT), "--offline", "--host", "192.0.2.55", "--port", "8123", timeout=30)
    assert res.returncode == 1 and "Traceback" not in res.stderr, res.stderr
    # (before: "... on 192.0.2.55:8123: [Errno 99] Cannot assign requested address")
    said = (
        "ucr: cannot serve the view: cannot listen on 192.0.2.55:8123: cannot assign requested "
        "address (not an address of this machine)"
    )
    assert res.stderr.strip().splitlines() == [said]
    assert "http://" not in res.stdout


def test_check_listen_refuses_what_viser_could_not_serve():
    from host.listen import ListenError, check_listen

    with pytest.raises(ListenError, match="^port must be 0..65535, got 70000$"):
        check_listen("127.0.0.1", 70000)  # (getaddrinfo took it as port 4464)
    with pytest.raises(ListenError, match="not an address of this machine") as got:
        check_listen("192.0.2.55", 0)
    assert got.value.errno == errno.EADDRNOTAVAIL
    with socket.socket() as busy:  # in use: the hint names the option that sets the port
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        with pytest.raises(ListenError, match="--view-port P, or 0 for any free port"):
            check_listen("127.0.0.1", port, "--view-port")
    check_listen("127.0.0.1", 0)


def test_a_negative_nice_is_a_usage_error():
    """Defect: ``--nice -5`` was accepted and silently ignored (only lowering is offered)."""
    res = _view(str(ROBOT), "--offline", "--nice", "-5", "--port", "0", timeout=30)
    assert res.returncode == 2 and "Traceback" not in res.stderr, res.stderr
    assert "argument --nice: must be >= 0, got -5: the view only lowers its priority" in res.stderr

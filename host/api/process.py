"""The API server in a process of its own, bridged to the daemon over a socket pair.

Why: in the daemon's process the WebSocket server shares the interpreter lock with the control
loop, and 200 clients polling ``status`` at 10 Hz cost the loop its rate (issue 12). In its own
process the server's CPU time never delays a cycle: the daemon's side of the bridge
(``host.api.bridge.DaemonBridge``) only answers RPCs, forwards each published message once and
sends a status snapshot every 50 ms.

``ApiProcess`` (daemon side) validates the configuration in the daemon first (clear errors before
anything starts), starts ``python -m host.api.process FD``, sends it the configuration over the
socket (tokens never appear on a command line or in the environment), waits until it listens, and
restarts it with back-off if it ever dies. The child exits when the daemon's side closes.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from typing import Any

from host.api import DEFAULT_HOST, DEFAULT_PORT
from host.api.auth import Token
from host.api.bridge import BridgeClosed, DaemonBridge, DaemonLink, recv_frame, send_frame
from host.api.memory import RELEASE_AFTER_GROWTH

log = logging.getLogger("ucr.api")
API_NICE = 5  # scheduling priority of the API process relative to the daemon (nice increment)
TERM_GRACE_S = 3.0  # s the API process waits, after SIGTERM, for the daemon to stop it


def child_env() -> dict[str, str]:
    """The API process's environment: the daemon's, with CPython's small objects on the C
    allocator (``PYTHONMALLOC=malloc``) unless the user chose an allocator. With CPython's own
    arenas a few objects that outlive a flood of connections or requests pin whole 1 MiB arenas,
    and the janitor's ``malloc_trim`` returns nothing of them (docs/api.md "Memory"); on the C
    allocator it returns the free pages."""
    env = dict(os.environ)
    env.setdefault("PYTHONMALLOC", "malloc")
    return env


def _options_json(options: dict[str, Any]) -> dict[str, Any]:
    out = dict(options)
    if "tokens" in out:
        out["tokens"] = [[t.value, t.scope, t.label] for t in out["tokens"]]
    for k in ("origins", "names"):
        if k in out:
            out[k] = list(out[k])
    return out


def _options_from_json(data: dict[str, Any]) -> dict[str, Any]:
    out = dict(data)
    if "tokens" in out:
        out["tokens"] = tuple(Token(*t) for t in out["tokens"])
    for k in ("origins", "names"):
        if k in out:
            out[k] = tuple(out[k])
    return out


class ApiProcess:
    """The API server in its own process (see module docstring); ``start()`` / ``stop()``."""

    def __init__(
        self,
        daemon: Any,
        host: str = DEFAULT_HOST,
        port: int = DEFAULT_PORT,
        token: str | None = None,
        *,
        log_level: str = "info",
        **options: Any,
    ) -> None:
        from host.api.server import ApiServer  # noqa: PLC0415 - validation only

        ApiServer(None, host, port, token, **options)  # raises ApiServerError on a bad config
        self.daemon = daemon
        self.host = host
        self.port: int | None = None
        self.url = ""
        self._config = {
            "host": host,
            "port": port,
            "token": token,
            "options": _options_json(options),
            "log_level": log_level,
        }
        self._child: subprocess.Popen | None = None
        self._bridge: DaemonBridge | None = None
        self._stopping = threading.Event()
        self._monitor: threading.Thread | None = None
        self.restarts = 0

    def start(self, timeout: float = 20.0) -> ApiProcess:
        """Start the child and wait until it listens; ApiServerError if it cannot."""
        self._spawn(timeout)
        self._monitor = threading.Thread(target=self._watch, name="ucr-api-watch", daemon=True)
        self._monitor.start()
        return self

    def _spawn(self, timeout: float) -> None:
        from host.api.server import ApiServerError  # noqa: PLC0415

        ours, theirs = socket.socketpair()
        try:
            child = subprocess.Popen(
                [sys.executable, "-m", "host.api.process", str(theirs.fileno())],
                pass_fds=[theirs.fileno()],
                env=child_env(),
                stdin=subprocess.DEVNULL,
                # a process group of its own: a terminal's Ctrl-C (sent to the foreground group)
                # reaches the daemon, which stops the API in order; before, it also reached the
                # API process, and while it still imported (seconds on a loaded Pi) it died
                # and the daemon reported "API process did not start" and exited 1
                process_group=0,
            )
        finally:
            theirs.close()
        lock = threading.Lock()
        config = dict(self._config)
        if self.port and not config["port"]:
            config["port"] = self.port  # a restart keeps the port clients know
        try:
            send_frame(ours, lock, b"C", json.dumps(config).encode())
            ours.settimeout(timeout)
            kind, body = recv_frame(ours)
            ours.settimeout(None)
            ready = json.loads(body) if kind == b"Y" else {"ok": False, "error": "no answer"}
        except (OSError, BridgeClosed, ValueError) as exc:
            ready = {"ok": False, "error": f"API process did not start: {exc}"}
        if not ready.get("ok"):
            ours.close()
            with contextlib.suppress(OSError):
                child.kill()
            child.wait(5)
            raise ApiServerError(str(ready.get("error")))
        self.port, self.url = ready["port"], ready["url"]
        self._child = child
        self._bridge = DaemonBridge(self.daemon, ours).start()
        log.info("API process %d listening on %s", child.pid, self.url)

    def _watch(self) -> None:
        backoff = 1.0
        while not self._stopping.is_set():
            bridge, child = self._bridge, self._child
            if bridge is None or child is None:
                return
            if not bridge.closed.wait(0.5):
                continue
            if self._stopping.is_set():
                return
            bridge.stop()
            with contextlib.suppress(subprocess.TimeoutExpired):
                child.wait(2)
            log.error("API process exited (code %s); restarting in %.0f s", child.poll(), backoff)
            if self._stopping.wait(backoff):
                return
            try:
                self._spawn(20.0)
                self.restarts += 1
                backoff = 1.0
            except Exception as exc:  # noqa: BLE001 - try again later
                log.error("API process restart failed: %s", exc)
                backoff = min(30.0, backoff * 2)

    def stop(self, timeout: float = 5.0) -> None:
        """Close the bridge (the child exits on its own), then make sure it is gone."""
        self._stopping.set()
        if self._bridge is not None:
            self._bridge.stop()
        child = self._child
        if child is not None:
            try:
                child.wait(timeout)
            except subprocess.TimeoutExpired:
                child.terminate()
                try:
                    child.wait(2)
                except subprocess.TimeoutExpired:
                    child.kill()
        if self._monitor is not None and self._monitor is not threading.current_thread():
            self._monitor.join(2)

    @property
    def pid(self) -> int | None:
        return self._child.pid if self._child is not None else None

    def stats(self) -> dict:
        bridge = self._bridge
        return {"pid": self.pid, "restarts": self.restarts, **(bridge.counters if bridge else {})}


def main(argv: list[str] | None = None) -> int:
    """Child entry point: ``python -m host.api.process FD``."""
    from host.api.server import ApiServer, ApiServerError  # noqa: PLC0415

    args = sys.argv[1:] if argv is None else argv
    sock = socket.socket(fileno=int(args[0]))
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the daemon decides when the API ends
    try:
        os.nice(API_NICE)  # when CPU is short, the control loop's process goes first
        nice_error = None
    except OSError as exc:  # e.g. a seccomp filter without setpriority (host/ucr-daemon.service)
        nice_error = exc
    lock = threading.Lock()
    try:
        kind, body = recv_frame(sock)
        config = json.loads(body)
    except (BridgeClosed, OSError, ValueError):
        return 1
    logging.basicConfig(
        level=getattr(logging, str(config.get("log_level", "info")).upper(), logging.INFO),
        format="%(asctime)s %(levelname)s %(name)s[api]: %(message)s",
    )
    if nice_error is not None:
        logging.getLogger("ucr.api").warning(
            "could not lower the API process's priority by %d (%s): it competes with the "
            "control loop at the daemon's priority",
            API_NICE,
            nice_error,
        )
    link = DaemonLink(sock)
    options = _options_from_json(config["options"])
    options.setdefault("release_after_growth", RELEASE_AFTER_GROWTH)  # alone in this process
    try:
        server = ApiServer(link, config["host"], config["port"], config["token"], **options).start(
            timeout=15
        )
    except (ApiServerError, OSError) as exc:
        send_frame(sock, lock, b"Y", json.dumps({"ok": False, "error": str(exc)}).encode())
        return 1
    ready = json.dumps({"ok": True, "url": server.url, "port": server.port}).encode()
    server.call_in_loop(link.send_raw, b"Y", ready)
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    while not stop.wait(0.5) and not link.closed:
        pass
    # SIGTERM usually reaches the daemon too (systemd, a terminal's process group): give it the
    # time to stop the API itself, so it does not take this exit for a crash and restart it
    deadline = time.monotonic() + TERM_GRACE_S
    while not link.closed and time.monotonic() < deadline:
        time.sleep(0.05)
    server.stop()
    link.close()
    return 0


def start_api_process(daemon: Any, *args: Any, **kwargs: Any) -> ApiProcess:
    """Create and start an :class:`ApiProcess`."""
    return ApiProcess(daemon, *args, **kwargs).start()


if __name__ == "__main__":
    raise SystemExit(main())

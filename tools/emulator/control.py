"""Line commands that control a running emulated chain (``ucr emulate`` stdin and unix socket).

Positions here are what a user sees: 1-based, like segment names (``segment_1`` is the one next to
the host) and the rest of the CLI. :class:`tools.emulator.EmulatedChain`'s Python API stays
0-based (``chain.unplug(0)`` is link 1); this module converts at its edge, in both directions.
"""

from __future__ import annotations

import os
import socket
import threading
from pathlib import Path

from tools.emulator.chain import EmulatedChain, EmulatorError

HELP = """commands (k = link/segment position, 1 = the one next to the host):
  status                 links (plug, baud, latency, corruption, counters) and segments
  unplug k | plug k      pull / plug the cable between segment k and its upstream side
  baud k RATE|off        throttle link k to RATE bit/s (10 bits per byte), or remove the throttle
                         (a byte-time model: the daemon slows its loop to what the link carries)
  latency k SECONDS      add a fixed delay to link k (both ways, 0..60 s; bytes in flight follow)
  corrupt k RATE         corrupt each byte on link k with probability RATE (0..1)
  restart k              reboot segment k (kill its process; it restarts)
  off k | on k           power segment k off / on
  silence on|off         the host's bytes stop reaching segment 1 (watchdog test)
  inject k HEX           put raw bytes (hex) on link k, travelling down
  repl k                 last lines segment k printed on its REPL
  help                   this text"""


def _k(chain: EmulatedChain, word: str) -> int:
    """The 0-based index of the user's 1-based position ``word``."""
    try:
        k = int(word)
    except ValueError:
        raise EmulatorError(f"position must be an integer, got {word!r}") from None
    if not 1 <= k <= chain.n:
        raise EmulatorError(f"position must be 1..{chain.n}, got {k}")
    return k - 1


def _float(word: str, what: str) -> float:
    try:
        return float(word)
    except ValueError:
        raise EmulatorError(f"{what} must be a number, got {word!r}") from None


def firmware_state(repl: str, position: int) -> str:
    """What a running segment process's firmware did, from its REPL output: "firmware up" (its
    `[main] segment … up` line last), "firmware stopped: <error>" (a traceback after it: the
    VM then sits at the REPL, so the process alone looks alive), or "firmware starting"."""
    up = repl.rfind("[main] segment")
    err = repl.rfind("Traceback (most recent call last)")
    if err > up:
        lines = [ln.strip() for ln in repl[err:].splitlines()]
        lines = [ln for ln in lines if ln and not ln.startswith((">>>", "..."))]
        return f"firmware stopped: {lines[-1][:120]} (see 'repl {position}')"
    return "firmware up" if up >= 0 else "firmware starting"


def status_text(chain: EmulatedChain) -> str:
    st = chain.stats()
    lines = [f"host port: {st['host_port']}" + ("  (host silenced)" if st["host_silenced"] else "")]
    for link, seg in zip(st["links"], st["segments"], strict=True):
        d = link["down"]
        u = link["up"]
        baud = f"{d['baud']} bd" if d["baud"] else "unthrottled"
        lines.append(
            f"link {link['index'] + 1}: {'plugged' if link['plugged'] else 'UNPLUGGED'}, {baud}, "
            f"latency {d['latency_s'] * 1000:g} ms, corrupt {d['corrupt_rate']:g}; "
            f"in flight {d['in_flight'] + u['in_flight']} B; "
            f"down {d['bytes_out']} B (dropped {d['dropped']}, corrupted {d['corrupted']}), "
            f"up {u['bytes_out']} B (dropped {u['dropped']}, corrupted {u['corrupted']})"
        )
        state = "running" if seg["running"] else ("off" if not seg["powered"] else "restarting")
        if seg["running"]:
            state += ", " + firmware_state(chain.repl_output(seg["index"]), seg["index"] + 1)
        lines.append(
            f"  segment {seg['index'] + 1}: uid {seg['uid']}, {state}, pid {seg['pid']}, "
            f"restarts {seg['restarts']}, REPL {seg['repl_port']}"
        )
    return "\n".join(lines)


def execute(chain: EmulatedChain, line: str) -> str:
    """Run one command line; return the answer text (errors start with 'error:')."""
    words = line.split()
    if not words:
        return ""
    cmd, args = words[0].lower(), words[1:]
    try:
        if cmd in ("help", "?"):
            return HELP
        if cmd == "status":
            return status_text(chain)
        need = {
            "unplug": 1,
            "plug": 1,
            "baud": 2,
            "latency": 2,
            "corrupt": 2,
            "restart": 1,
            "off": 1,
            "on": 1,
            "silence": 1,
            "inject": 2,
            "repl": 1,
        }
        if cmd not in need:
            return f"error: unknown command {cmd!r} (try 'help')"
        if len(args) != need[cmd]:
            return f"error: {cmd} takes {need[cmd]} argument(s) (try 'help')"
        if cmd == "silence":
            if args[0] not in ("on", "off"):
                return "error: silence on|off"
            if args[0] == "on":
                chain.kill_host_link()
            else:
                chain.restore_host_link()
            return f"host silence {args[0]}"
        k = _k(chain, args[0])
        u = k + 1  # as the user wrote it
        if cmd == "unplug":
            chain.unplug(k)
            return f"link {u} unplugged"
        if cmd == "plug":
            chain.plug(k)
            return f"link {u} plugged"
        if cmd == "baud":
            if args[1].lower() in ("off", "none"):
                chain.set_link(k, baud=None)
                return f"link {u} unthrottled"
            try:
                rate = int(args[1])
            except ValueError:
                return f"error: baud must be an integer or 'off', got {args[1]!r}"
            if rate <= 0:
                return f"error: baud must be > 0 bit/s, or 'off' for no throttle, got {rate}"
            chain.set_link(k, baud=rate)
            return f"link {u} throttled to {rate} bit/s"
        if cmd == "latency":
            chain.set_link(k, latency=_float(args[1], "latency"))
            return f"link {u} latency {args[1]} s"
        if cmd == "corrupt":
            chain.set_link(k, corrupt_rate=_float(args[1], "rate"))
            return f"link {u} corrupts bytes with probability {args[1]}"
        if cmd == "restart":
            chain.restart(k)
            return f"segment {u} restarted"
        if cmd == "off":
            chain.power_off(k)
            return f"segment {u} off"
        if cmd == "on":
            chain.power_on(k)
            return f"segment {u} on"
        if cmd == "inject":
            try:
                data = bytes.fromhex(args[1])
            except ValueError:
                return f"error: not hex: {args[1]!r}"
            chain.inject(k, data)
            return f"{len(data)} bytes injected on link {u}"
        if cmd == "repl":
            return chain.repl_output(k)[-2000:]
    except EmulatorError as exc:
        return f"error: {exc}"
    return f"error: unhandled command {cmd!r}"


#: The longest path a unix socket address holds (Linux: 108 bytes with the final NUL).
MAX_SOCKET_PATH = 107


def socket_path_problem(path: str | os.PathLike) -> str | None:
    """Why a control socket cannot listen on ``path``, else None. A socket file nobody listens
    on (left by an emulator that was killed) may be replaced; one that accepts a connection is
    another emulator's control socket (or another program's), and anything else is not ours."""
    p = Path(path)
    if len(os.fsencode(p)) > MAX_SOCKET_PATH:
        return f"{p}: too long for a unix socket (at most {MAX_SOCKET_PATH} bytes)"
    if not p.parent.is_dir():
        return f"{p}: no such directory {p.parent}"
    if not os.access(p.parent, os.W_OK | os.X_OK):
        return f"{p}: cannot create it (the directory {p.parent} is not writable)"
    if not os.path.lexists(p):
        return None
    if not p.is_socket():
        return f"{p} exists and is not a socket (not replaced): choose another path"
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as probe:
        probe.settimeout(2.0)
        try:
            probe.connect(str(p))
        except ConnectionRefusedError:
            return None  # stale: nobody listens
        except OSError as exc:
            return f"{p}: cannot tell whether something listens on it ({exc}): choose another path"
    return (
        f"{p} is the control socket of a running emulator (or another program): choose another path"
    )


class ControlSocket:
    """A unix socket server: one command per line, each answer followed by an empty line."""

    def __init__(self, chain: EmulatedChain, path: str | os.PathLike) -> None:
        self.chain = chain
        self.path = Path(path)
        why = socket_path_problem(self.path)
        if why:
            raise EmulatorError(why)
        if os.path.lexists(self.path):
            self.path.unlink()  # a stale socket: nobody listens on it
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            self._sock.bind(str(self.path))
            self._sock.listen(4)
        except OSError as exc:
            self._sock.close()
            raise EmulatorError(f"{self.path}: cannot listen on it ({exc.strerror})") from None
        self._closed = False
        self._thread = threading.Thread(
            target=self._serve, name="ucr-emulator-control", daemon=True
        )
        self._thread.start()

    def _serve(self) -> None:
        while not self._closed:
            try:
                conn, _ = self._sock.accept()
            except OSError:
                return
            threading.Thread(target=self._client, args=(conn,), daemon=True).start()

    def _client(self, conn: socket.socket) -> None:
        with conn, conn.makefile("rwb") as f:
            for raw in f:
                line = raw.decode(errors="replace").strip()
                if line in ("quit", "exit"):
                    return
                f.write((execute(self.chain, line) + "\n\n").encode())
                f.flush()

    def close(self) -> None:
        self._closed = True
        try:
            self._sock.close()
        finally:
            try:
                self.path.unlink()
            except OSError:
                pass

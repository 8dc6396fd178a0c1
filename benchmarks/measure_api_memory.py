"""What large client frames cost the API server's memory (docs/api.md, "Limits"): measured, not
asserted (the machine may be shared; tests/host/test_api_abuse.py asserts the bound itself by
counting the buffers).

    .venv/bin/python benchmarks/measure_api_memory.py [--conns 200] [--frames 4]
        [--deflate] [--subscribers 0] [--connection-flood 0]
        [--url URL --pid PID [--token-file FILE]]

``--conns`` connections each send ``--frames`` text frames of 1 MiB (the frame size limit)
with permessage-deflate offered (~1 KiB each on the wire when the server agrees), hold the
connection 5 s, then go; the server process's resident size is reported before, at its peak
(VmHWM) and after, with the server's counts (``inbound_peak``: the most request bytes its
connections held at once; ``inbound_closed``: connections closed for holding the most).

By default the server is an API server (``host.api.server.ApiServer``, this tree's code) in a
process of its own, in front of the in-memory facade of test_api_protocol.py. ``--deflate``
runs that server as it was before the review, with permessage-deflate (for the comparison).
``--url``/``--pid`` measure a running daemon's API process instead (``pgrep -P <daemon pid>``).
``--subscribers N`` instead measures the outbound side: N clients subscribed to joint_states at
100 Hz for 10 s, the server's CPU time and the bytes it wrote (with and without ``--deflate``).
``--connection-flood N`` measures a connection flood instead: N connections opened at once, each
sending 16 subscriptions (joint_states, transforms, events, topology at up to 1000 Hz) and never
reading, held 6 s, then aborted; resident size before, during, 6 s in and 10 s after, with how
many got through and the server's ``evicted_pending`` (docs/api.md "Memory after a connection
flood").
"""

from __future__ import annotations

import argparse
import asyncio
import collections
import json
import os
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

_SERVER = r"""
import functools, importlib.util, json, sys
sys.path.insert(0, {repo!r})
spec = importlib.util.spec_from_file_location("stub", {stub!r})
mod = importlib.util.module_from_spec(spec); spec.loader.exec_module(mod)
import host.api.server as server
if {deflate!r}:  # the server as before the review: permessage-deflate on
    serve = server.serve
    server.serve = lambda *a, **kw: serve(*a, **{{**kw, "compression": "deflate"}})
stub = mod.FacadeStub(publish_hz=100.0)
srv = server.ApiServer(stub, "127.0.0.1", 0, **{options!r}).start()
print(srv.port, flush=True)
import queue
for line in sys.stdin:
    done = queue.Queue()
    srv.call_in_loop(lambda: done.put(srv.stats()))
    print(json.dumps(done.get(timeout=10)), flush=True)
"""


def _status(pid: int, key: str) -> int:
    """A /proc/PID/status figure in KiB (VmRSS, VmHWM)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1])
    return 0


def _cpu_s(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _mib(kib: int) -> str:
    return f"{kib / 1024:.0f} MiB"


async def _flood(url: str, headers: dict | None, frames: int, kib: int) -> str:
    from websockets.asyncio.client import connect

    frame = "x" * (kib * 1024 - 64)
    try:
        ws = await connect(url, additional_headers=headers, max_size=None, open_timeout=30,
                           ping_interval=None, compression="deflate")  # fmt: skip
    except Exception as exc:  # noqa: BLE001 - counted, as any outcome
        return f"connect failed ({type(exc).__name__})"
    try:
        for _ in range(frames):
            await asyncio.wait_for(ws.send(frame), 20)
        await asyncio.sleep(5)
        return "held"
    except Exception as exc:  # noqa: BLE001
        code = getattr(getattr(exc, "rcvd", None), "code", None)
        return f"closed {code}" if code else type(exc).__name__
    finally:
        await ws.close()


async def _idle_subscriber(url: str, headers: dict | None, held: list) -> str:
    """One connection of the flood: 16 subscriptions, then it never reads (kept in ``held``)."""
    from websockets.asyncio.client import connect

    try:
        ws = await connect(url, additional_headers=headers, open_timeout=10, ping_interval=None)
        for k in range(16):
            kinds = ["joint_states", "transforms", "events", "topology"]
            msg = {"id": k, "op": "subscribe", "kinds": kinds, "max_rate": 1000}
            await ws.send(json.dumps(msg))
    except Exception as exc:  # noqa: BLE001 - counted, as any outcome
        return f"failed ({type(exc).__name__})"
    held.append(ws)
    return "open"


def _connection_flood(url: str, headers: dict | None, pid: int, n: int, stats) -> None:
    held: list = []
    rss = [_status(pid, "VmRSS")]

    async def run() -> list[str]:
        got = await asyncio.gather(*(_idle_subscriber(url, headers, held) for _ in range(n)))
        rss.append(_status(pid, "VmRSS"))
        await asyncio.sleep(6)  # they do not read: slow consumers, closed by the server
        rss.append(_status(pid, "VmRSS"))
        for ws in held:
            ws.transport.abort()
        return got

    results = asyncio.run(run())
    time.sleep(10)
    rss.append(_status(pid, "VmRSS"))
    s = stats()
    print(f"{n} connections opened at once, 16 subscriptions each, never reading: "
          f"{dict(collections.Counter(results))}")  # fmt: skip
    print("server RSS before {}, all opened {}, 6 s later {}, 10 s after closing {}".format(
        *(_mib(k) for k in rss)))  # fmt: skip
    if s:
        print(f"server: evicted_pending {s.get('evicted_pending', '-')}, slow_closed "
              f"{s.get('slow_closed', '-')}, "
              f"refused_connections {s['refused_connections']}")  # fmt: skip


async def _subscriber(url: str, headers: dict | None, seconds: float) -> tuple[int, int, bool]:
    """Messages and bytes (on the wire) a joint_states subscriber gets in ``seconds``, and
    whether the server agreed to permessage-deflate."""
    from websockets.asyncio.client import ClientConnection, connect

    wire = [0]

    class Counting(ClientConnection):
        def data_received(self, data: bytes) -> None:
            wire[0] += len(data)
            super().data_received(data)

    n = 0
    async with connect(
        url, additional_headers=headers, compression="deflate", create_connection=Counting
    ) as ws:
        await ws.send(json.dumps({"id": 1, "op": "subscribe", "kinds": ["joint_states"]}))
        end = time.monotonic() + seconds
        while (left := end - time.monotonic()) > 0:
            try:
                await asyncio.wait_for(ws.recv(), left)
                n += 1
            except TimeoutError:
                break
        deflate = ws.response.headers.get("Sec-WebSocket-Extensions") is not None
    return n, wire[0], deflate


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--conns", type=int, default=200)
    ap.add_argument("--frames", type=int, default=4)
    ap.add_argument("--deflate", action="store_true", help="the server with permessage-deflate")
    ap.add_argument("--subscribers", type=int, default=0)
    ap.add_argument("--connection-flood", type=int, default=0, metavar="N")
    ap.add_argument("--url")
    ap.add_argument("--pid", type=int)
    ap.add_argument("--token-file")
    ap.add_argument("--frame-kib", type=int, default=1024, help="frame size (default 1 MiB)")
    ap.add_argument(
        "--option", action="append", default=[], metavar="NAME=INT",
        help="a ServerOptions field of the server started here (repeatable)",
    )  # fmt: skip
    args = ap.parse_args()
    headers = None
    if args.token_file:
        headers = {"Authorization": "Bearer " + Path(args.token_file).read_text().strip()}
    child = None
    if args.url:
        url, pid = args.url, args.pid
    else:
        from host.api.memory import RELEASE_AFTER_GROWTH  # the API process's setting

        code = _SERVER.format(
            repo=str(REPO), stub=str(REPO / "tests" / "host" / "test_api_protocol.py"),
            deflate=args.deflate,
            options={"release_after_growth": RELEASE_AFTER_GROWTH,  # as the API process
                     **{k: int(v) for k, v in (kv.split("=", 1) for kv in args.option)}},
        )  # fmt: skip
        from host.api.process import child_env  # the API process's allocator, as deployed

        child = subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE,
                                 stdout=subprocess.PIPE, text=True, env=child_env())  # fmt: skip
        url, pid = f"ws://127.0.0.1:{child.stdout.readline().strip()}", child.pid
        time.sleep(1.0)

    def stats() -> dict:
        if child is None:
            return {}
        child.stdin.write("stats\n")
        child.stdin.flush()
        return json.loads(child.stdout.readline())

    try:
        before = _status(pid, "VmRSS")
        if args.connection_flood:
            _connection_flood(url, headers, pid, args.connection_flood, stats)
            return 0
        if args.subscribers:
            cpu0 = _cpu_s(pid)

            async def subs() -> list[tuple[int, int, bool]]:
                return await asyncio.gather(
                    *(_subscriber(url, headers, 10.0) for _ in range(args.subscribers))
                )

            got = asyncio.run(subs())
            cpu = _cpu_s(pid) - cpu0
            msgs, wire = sum(g[0] for g in got), sum(g[1] for g in got)
            print(
                f"{args.subscribers} joint_states subscribers for 10 s (deflate "
                f"{'on' if all(g[2] for g in got) else 'off'}): {msgs} messages, server CPU "
                f"{cpu:.2f} s "
                f"({cpu / max(1, msgs) * 1e6:.0f} us per message and subscriber), "
                f"{wire / max(1, msgs):.0f} bytes per message on the wire, "
                f"RSS {_mib(before)} -> {_mib(_status(pid, 'VmRSS'))}"
            )
            return 0

        async def flood() -> list[str]:
            return await asyncio.gather(
                *(_flood(url, headers, args.frames, args.frame_kib) for _ in range(args.conns))
            )

        t0 = time.monotonic()
        results = asyncio.run(flood())
        time.sleep(2.0)  # the janitor's quiet second: memory handed back
        s = stats()
        print(
            f"{args.conns} connections x {args.frames} frames of {args.frame_kib} KiB (deflate "
            f"offered; server "
            f"{'agrees' if args.deflate else 'as configured'}), {time.monotonic() - t0:.0f} s: "
            f"{dict(collections.Counter(results))}"
        )
        print(f"server RSS before {_mib(before)}, peak {_mib(_status(pid, 'VmHWM'))}, "
              f"after {_mib(_status(pid, 'VmRSS'))}")  # fmt: skip
        if s:
            print(
                f"server: inbound_peak {s.get('inbound_peak', 0) / 2**20:.1f} MiB, "
                f"inbound_closed {s.get('inbound_closed', '-')}, errors {s['errors']}, "
                f"rate_limited {s.get('rate_limited', '-')}, throttled {s['throttled']}"
            )
        return 0
    finally:
        if child is not None:
            child.stdin.close()
            child.terminate()
            child.wait(10)


if __name__ == "__main__":
    sys.exit(main())

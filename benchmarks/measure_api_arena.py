"""Where the API process's memory stays after abuse (docs/api.md "Memory"): live objects or the
allocator's free space. Measured, not asserted.

    .venv/bin/python benchmarks/measure_api_arena.py [--rounds 2]

Starts an API server (``host.api.server.ApiServer``, this tree's code, with the API process's
environment and growth rule) in a process of its own in front of the in-memory facade of
tests/host/test_api_protocol.py; warms it up with 5 clients polling ``status`` for 2 s; then,
``--rounds`` times, runs bench_api's abuse generators one after another (1,000 connection
attempts, 1,000 subscription requests on one connection, 20 connections flooding ~58 KB invalid
trajectories). 5 s after each, the server collects garbage and returns free heap
(``host.api.memory.release_memory``, as its janitor does) and prints its resident size, the
count of live Python objects (``gc.get_objects()``) and glibc's own account of its heaps
(``malloc_info(3)``: bytes the arenas hold from the system, and of them free in chunks), with
the resident size by kind of mapping (the main ``[heap]``, anonymous: the API thread's arena).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

_SERVER = r"""
import collections, ctypes, gc, importlib.util, json, re, sys, tempfile
sys.path.insert(0, {repo!r})
spec = importlib.util.spec_from_file_location("stub", {stub!r})
mod = importlib.util.module_from_spec(spec); spec.loader.exec_module(mod)
import host.api.server as server
from host.api.memory import RELEASE_AFTER_GROWTH, release_memory, rss_bytes
srv = server.ApiServer(mod.FacadeStub(publish_hz=100.0), "127.0.0.1", 0,
                       release_after_growth=RELEASE_AFTER_GROWTH).start()
print(srv.port, flush=True)
libc = ctypes.CDLL("libc.so.6")
libc.fopen.restype = ctypes.c_void_p

def arenas():
    with tempfile.NamedTemporaryFile(suffix=".xml") as f:
        fp = libc.fopen(f.name.encode(), b"w")
        libc.malloc_info(0, ctypes.c_void_p(fp))
        libc.fclose(ctypes.c_void_p(fp))
        xml = open(f.name).read()
    tail = xml[xml.rfind("</heap>"):]  # the totals over all arenas
    sizes = re.findall(r'<total type="(?:fast|rest)" count="\d+" size="(\d+)"', tail)
    free = sum(int(m) for m in sizes)
    held = int(re.search(r'<system type="current" size="(\d+)"', tail).group(1))
    return held, free

def mappings():
    out = collections.Counter(); kind = None
    for line in open("/proc/self/smaps"):
        f = line.split()
        if f[0] == "Rss:":
            out[kind] += int(f[1]) * 1024
        elif "-" in f[0] and not f[0].endswith(":"):
            name = f[5] if len(f) > 5 else ""
            kind = "heap" if name == "[heap]" else "anonymous" if not name else "other"
    return out

for line in sys.stdin:
    release_memory()
    held, free = arenas()
    m = mappings()
    print(json.dumps({{"rss": rss_bytes(), "objects": len(gc.get_objects()), "held": held,
                      "free": free, "heap": m["heap"], "anonymous": m["anonymous"]}}), flush=True)
"""


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rounds", type=int, default=2)
    args = ap.parse_args()
    from host.api.process import child_env  # the API process's allocator, as deployed

    code = _SERVER.format(repo=str(REPO), stub=str(REPO / "tests/host/test_api_protocol.py"))
    child = subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE,
                             stdout=subprocess.PIPE, text=True, env=child_env())  # fmt: skip
    url = f"ws://127.0.0.1:{child.stdout.readline().strip()}"
    bench = REPO / "benchmarks" / "bench_api.py"

    def gen(kind: str, n: int, seconds: float) -> None:
        subprocess.run([sys.executable, str(bench), "--gen", kind, "--url", url, "--n", str(n),
                        "--seconds", str(seconds)], capture_output=True, cwd=REPO)  # fmt: skip

    def show(label: str) -> None:
        child.stdin.write("\n")
        child.stdin.flush()
        d = json.loads(child.stdout.readline())
        mib = 1 << 20
        print(f"{label:<18} RSS {d['rss'] / mib:5.1f} MiB ([heap] {d['heap'] / mib:4.1f}, "
              f"anonymous {d['anonymous'] / mib:4.1f})  live objects {d['objects']:6d}  "
              f"malloc: {d['held'] / mib:5.1f} MiB held, {d['free'] / mib:4.1f} MiB of it free",
              flush=True)  # fmt: skip

    try:
        time.sleep(1.0)
        show("started")
        gen("poll", 5, 2.0)
        time.sleep(2.0)
        show("warm (5 pollers)")
        for rnd in range(1, args.rounds + 1):
            for kind, n in (("connect", 1000), ("subscribe", 1000), ("badtraj", 20)):
                gen(kind, n, 4.0)
                time.sleep(5.0)
                show(f"{kind} #{rnd}")
    finally:
        child.stdin.close()
        child.wait(10)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

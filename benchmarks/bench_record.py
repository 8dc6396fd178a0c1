"""Recording and live Foxglove benchmark (interop/, docs/recording.md).

Prints:
1. MCAP size per second of robot time, zstd-compressed as `ucr record` writes it (chunks closed
   every second), for 3 and 8 segments with joint states at 100 Hz: with the default visual
   rate (/tf and /ucr/arcs at 20 Hz) and with everything at 100 Hz; plus the recorder's CPU time
   per second of data (build + encode + write). Synthetic joint states (a slow sine on every
   segment), so the figures do not depend on the machine's load.
2. Loop jitter p99 of the daemon driving the emulated 3-segment chain (real firmware on the
   MicroPython VM) at 100 Hz, with nothing attached vs with `ucr record --foxglove-port P` (the
   recorder serving Foxglove too: one API client) in its own process and a Foxglove WebSocket
   client subscribed to every channel.
   Phases alternate (off, on, off, on, ...) to spread the machine's drift. Goal: ratio <= 1.05.

Run: ``.venv/bin/python benchmarks/bench_record.py`` (``--quick`` for shorter phases).
"""

from __future__ import annotations

import argparse
import math
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))

from bench_host import robot_with  # noqa: E402

from benchmarks.figures import Figures  # noqa: E402
from interop.record import McapSink  # noqa: E402
from interop.sinks import Fanout  # noqa: E402
from interop.topics import RobotTopics  # noqa: E402
from ucrdf.writer import dumps  # noqa: E402

ROBOT = REPO / "robots" / "softrobot3.ucrdf"

# A Foxglove WebSocket client subscribing to every channel; counts bytes until killed.
FOXGLOVE_CLIENT = r"""
import json, sys
from websockets.sync.client import connect
n = 0
with connect(sys.argv[1], subprotocols=["foxglove.sdk.v1"], max_size=None) as ws:
    sub = 0
    while True:
        m = ws.recv()
        if isinstance(m, str):
            msg = json.loads(m)
            if msg.get("op") == "advertise":
                chans = msg["channels"]
                subs = [{"id": sub + i, "channelId": c["id"]} for i, c in enumerate(chans)]
                sub += len(subs)
                ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
        else:
            n += len(m)
"""


def mcap_rate(n: int, seconds: float, viz_hz: float) -> tuple[float, float, int]:
    """(bytes per second of robot time, recorder CPU ms per second, messages) for ``n``
    segments, joint states at 100 Hz."""
    robot, _ = robot_with(n)
    topics = RobotTopics(robot, dumps(robot), 10)
    names = list(robot.bendables)
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "bench.mcap"
        sink = McapSink(path, flush_interval=math.inf)
        out = Fanout([sink])
        t0_ns = time.time_ns()
        cpu0 = time.process_time()
        for m in topics.static_messages(t0_ns):
            out.publish(m)
        steps = int(seconds * 100)
        viz_every = max(1, round(100 / viz_hz))
        for k in range(steps):
            t = k / 100.0
            t_ns = t0_ns + int(t * 1e9)
            kappa = [1.5 + 1.2 * math.sin(0.5 * t + i) for i in range(n)]
            phi = [math.remainder(0.3 * t + i, 2 * math.pi) for i in range(n)]
            js = {"kind": "joint_states", "t": t, "names": names, "kappa": kappa, "phi": phi,
                  "kx": [a * math.cos(b) for a, b in zip(kappa, phi, strict=True)],
                  "ky": [a * math.sin(b) for a, b in zip(kappa, phi, strict=True)],
                  "valid": [True] * n, "rigid": {}}  # fmt: skip
            out.publish(topics.joint_states(js, t_ns))
            if k % viz_every == 0:
                out.publish(topics.tf(js, t_ns))
                out.publish(topics.arcs(js, t_ns))
            if k % 100 == 0:
                status = {"state": "connected", "joint_states": {
                    nm: {"kappa": kappa[i], "phi": phi[i], "valid": True}
                    for i, nm in enumerate(names)}}  # fmt: skip
                out.publish(topics.segments(status, {"segments": []}, t_ns))
                stats = {"cycles": k, "overruns": 0, "period_us": {"mean": 10000.0, "p99": 10100.0},
                         "jitter_us": {"mean": 20.0, "p99": 90.0, "max": 300.0}}  # fmt: skip
                out.publish(topics.loop_stats(stats, t_ns))
                sink.flush()  # as the recorder does every second
        cpu = time.process_time() - cpu0
        sink.close()
        size = path.stat().st_size
    return size / seconds, cpu / seconds * 1000.0, sink.messages


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _cpu_s(pid: int | None) -> float:
    """CPU time (s, user + system) a process used so far; 0 if unknown."""
    if pid is None:
        return 0.0
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def jitter_phases(
    phase_s: float,
    rounds: int,
    in_process: bool = False,
    rt_priority: int = 0,
    figs: Figures | None = None,
) -> None:
    from host.api.process import start_api_process
    from host.api.server import ApiServer
    from host.daemon import Daemon, DaemonError
    from tools.emulator import EmulatedChain
    from tools.segment_config import configs
    from ucrdf.parser import load

    robot = load(ROBOT)
    chain = EmulatedChain(3, config_for=configs(robot))
    daemon = srv = None
    procs: list[subprocess.Popen] = []
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    try:
        deadline = time.monotonic() + 20
        while True:
            try:
                daemon = Daemon(robot, port=chain.host_port, realtime_priority=rt_priority).start()
                break
            except DaemonError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.2)
        # as `ucr daemon` runs it: the API in its own process (--api-in-process: a daemon thread)
        if in_process:
            srv = ApiServer(daemon, "127.0.0.1", 0).start()
        else:
            srv = start_api_process(daemon, "127.0.0.1", 0)
        print(f"   API in {'a thread of the daemon' if in_process else 'its own process'}")
        # keep the robot moving: a slow wave on every segment, resent when it ends
        pts = [{"time_from_start": 2.0 * (k + 1), "segments": {
            n: {"kappa": 1.0 + 0.8 * math.sin(k + i), "phi": 0.5 * k} for i, n in
            enumerate(robot.bendables)}} for k in range(200)]  # fmt: skip

        def keep_moving() -> None:  # a stall under load aborts a goal: start the wave again
            if not daemon.status()["running_goals"]:
                try:
                    daemon.send_trajectory(pts)
                except Exception as exc:  # noqa: BLE001 - rebuilding: the next phase retries
                    print(f"   (wave not restarted: {exc})")

        keep_moving()
        time.sleep(3.0)
        results: dict[str, list[dict]] = {"off": [], "on": []}
        cpus: list[list[float]] = []
        sizes: list[float] = []
        loads: dict[str, list[float]] = {"off": [], "on": []}
        tmp = tempfile.mkdtemp()
        for r in range(rounds):
            for mode in ("off", "on"):
                keep_moving()
                if mode == "on":
                    port = free_port()
                    ucr = [sys.executable, "-m", "tools.cli"]
                    common = ["--url", srv.url, "--robot", str(ROBOT)]
                    # one API client serves both: the recorder with its Foxglove server on
                    procs = [
                        subprocess.Popen([*ucr, "record", "-o", f"{tmp}/bench{r}.mcap",
                                          "--foxglove-port", str(port), *common],
                                         cwd=REPO, env=env, stderr=subprocess.DEVNULL),
                    ]  # fmt: skip
                    time.sleep(2.0)
                    procs.append(subprocess.Popen(
                        [sys.executable, "-c", FOXGLOVE_CLIENT, f"ws://127.0.0.1:{port}"],
                        cwd=REPO, env=env, stderr=subprocess.DEVNULL))  # fmt: skip
                cpu0 = [_cpu_s(p.pid) for p in procs]
                daemon.loop.stats.reset()
                time.sleep(phase_s)
                st = daemon.loop_stats()
                results[mode].append(st)
                loads[mode].append(os.getloadavg()[0])
                if procs:
                    cpu = [
                        (_cpu_s(p.pid) - c) * 1e3 / phase_s
                        for p, c in zip(procs, cpu0, strict=True)
                    ]
                    cpus.append(cpu)
                    print(f"   round {r + 1}: recorder + Foxglove server {cpu[0]:.0f} CPU ms/s, "
                          f"Foxglove client {cpu[1]:.0f} CPU ms/s")  # fmt: skip
                for p in procs:
                    p.send_signal(signal.SIGINT)
                for p in procs:
                    try:
                        p.wait(timeout=15)
                    except subprocess.TimeoutExpired:
                        p.kill()
                if procs:
                    size = Path(f"{tmp}/bench{r}.mcap").stat().st_size
                    sizes.append(size / phase_s / 1024)
                    print(f"   round {r + 1}: recorded {size / 1024:.0f} KiB in ~{phase_s:.0f} s "
                          f"({size / phase_s / 1024:.1f} KiB/s live, 3 segments)")  # fmt: skip
                procs = []
                time.sleep(1.0)
        print(f"{'':6s}{'jitter p99 µs per round':>28s}{'period p99 µs per round':>28s}"
              f"{'overruns':>10s}  load average per round")  # fmt: skip
        p99 = {}
        for mode in ("off", "on"):
            vals = [s["jitter_us"]["p99"] for s in results[mode]]
            per = [s["period_us"]["p99"] for s in results[mode]]
            p99[mode] = sorted(vals)[len(vals) // 2]
            print(f"{mode:6s}{' / '.join(f'{v:.0f}' for v in vals):>28s}"
                  f"{' / '.join(f'{v:.0f}' for v in per):>28s}"
                  f"{results[mode][-1]['overruns']:>10d}  "
                  f"{' / '.join(f'{v:.1f}' for v in loads[mode])}")  # fmt: skip
        ratio = p99["on"] / p99["off"] if p99["off"] else float("inf")
        verdict = "ok" if ratio <= 1.05 else "ABOVE GOAL"
        print(f"jitter p99 median on/off: {p99['on']:.0f} / {p99['off']:.0f} µs = "
              f"{ratio:.3f}  (goal <= 1.05: {verdict})")  # fmt: skip
        if figs is not None:
            sched = daemon.loop_stats()["scheduling"].get("control loop", "normal")
            where = "a thread of the daemon" if in_process else "its own process"
            figs.table(
                "jitter",
                ["round", "loop jitter p99, nothing attached", "recording + Foxglove client",
                 "1-min load off / on", "recorder + server / client CPU ms/s",
                 "recorded KiB/s"],
                note=f"100 Hz, 3 emulated segments moving a wave; API in {where}; loop thread "
                f"{sched}; {rounds} alternating rounds of {phase_s:g} s; topology changes "
                f"during the run: {daemon.status()['topology_changes']}",
            )  # fmt: skip
            for r in range(rounds):
                c = cpus[r] if r < len(cpus) else [math.nan, math.nan]
                figs.row("jitter", [
                    str(r + 1), f"{results['off'][r]['jitter_us']['p99']:.0f} µs",
                    f"{results['on'][r]['jitter_us']['p99']:.0f} µs",
                    f"{loads['off'][r]:.1f} / {loads['on'][r]:.1f}", f"{c[0]:.0f} / {c[1]:.0f}",
                    f"{sizes[r]:.1f}" if r < len(sizes) else "",
                ])  # fmt: skip
            figs.row("jitter", [
                "median", f"{p99['off']:.0f} µs",
                f"{p99['on']:.0f} µs (ratio {ratio:.2f}, goal ≤ 1.05)", "", "", "",
            ])  # fmt: skip
    finally:
        for p in procs:
            p.kill()
        if srv is not None:
            srv.stop()
        if daemon is not None:
            daemon.stop()
        chain.close()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="shorter phases")
    ap.add_argument("--skip-jitter", action="store_true", help="only the file-size figures")
    ap.add_argument("--skip-size", action="store_true", help="only the jitter figures")
    ap.add_argument("--rounds", type=int, default=None, help="off/on rounds (3; --quick 2)")
    ap.add_argument("--phase", type=float, default=None, help="s per phase (20; --quick 12)")
    ap.add_argument("--api-in-process", action="store_true", help="API as a daemon thread")
    ap.add_argument(
        "--rt-priority", type=int, default=0, metavar="N",
        help="SCHED_FIFO priority of the daemon's loop and link reader (the unit: 10; 0: normal)",
    )  # fmt: skip
    ap.add_argument("--figures", metavar="FILE", help="save the tables the docs quote (JSON)")
    args = ap.parse_args()
    figs = Figures.from_argv("bench_record")
    seconds = 10.0 if args.quick else 30.0
    if not args.skip_size:
        print(f"1. MCAP size, zstd, chunk per second ({seconds:.0f} s of synthetic robot time)")
        print(f"{'segments':>9s}{'viz Hz':>8s}{'KiB/s':>9s}{'MiB/hour':>10s}{'CPU ms/s':>10s}"
              f"{'msgs/s':>8s}")  # fmt: skip
        if figs is not None:
            figs.table(
                "size", ["segments", "/tf, /ucr/arcs", "KiB/s", "MiB/hour", "recorder CPU ms/s"],
                note=f"{seconds:.0f} s of synthetic joint states at 100 Hz, every segment moving, "
                "zstd, a chunk per second",
            )  # fmt: skip
        for n in (3, 8):
            for viz in (20.0, 100.0):
                rate, cpu, msgs = mcap_rate(n, seconds, viz)
                print(f"{n:9d}{viz:8.0f}{rate / 1024:9.1f}{rate * 3600 / 2**20:10.1f}"
                      f"{cpu:10.1f}{msgs / seconds:8.0f}")  # fmt: skip
                if figs is not None:
                    label = f"{viz:.0f} Hz" + (" (default)" if viz == 20.0 else "")
                    figs.row("size", [n, label, f"{rate / 1024:.1f}",
                                      f"{rate * 3600 / 2**20:.0f}", f"{cpu:.0f}"])  # fmt: skip
    if not args.skip_jitter:
        phase = args.phase or (12.0 if args.quick else 20.0)
        rounds = args.rounds or (2 if args.quick else 3)
        print(
            f"\n2. daemon loop jitter at 100 Hz, 3 emulated segments, {rounds} x ({phase:.0f} s "
            f"off, {phase:.0f} s on: ucr record --foxglove-port + a subscribed client)"
        )
        jitter_phases(phase, rounds, args.api_in_process, args.rt_priority, figs)
    if figs is not None:
        figs.save()


if __name__ == "__main__":
    main()

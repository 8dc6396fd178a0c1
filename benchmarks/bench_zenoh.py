"""ROS 2 over Zenoh benchmark: segment STATE -> Zenoh subscriber latency on loopback, and what the
bridge plus a subscriber do to the control loop's jitter. Runs the real daemon on an emulated
3-segment chain with its API server in a process of its own (``host.api.process.ApiProcess``, as
``ucr daemon`` runs it), `ucr zenoh-router` and `ucr zenoh` as their own processes (as deployed),
and a Zenoh subscriber on /<robot>/joint_states and /<robot>/tf in another process.

    .venv/bin/python benchmarks/bench_zenoh.py [--seconds 5] [--rounds 5] [--rt-priority 10]
        [--figures FILE]

Latency: receive time (wall clock) minus the JointState header stamp, which is the daemon's
time of the cycle that produced the state (daemon monotonic clock mapped to wall clock; same
machine). It covers daemon -> API -> bridge (decode, CDR encode) -> Zenoh -> subscriber.

Jitter: the daemon's |period - target| p99 and mean, in phases that alternate ``--rounds`` times
so that the machine's background load falls on all alike:
- off: daemon and API process only;
- control: a plain process burning ``--hog-percent`` of one core at the bridge's nice (CPU load
  alone: no Zenoh, no API subscription);
- API subscription only: a client holding the subscription ``ucr zenoh`` holds (no Zenoh);
- on: router, bridge and subscriber running.
Goal: ratio on/off <= 1.05. CPU per process and phase shows where the work is (the daemon's
own share grows only by what the API subscription costs it). ``--rt-priority N`` runs the
daemon's loop and link reader SCHED_FIFO N, as the service unit does (``ucr daemon
--rt-priority``); ``--api thread`` runs the API server in the daemon's process (not deployed).
Prints figures, ratios and the load average (saved with ``--figures`` for tools/docfigures.py);
asserts nothing (the machine may be shared).
"""

# ruff: noqa: PLC0415 - heavy imports (daemon, emulator, zenoh) only when the benchmark runs
from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def _pct(values: list[float], q: float) -> float:
    s = sorted(values)
    return s[min(len(s) - 1, int(q * len(s)))]


def _jitter(daemon, seconds: float) -> dict:
    daemon.loop.stats.reset()
    time.sleep(seconds)
    return daemon.loop_stats()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _spawn(args: list[str], nice: int = 0) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, *args],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=(lambda: os.nice(nice)) if nice else None,
    )


def _cpu_s(pid: int) -> float:
    """CPU time (user + system, s) a process has used so far (Linux /proc)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _stop(proc: subprocess.Popen) -> None:
    proc.send_signal(signal.SIGINT)
    try:
        proc.wait(timeout=20)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def subscriber(endpoint: str, ns: str, seconds: float, warmup: float) -> int:
    """Child process: subscribe to joint_states and tf, print latencies (ms) as JSON."""
    import zenoh

    from interop import ros2
    from interop.ros2.type_hash import type_hash
    from interop.zenoh import rmw

    js_type, tf_type = "sensor_msgs/msg/JointState", "tf2_msgs/msg/TFMessage"
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    conf.insert_json5("listen/endpoints", '["tcp/127.0.0.1:0"]')
    conf.insert_json5("scouting/multicast/enabled", "false")
    codec = ros2.codec(js_type)
    lat: list[float] = []
    tf_count = [0]

    def on_js(sample) -> None:
        now = time.time_ns()
        m = codec.decode(sample.payload.to_bytes())
        stamp = m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec
        lat.append((now - stamp) / 1e6)

    def on_tf(sample) -> None:
        tf_count[0] += 1

    with zenoh.open(conf) as session:
        key_js = rmw.topic_key(0, f"{ns}/joint_states", js_type, type_hash(js_type))
        key_tf = rmw.topic_key(0, f"{ns}/tf", tf_type, type_hash(tf_type))
        subs = [
            session.declare_subscriber(key_js, on_js),
            session.declare_subscriber(key_tf, on_tf),
        ]
        print("ready", flush=True)
        time.sleep(warmup)
        lat.clear()
        tf_count[0] = 0
        time.sleep(seconds)
        out = {"lat_ms": list(lat), "tf": tf_count[0]}
        for s in subs:
            s.undeclare()
    print(json.dumps(out), flush=True)
    return 0


def hog(percent: float) -> int:
    """Child process: burn ``percent`` of one core in 20 ms periods until killed (a control:
    CPU load like the bridge's, with no Zenoh and no API subscription)."""
    busy = 0.02 * percent / 100
    while True:
        t0 = time.perf_counter()
        while time.perf_counter() - t0 < busy:
            pass
        time.sleep(max(0.0, 0.02 - (time.perf_counter() - t0)))


def api_subscriber(url: str) -> int:
    """Child process: hold the API subscription ``ucr zenoh`` holds (joint_states at 50 Hz,
    events, topology) and drain it, with no Zenoh: what the API subscription alone costs."""
    from host.api.client import connect

    with connect(url) as c, c.subscribe(["joint_states", "events", "topology"], max_rate=50.0) as s:
        while True:
            s.get(timeout=1.0)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=5.0, help="duration of each phase, s")
    ap.add_argument("--rounds", type=int, default=5, help="rounds of the phases (5)")
    ap.add_argument(
        "--nice",
        type=int,
        default=10,
        help="niceness of the router, bridge and subscriber processes (10, as docs/ros2.md "
        "recommends for the service; 0: same priority as the daemon)",
    )
    ap.add_argument(
        "--api",
        choices=("process", "thread"),
        default="process",
        help="API server in its own process (as `ucr daemon`) or in the daemon's (thread)",
    )
    ap.add_argument(
        "--daemon-nice",
        type=int,
        default=-5,
        help="niceness of the daemon (this process): -5 as host/ucr-daemon.service runs it "
        "(needs root or CAP_SYS_NICE; 0 otherwise)",
    )
    ap.add_argument(
        "--hog-percent",
        type=float,
        default=12.0,
        help="CPU (%% of one core) of the control phase's busy process, at the bridge's nice "
        "(12: about what bridge, subscriber and the API's extra work use; 0: no control phase)",
    )
    ap.add_argument(
        "--rt-priority",
        type=int,
        default=0,
        metavar="N",
        help="SCHED_FIFO priority of the daemon's loop and link reader threads (1-98; needs "
        "root or RLIMIT_RTPRIO; the service unit: 10; 0: normal scheduling)",
    )
    ap.add_argument("--figures", metavar="FILE", help="save the tables the docs quote (JSON)")
    ap.add_argument("--hog", type=float, help=argparse.SUPPRESS)
    ap.add_argument("--api-subscriber", help=argparse.SUPPRESS)
    ap.add_argument("--subscriber", nargs=2, metavar=("ENDPOINT", "NS"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.hog is not None:
        return hog(args.hog)
    if args.api_subscriber:
        return api_subscriber(args.api_subscriber)
    if args.subscriber:
        return subscriber(*args.subscriber, seconds=args.seconds, warmup=2.0)

    from benchmarks.figures import Figures
    from host.api.process import ApiProcess
    from host.api.server import ApiServer
    from host.daemon import Daemon, DaemonError
    from interop.zenoh import rmw
    from tools.emulator import EmulatedChain
    from tools.segment_config import configs
    from ucrdf.parser import load

    figs = Figures.from_argv("bench_zenoh", argv)
    daemon_nice = 0
    if args.daemon_nice:
        try:
            os.nice(args.daemon_nice)
            daemon_nice = args.daemon_nice
        except PermissionError:
            print(f"cannot set nice {args.daemon_nice} (not root): daemon at nice 0")
    robot = load(ROOT / "robots" / "softrobot3.ucrdf")
    ns = rmw.namespace_for(robot.name)
    with EmulatedChain(3, config_for=configs(robot)) as chain:
        deadline = time.monotonic() + 15
        while True:
            try:
                daemon = Daemon(
                    robot, port=chain.host_port, realtime_priority=args.rt_priority
                ).start()
                break
            except DaemonError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.2)
        srv = (ApiProcess if args.api == "process" else ApiServer)(daemon, "127.0.0.1", 0).start()
        port = _free_port()
        endpoint = f"tcp/127.0.0.1:{port}"
        offs: list[dict] = []
        ons: list[dict] = []
        hogs: list[dict] = []
        apis: list[dict] = []
        cpu_api: dict[str, float] = {}
        api_pid = getattr(getattr(srv, "_child", None), "pid", None)
        base_pids = {"daemon": os.getpid(), **({"api": api_pid} if api_pid else {})}
        cpu_off: dict[str, float] = {}
        cpu_hog: dict[str, float] = {}

        def measured(store: list, pids: dict[str, int], acc: dict[str, float]) -> None:
            before = {k: _cpu_s(pid) for k, pid in pids.items()}
            store.append(_jitter(daemon, args.seconds))
            for k, pid in pids.items():
                acc[k] = acc.get(k, 0.0) + _cpu_s(pid) - before[k]

        lat: list[float] = []
        tf = 0
        cpu: dict[str, float] = {}
        load0 = os.getloadavg()
        try:
            time.sleep(0.5)
            for _ in range(args.rounds):
                measured(offs, base_pids, cpu_off)
                if args.hog_percent > 0:
                    h = _spawn([__file__, "--hog", str(args.hog_percent)], nice=args.nice)
                    try:
                        time.sleep(0.5)
                        measured(hogs, {**base_pids, "hog": h.pid}, cpu_hog)
                    finally:
                        h.kill()
                        h.wait()
                a = _spawn([__file__, "--api-subscriber", srv.url], nice=args.nice)
                try:
                    time.sleep(1.5)
                    measured(apis, {**base_pids, "api client": a.pid}, cpu_api)
                finally:
                    a.kill()
                    a.wait()
                router = _spawn(
                    ["-m", "tools.cli", "zenoh-router", "--listen", endpoint], nice=args.nice
                )
                bridge = sub = None
                try:
                    time.sleep(1.5)
                    bridge = _spawn(
                        [
                            "-m",
                            "tools.cli",
                            "zenoh",
                            "--url",
                            srv.url,
                            "--connect",
                            endpoint,
                            "--listen",
                            "tcp/127.0.0.1:0",
                        ],
                        nice=args.nice,
                    )
                    line = bridge.stderr.readline()
                    if "ROS 2 node" not in line:
                        print(
                            f"bridge did not start: {line}{bridge.stderr.read()}", file=sys.stderr
                        )
                        return 1
                    sub = _spawn(
                        [__file__, "--seconds", str(args.seconds), "--subscriber", endpoint, ns],
                        nice=args.nice,
                    )
                    if sub.stdout.readline().strip() != "ready":
                        print(f"subscriber did not start: {sub.stderr.read()}", file=sys.stderr)
                        return 1
                    time.sleep(2.0)  # the subscriber's warm-up: discovery, first messages
                    procs = {"router": router, "bridge": bridge, "subscriber": sub}
                    pids = {**base_pids, **{k: p.pid for k, p in procs.items()}}
                    measured(ons, pids, cpu)
                    out = json.loads(sub.stdout.readline() or "{}")
                    lat += out.get("lat_ms", [])
                    tf += out.get("tf", 0)
                finally:
                    for p in (sub, bridge, router):
                        if p is not None:
                            _stop(p)
            load1 = os.getloadavg()
            n = len(lat)
            total = args.seconds * args.rounds
            if n:
                print(
                    f"STATE -> Zenoh subscriber (/joint_states)  n={n} ({n / total:.0f}/s)  "
                    f"p50 {statistics.median(lat):.2f} ms  p99 {_pct(lat, 0.99):.2f} ms  "
                    f"max {max(lat):.2f} ms"
                )
            else:
                print("STATE -> Zenoh subscriber: no message received")
            print(f"/tf messages received: {tf} ({tf / total:.0f}/s)")
            print(
                f"loop rate {daemon.rate_hz:.0f} Hz; API server: {args.api}; router, bridge and "
                f"subscriber at nice {args.nice}; {args.rounds} rounds of {args.seconds:.0f} s"
            )
            for label, acc in (
                ("off", cpu_off),
                ("control", cpu_hog),
                ("API subscription", cpu_api),
                ("on", cpu),
            ):
                if acc:
                    print(
                        f"CPU in the {label} phases (% of one core): "
                        + ", ".join(f"{k} {100 * v / total:.1f}" for k, v in acc.items())
                    )
            policy = daemon.loop_stats()["scheduling"].get("control loop", "normal")
            print(f"daemon at nice {daemon_nice}; loop thread scheduling: {policy}")
            print(f"load average (1 min) at start {load0[0]:.2f}, at end {load1[0]:.2f}")
            for label, sts in (
                ("bridge off", offs),
                (f"control: busy {args.hog_percent:.0f}%", hogs),
                ("API subscription only", apis),
                ("bridge + subscriber on", ons),
            ):
                for st in sts:
                    j = st["jitter_us"]
                    print(
                        f"{label:<24} jitter p99 {j['p99']:7.0f} µs  mean {j['mean']:6.1f} µs  "
                        f"overruns {st['overruns']}"
                    )
            p99_off = statistics.median(s["jitter_us"]["p99"] for s in offs)
            p99_on = statistics.median(s["jitter_us"]["p99"] for s in ons)
            m_off = statistics.median(s["jitter_us"]["mean"] for s in offs)
            m_on = statistics.median(s["jitter_us"]["mean"] for s in ons)
            print(
                f"jitter ratio on/off (medians over rounds): p99 {p99_on / max(p99_off, 1e-9):.3f}"
                f"  mean {m_on / max(m_off, 1e-9):.3f}  (goal <= 1.05)"
            )
            p99_a = statistics.median(s["jitter_us"]["p99"] for s in apis)
            m_a = statistics.median(s["jitter_us"]["mean"] for s in apis)
            print(
                f"jitter ratio API-subscription/off: p99 {p99_a / max(p99_off, 1e-9):.3f}  "
                f"mean {m_a / max(m_off, 1e-9):.3f}  (the bridge's API subscription, no Zenoh)"
            )
            if hogs:
                p99_h = statistics.median(s["jitter_us"]["p99"] for s in hogs)
                m_h = statistics.median(s["jitter_us"]["mean"] for s in hogs)
                print(
                    f"jitter ratio control/off: p99 {p99_h / max(p99_off, 1e-9):.3f}  "
                    f"mean {m_h / max(m_off, 1e-9):.3f}  (CPU load alone, no Zenoh, no API "
                    "subscription)"
                )
            if figs is not None:
                cond = (
                    f"daemon at nice {daemon_nice}, loop thread {policy}; API {args.api}; "
                    f"router, bridge and subscriber at nice {args.nice}; {args.rounds} rounds of "
                    f"{args.seconds:g} s"
                )
                figs.table(
                    "jitter",
                    [
                        "phase",
                        "loop jitter p99 (median over rounds)",
                        "worst round's p99",
                        "mean",
                        "ratio p99 / off (goal on ≤ 1.05)",
                    ],
                    note=cond,
                )
                for label, sts in (
                    ("bridge off", offs),
                    (f"control: a process busy {args.hog_percent:.0f} % of one core", hogs),
                    ("API subscription only (no Zenoh)", apis),
                    ("bridge + subscriber on", ons),
                ):
                    if sts:
                        p = statistics.median(s["jitter_us"]["p99"] for s in sts)
                        m = statistics.median(s["jitter_us"]["mean"] for s in sts)
                        figs.row(
                            "jitter",
                            [
                                label,
                                f"{p:.0f} µs",
                                f"{max(s['jitter_us']['p99'] for s in sts):.0f} µs",
                                f"{m:.1f} µs",
                                f"{p / max(p99_off, 1e-9):.2f}",
                            ],
                        )
                if n:
                    figs.table(
                        "latency",
                        ["STATE → Zenoh subscriber (/joint_states)", "p50", "p99", "max"],
                        note=cond,
                    )
                    figs.row(
                        "latency",
                        [
                            f"{n} messages",
                            f"{statistics.median(lat):.2f} ms",
                            f"{_pct(lat, 0.99):.2f} ms",
                            f"{max(lat):.2f} ms",
                        ],
                    )
                figs.save()
        finally:
            srv.stop()
            daemon.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())

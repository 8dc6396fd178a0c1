"""ROS 2 over Zenoh benchmark: segment STATE -> Zenoh subscriber latency on loopback, and what the
bridge plus a subscriber do to the control loop's jitter. Runs the real daemon on an emulated
3-segment chain, `ucr zenoh-router` and `ucr zenoh` as their own processes (as deployed), and a
Zenoh subscriber on /<robot>/joint_states and /<robot>/tf in this process.

    .venv/bin/python benchmarks/bench_zenoh.py [--seconds 5]

Latency: receive time (wall clock) minus the JointState header stamp, which is the daemon's
time of the cycle that produced the state (daemon monotonic clock mapped to wall clock; same
machine). It covers daemon -> API -> bridge (decode, CDR encode) -> Zenoh -> subscriber.
Jitter: the daemon's |period - target| p99 and mean, bridge off vs on; goal ratio <= 1.05.
Prints figures and ratios; asserts nothing (the machine may be shared and noisy).
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


def _ucr(*args: str, nice: int = 0) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "tools.cli", *args], cwd=ROOT,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            preexec_fn=(lambda: os.nice(nice)) if nice else None)  # fmt: skip


def _stop(proc: subprocess.Popen) -> None:
    proc.send_signal(signal.SIGINT)
    try:
        proc.wait(timeout=20)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def main(argv: list[str] | None = None) -> int:
    import zenoh

    from interop import ros2
    from interop.ros2.type_hash import type_hash
    from interop.zenoh import rmw
    from tools.rig import EmulatedRig

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=5.0, help="duration of each phase, s")
    ap.add_argument(
        "--nice",
        type=int,
        default=10,
        help="niceness of the router and bridge processes (10, as docs/ros2.md "
        "recommends for the service; 0: same priority as the daemon)",
    )
    args = ap.parse_args(argv)

    js_type, tf_type = "sensor_msgs/msg/JointState", "tf2_msgs/msg/TFMessage"
    with EmulatedRig(ROOT / "robots" / "softrobot3.ucrdf", boot_timeout_s=15) as rig:
        robot, daemon, srv = rig.robot, rig.daemon, rig.srv
        ns = rmw.namespace_for(robot.name)
        port = _free_port()
        router = bridge = None
        try:
            time.sleep(0.5)
            off = _jitter(daemon, args.seconds)

            router = _ucr("zenoh-router", "--listen", f"tcp/127.0.0.1:{port}", nice=args.nice)
            time.sleep(1.5)
            bridge = _ucr("zenoh", "--url", srv.url, "--connect", f"tcp/127.0.0.1:{port}",
                          "--listen", "tcp/127.0.0.1:0", nice=args.nice)  # fmt: skip
            line = bridge.stderr.readline()
            if "ROS 2 node" not in line:
                print(f"bridge did not start: {line}{bridge.stderr.read()}", file=sys.stderr)
                return 1
            conf = zenoh.Config()
            conf.insert_json5("mode", '"peer"')
            conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
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
                subs = [session.declare_subscriber(key_js, on_js),
                        session.declare_subscriber(key_tf, on_tf)]  # fmt: skip
                time.sleep(2.0)  # discovery, first messages
                lat.clear()
                tf_count[0] = 0
                on = _jitter(daemon, args.seconds)
                for s in subs:
                    s.undeclare()
            n = len(lat)
            if n:
                print(f"STATE -> Zenoh subscriber (/joint_states)  n={n} "
                      f"({n / args.seconds:.0f}/s)  p50 {statistics.median(lat):.2f} ms  "
                      f"p99 {_pct(lat, 0.99):.2f} ms  max {max(lat):.2f} ms")  # fmt: skip
            else:
                print("STATE -> Zenoh subscriber: no message received")
            print(f"/tf messages received: {tf_count[0]} ({tf_count[0] / args.seconds:.0f}/s)")
            print(f"loop rate {daemon.rate_hz:.0f} Hz; router and bridge at nice {args.nice}")
            for label, st in (("bridge off", off), ("bridge + subscriber on", on)):
                j = st["jitter_us"]
                print(f"{label:<24} jitter p99 {j['p99']:7.0f} µs  mean {j['mean']:6.0f} µs  "
                      f"overruns {st['overruns']}")  # fmt: skip
            r99 = on["jitter_us"]["p99"] / max(off["jitter_us"]["p99"], 1e-9)
            rmean = on["jitter_us"]["mean"] / max(off["jitter_us"]["mean"], 1e-9)
            print(f"jitter ratio on/off: p99 {r99:.3f}  mean {rmean:.3f}  (goal <= 1.05)")
        finally:
            for p in (bridge, router):
                if p is not None:
                    _stop(p)
            rig.stop_daemon()
    return 0


if __name__ == "__main__":
    sys.exit(main())

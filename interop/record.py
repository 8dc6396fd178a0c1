"""``ucr record``: the live robot into an MCAP file that rosbag2 readers, Foxglove and Lichtblick
open without ucr (ROS 2 schemas, ``ros2msg`` schema text, CDR messages; docs/recording.md).

The file is written with the ``mcap`` library: zstd-compressed chunks, closed at least every
``flush_interval`` seconds (and at ``chunk_size`` bytes) and fsynced then, so a recorder killed
mid-run (SIGKILL, power loss) leaves a file readable up to its last closed chunk; a clean stop
(Ctrl-C, SIGTERM, ``--duration``) writes the summary and index as well.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path
from typing import IO, Any

from mcap.writer import CompressionType, Writer

from host.api.client import ApiError
from host.client_common import CliError, connect_daemon
from host.stopsignals import INTERRUPTED, StopSignals
from interop import ros2
from interop.live import DaemonLink, FeedError, LiveFeed, robot_for, run_reconnecting
from interop.sinks import Fanout
from interop.topics import LATCHED, RobotTopics
from ucrdf.errors import UcrdfError

PROFILE = "ros2"  # the MCAP profile rosbag2 writes

# The QoS a ucr publisher offers, in the YAML rosbag2 (Jazzy) writes into each channel's
# ``offered_qos_profiles`` metadata; ``ros2 bag play`` re-offers it. Durations "infinite" as
# RMW_DURATION_INFINITE. Latched topics: transient_local, depth 1 (as robot_state_publisher).
_INFINITE = "{sec: 9223372036, nsec: 854775807}"
_QOS = (
    "- history: keep_last\n  depth: {depth}\n  reliability: reliable\n"
    "  durability: {durability}\n  deadline: {inf}\n  lifespan: {inf}\n"
    "  liveliness: automatic\n  liveliness_lease_duration: {inf}\n"
    "  avoid_ros_namespace_conventions: false"
)


def offered_qos_profiles(topic: str) -> str:
    """The ``offered_qos_profiles`` YAML of a topic, as rosbag2 writes it into MCAP channels."""
    if topic in LATCHED:
        return _QOS.format(depth=1, durability="transient_local", inf=_INFINITE)
    return _QOS.format(depth=100 if topic.startswith("/tf") else 10, durability="volatile",
                       inf=_INFINITE)  # fmt: skip


class McapSink:
    """Writes encoded ROS 2 messages into an MCAP file (one schema per type, one channel per
    topic, registered when first used)."""

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        compression: str = "zstd",
        chunk_size: int = 256 * 1024,
        flush_interval: float = 1.0,
        overwrite: bool = True,
    ) -> None:
        kinds = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4,
                 "none": CompressionType.NONE}  # fmt: skip
        if compression not in kinds:
            raise ValueError(f"compression must be one of {', '.join(kinds)}, got {compression!r}")
        self.path = Path(path)
        # overwrite=False: FileExistsError rather than replace a file created meanwhile
        self._file: IO[bytes] = open(self.path, "wb" if overwrite else "xb")  # noqa: SIM115
        self._writer = Writer(self._file, chunk_size=chunk_size, compression=kinds[compression])
        self._writer.start(profile=PROFILE, library="ucr interop.record (mcap)")
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._seq: dict[int, int] = {}
        self.flush_interval = flush_interval
        self._next_flush = time.monotonic() + flush_interval
        self.messages = 0
        self.t_first: int | None = None
        self.t_last: int | None = None
        self.closed = False
        self.fsyncs = 0  # chunks made durable, and the time that took (s): docs/recording.md
        self.fsync_s = 0.0

    def write(self, topic: str, typename: str, schema: str, data: bytes, t_ns: int) -> None:
        cid = self._channels.get(topic)
        if cid is None:
            sid = self._schemas.get(typename)
            if sid is None:
                sid = self._writer.register_schema(
                    name=typename, encoding=ros2.SCHEMA_ENCODING, data=schema.encode()
                )
                self._schemas[typename] = sid
            cid = self._writer.register_channel(
                topic=topic, message_encoding=ros2.MESSAGE_ENCODING, schema_id=sid,
                metadata={"offered_qos_profiles": offered_qos_profiles(topic)},
            )  # fmt: skip
            self._channels[topic] = cid
        seq = self._seq.get(cid, 0)
        self._seq[cid] = seq + 1
        self._writer.add_message(
            channel_id=cid, log_time=t_ns, data=data, publish_time=t_ns, sequence=seq
        )
        self.messages += 1
        self.t_first = t_ns if self.t_first is None else self.t_first
        self.t_last = t_ns
        self.tick()

    def tick(self) -> None:
        """Close the current chunk if it is older than ``flush_interval``."""
        now = time.monotonic()
        if now >= self._next_flush:
            self.flush()

    def flush(self) -> None:
        """Close the current chunk now (compressed, indexed) and fsync it: on the disk, not
        only in the OS's cache, so it survives a power cut as well as a killed recorder."""
        self._next_flush = time.monotonic() + self.flush_interval
        self._writer.flush()  # writes the chunk and flushes the Python buffer to the OS
        t = time.perf_counter()
        os.fsync(self._file.fileno())
        self.fsync_s += time.perf_counter() - t
        self.fsyncs += 1

    @property
    def bytes_written(self) -> int:
        return self._file.tell() if not self.closed else self.path.stat().st_size

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        try:
            self._writer.finish()
            self._file.flush()
            os.fsync(self._file.fileno())  # the summary too: a power cut after a clean stop
        finally:
            self._file.close()


def _human_bytes(n: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB"):
        if n < 1024 or unit == "GiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} GiB"


class Progress:
    """One status line on the terminal (rewritten in place on a tty, a line every 5 s else)."""

    def __init__(self, sink: McapSink, stream: Any = None) -> None:
        self.sink = sink
        self.stream = stream or sys.stderr
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.t0 = time.monotonic()
        self._next = 0.0

    def line(self) -> str:
        s = self.sink
        return (f"recording {s.path}  {time.monotonic() - self.t0:6.1f} s  "
                f"{s.messages} messages  {_human_bytes(s.bytes_written)}")  # fmt: skip

    def __call__(self, final: bool = False) -> None:
        now = time.monotonic()
        if not final and now < self._next:
            return
        self._next = now + (0.5 if self.tty else 5.0)
        if self.tty:
            self.stream.write("\r" + self.line() + ("\n" if final else ""))
        else:
            self.stream.write(self.line() + "\n")
        self.stream.flush()


def output_refusal(path: str | os.PathLike[str], overwrite: bool) -> str | None:
    """Why ``ucr record -o path`` must not start, else None: an existing recording is kept
    unless ``--overwrite`` (as ``ros2 bag record``); a directory, a missing directory or a
    symlink to nothing never."""
    p = Path(path)
    if p.is_dir():
        return f"{p} is a directory: give a file name, e.g. {p / 'run.mcap'}"
    if p.is_symlink() and not p.exists():
        return (f"{p} is a symlink to {os.readlink(p)}, which does not exist: refused, "
                "not followed")  # fmt: skip
    if p.exists() and not overwrite:
        return f"{p} exists: refused, it is kept (--overwrite replaces it)"
    if not p.parent.is_dir():
        return f"{p}: directory {p.parent} does not exist"
    return None


#: The port of ``ucr record --foxglove-host H`` without ``--foxglove-port`` (``ucr foxglove``'s).
DEFAULT_FOXGLOVE_PORT = 8766


def foxglove_address(args: Any) -> tuple[str, int | None]:
    """(host, port) of the Foxglove server ``ucr record`` also runs; port None: no server.
    ``--foxglove-host`` alone serves on the default port (8766, as ``ucr foxglove``)."""
    host = getattr(args, "foxglove_host", None)
    port = getattr(args, "foxglove_port", None)
    if port is None and host is not None:
        port = DEFAULT_FOXGLOVE_PORT
    return host or "127.0.0.1", port


def run(args: Any) -> int:
    """The ``ucr record`` command: 0 at the end (``--duration``, SIGTERM), 130 after Ctrl-C,
    1 when the file cannot be written (the recording stops at once)."""
    signals = StopSignals().install()
    stop, interrupted = signals.stop, signals.interrupted
    failed: list[str] = []  # why the file sink was dropped
    refusal = output_refusal(args.output, getattr(args, "overwrite", False))
    if refusal:  # before connecting: nothing to wait for
        print(f"ucr: {refusal}", file=sys.stderr)
        return 1
    try:
        link = DaemonLink(connect_daemon(args))  # the client of the moment: a restart replaces it
    except CliError as exc:
        print(f"ucr: {exc}", file=sys.stderr)
        return exc.exit_code
    sinks: list[Any] = []
    try:
        robot, text = robot_for(link, args.robot)
        topics = RobotTopics(robot, text, args.subdivisions)
        host, port = foxglove_address(args)
        if port is not None:  # before the file: a refused address or port leaves no file behind
            from interop.foxglove import sink_from_args  # noqa: PLC0415 - only when asked

            fox = sink_from_args(host, port, args, option="--foxglove-port")
            sinks.append(fox)
            print(f"ucr: Foxglove WebSocket server on {fox.url}", file=sys.stderr, flush=True)
        if interrupted.is_set():  # Ctrl-C while starting: no file
            print("ucr: interrupted (Ctrl-C) before recording", file=sys.stderr)
            return INTERRUPTED
        try:
            sink = McapSink(args.output, compression=args.compression,
                            flush_interval=args.flush_interval,
                            overwrite=getattr(args, "overwrite", False))  # fmt: skip
        except FileExistsError:
            why = output_refusal(args.output, False) or f"{args.output} appeared meanwhile"
            print(f"ucr: {why}: refused", file=sys.stderr)
            return 1
        except OSError as exc:
            print(f"ucr: cannot create {args.output}: {exc.strerror or exc}", file=sys.stderr)
            return 1
        sinks.insert(0, sink)

        def on_drop(dropped: Any, exc: Exception) -> None:
            if dropped is sink:  # the recording itself failed (disk full, I/O error): stop
                failed.append(getattr(exc, "strerror", None) or f"{type(exc).__name__}: {exc}")
                stop.set()
            else:  # the live Foxglove server: the recording goes on
                print(f"ucr: the Foxglove server stopped: {exc}", file=sys.stderr)

        out = Fanout(sinks, on_drop=on_drop)
        progress = Progress(sink)

        def say(line: str) -> None:  # below the progress line written in place
            print(f"{chr(10) if progress.tty else ''}ucr: {line}", file=sys.stderr, flush=True)

        # a daemon restart: the same file goes on, the gap marked by two events (docs)
        dropped = run_reconnecting(
            link, lambda client: LiveFeed(client, topics, out, viz_rate=args.viz_rate), stop,
            lambda: connect_daemon(args), robot_text=text, robot_path=args.robot,
            duration=args.duration, on_tick=progress, say=say,
        )  # fmt: skip
        if not failed:
            try:
                sink.close()  # the summary, fsynced: may fail as any write
            except OSError as exc:
                failed.append(exc.strerror or str(exc))
        if failed:
            end = "\n" if progress.tty else ""  # after the progress line written in place
            print(f"{end}ucr: recording stopped: cannot write {sink.path}: {failed[0]}",
                  file=sys.stderr)  # fmt: skip
            return 1
        progress(final=True)
        if dropped:
            print(f"ucr: {dropped} stream messages were dropped (recorder too slow)",
                  file=sys.stderr)  # fmt: skip
        if interrupted.is_set():
            print(f"ucr: interrupted (Ctrl-C): {sink.path} closed", file=sys.stderr)
        return signals.exit_code()
    except OSError as exc:
        print(f"ucr: {exc.strerror or exc}", file=sys.stderr)
        return 1
    except (FeedError, ValueError, RuntimeError, UcrdfError) as exc:
        print(f"ucr: {exc}", file=sys.stderr)
        return 1
    except ApiError as exc:
        print(f"ucr: recording stopped: {exc}", file=sys.stderr)
        return 1
    finally:
        for s in sinks:
            try:
                s.close()
            except OSError:  # the file sink's failure is reported above
                pass
        link.close()

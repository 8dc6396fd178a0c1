"""Where the view's robot state comes from: the daemon's API (live) or a U(C)RDF file (offline).

Both keep a small :class:`Snapshot` under a lock; the view's update thread polls it, so a slow page
never slows the source and the daemon never waits for the view (the API drops stream messages for
a slow reader; we read with a bounded queue of our own).
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from host.api.client import ApiError, connect
from host.api.reconnect import reconnect
from host.api.schema import robot_description
from ucrdf.errors import UcrdfError
from ucrdf.parser import load, parse_string
from view.control import FfcParams, driven_ffc

log = logging.getLogger("ucr.view")

#: A segment event keeps its colour this long (s).
EVENT_HOLD_S = 1.5
#: joint_states per second while no page is open (nothing is drawn; the first page's scene is at
#: most this old until the full rate resumes, within :data:`DEMAND_CHECK_S`).
IDLE_RATE_HZ = 2.0
#: How often (s) the stream thread looks whether a page opened or the last one closed.
DEMAND_CHECK_S = 0.1
#: The upload id the scope probe cancels (none of ours: the reply is not_found or forbidden);
#: sent only to a daemon older than the ``session`` op.
SCOPE_PROBE_UPLOAD = 2**31 - 1
#: Relative tolerance comparing FILE's segment geometry and limits with the daemon's ``topology``
#: segments (a daemon older than ``robot.description``).
CONTENT_RTOL = 1e-3
#: How many of our API connections' addresses are remembered (``LiveSource.own_peers``).
OWN_PEERS = 8
#: Differences named in a mismatch message at most (then "and N more").
MAX_NAMED_DIFFERENCES = 8
#: The end of every mismatch message: what happens and what to do.
_REFUSED = (
    "Controls refused (view only): run `ucr view` without FILE to use the daemon's own file, or "
    "give the file the daemon runs."
)


@dataclass
class Snapshot:
    """What the view knows now. ``t_daemon``: daemon monotonic time (s) of the joint states."""

    robot_file: str = ""
    robot_version: int = 0  # bumps when the robot file (re)loads
    present: list[str] = field(default_factory=list)  # bendables on the chain (live) / all
    expected: list[str] = field(default_factory=list)
    state: dict[str, dict[str, float]] = field(default_factory=dict)  # name -> kappa, phi
    valid: dict[str, bool] = field(default_factory=dict)
    status: dict[str, str] = field(default_factory=dict)  # ok | clamped | fault | missing
    t_daemon: float = 0.0
    t_received: float = 0.0  # our monotonic clock when it arrived
    seq: int = 0  # bumps with every change (joint state, file reload, connection, topology)
    sample_seq: int = 0  # bumps with every sample: a daemon joint state / an offline slider move
    topology_seq: int = 0  # bumps with every topology change
    control: dict[str, Any] = field(default_factory=dict)  # from status(): who controls
    errors: list[str] = field(default_factory=list)  # file problems (offline) / connection
    connected: bool = False
    #: why the FILE given does not describe the daemon's robot ("" when it does): no controls
    mismatch: str = ""


def _num(v: float) -> str:
    """A number as short as it reads back (``0.316``), else in full (``0.31600000001``)."""
    return f"{v:g}" if float(f"{v:g}") == v else repr(v)


def _content_differences(robot: Any, segments: list, rtol: float = CONTENT_RTOL) -> list[str]:
    """How FILE's bendables differ from the daemon's segments (``topology`` ``segments`` or
    :func:`_segments_of` the daemon's description: model, length, kappa_max, kappa_rate_max),
    i.e. what the page draws and solves IK with; [] when they agree (within ``rtol``)."""
    out: list[str] = []
    for seg in segments:
        if not isinstance(seg, dict):
            continue
        name = seg.get("bendable")
        b = robot.bendables.get(name) if isinstance(name, str) else None
        if b is None:
            continue
        mine = {
            "model": b.model.type,
            "length": b.model.backbone.length,
            "kappa_max": b.model.limits.kappa_max,
            "kappa_rate_max": b.model.limits.kappa_rate_max,
        }
        for key, ours in mine.items():
            theirs = seg.get(key)
            if theirs is None or ours is None:
                continue  # not declared on one side: nothing to compare
            if key == "model":
                if str(theirs) != str(ours):
                    out.append(f"{name} model: the daemon's {theirs!r}, the file's {ours!r}")
                continue
            try:
                a, c = float(theirs), float(ours)
            except (TypeError, ValueError):
                continue
            if abs(a - c) > rtol * max(abs(a), abs(c), 1e-9):
                out.append(f"{name} {key}: the daemon's {_num(a)}, the file's {_num(c)}")
    return out


def _segments_of(robot: Any) -> list[dict]:
    """A robot's bendables as ``topology`` ``segments`` describe them (for
    :func:`_content_differences`)."""
    return [
        {"bendable": n, "model": b.model.type, "length": b.model.backbone.length,
         "kappa_max": b.model.limits.kappa_max, "kappa_rate_max": b.model.limits.kappa_rate_max}
        for n, b in robot.bendables.items()
    ]  # fmt: skip


def description_sha256(robot: Any) -> str:
    """The sha256 of a robot's canonical U(C)RDF text, as the daemon's ``robot.description``
    computes it for its own robot."""
    return robot_description(robot)["sha256"]


def _element_differences(ours: Any, theirs: Any, named: set[str]) -> list[str]:
    """Which links, joints and bendables (and ros2_control blocks, extension elements) differ
    between FILE's robot (``ours``) and the daemon's (``theirs``), and in which fields; a
    bendable in ``named`` was already described by its numbers, its ``model`` is not repeated."""
    out: list[str] = []
    for what, mine, their in (
        ("link", ours.links, theirs.links),
        ("joint", ours.joints, theirs.joints),
        ("bendable", ours.bendables, theirs.bendables),
    ):
        for name in [*their, *(n for n in mine if n not in their)]:
            if name not in mine:
                out.append(f"{what} {name!r} only in the daemon's")
            elif name not in their:
                out.append(f"{what} {name!r} only in the file")
            elif mine[name] != their[name]:
                fields = [
                    f.name
                    for f in dataclasses.fields(mine[name])
                    if f.compare and getattr(mine[name], f.name) != getattr(their[name], f.name)
                ]
                if what == "bendable" and name in named:
                    fields = [f for f in fields if f != "model"]
                if fields:
                    verb = "differs" if len(fields) == 1 else "differ"
                    out.append(f"{what} {name!r}: {', '.join(fields)} {verb}")
    if ours.ros2_control != theirs.ros2_control:
        out.append("ros2_control differs")
    if ours.extensions != theirs.extensions:
        out.append("extension elements (<gazebo>, <material>, …) differ")
    return out


def description_differences(robot: Any, description: dict) -> list[str]:
    """How FILE's ``robot`` differs from the daemon's (``description``: a ``robot.description``
    reply), in plain words, the sha256 of both last; [] when it is the same robot. Compared as
    parsed models (comments, spacing, attribute order and number spelling do not count); a
    description without its text (too large) is compared by its sha256 alone."""
    theirs = None
    text = description.get("text")
    if isinstance(text, str):
        try:
            theirs = parse_string(text, source="the daemon's description", check=False)
        except UcrdfError:
            theirs = None
    ours_sha = description_sha256(robot)
    their_sha = str(description.get("sha256") or "")
    out: list[str] = []
    if theirs is not None:
        if theirs == robot:
            return []
        from host.topology import chain_bendables  # noqa: PLC0415 - only with a FILE

        if theirs.name != robot.name:
            out.append(f"robot name: the daemon's {theirs.name!r}, the file's {robot.name!r}")
        mine, their = chain_bendables(robot), chain_bendables(theirs)
        if mine != their:
            out.append(
                f"bendables in chain order: the daemon's ({', '.join(their) or 'none'}), "
                f"the file's ({', '.join(mine) or 'none'})"
            )
        numbers = _content_differences(robot, _segments_of(theirs), rtol=0.0)
        named = {line.split(" ", 1)[0] for line in numbers}
        out += numbers + _element_differences(robot, theirs, named)
    elif ours_sha == their_sha:
        return []
    else:
        name = description.get("robot")
        if isinstance(name, str) and name != robot.name:
            out.append(f"robot name: the daemon's {name!r}, the file's {robot.name!r}")
    if len(out) > MAX_NAMED_DIFFERENCES:
        more = len(out) - MAX_NAMED_DIFFERENCES
        out = [*out[:MAX_NAMED_DIFFERENCES], f"and {more} more difference(s)"]
    where = description.get("file")
    out.append(
        f"the daemon's robot description{f' ({where})' if where else ''} differs from the file "
        f"(the daemon's sha256 {their_sha[:12]}…, the file's {ours_sha[:12]}…)"
    )
    return out


def daemon_is_local(url: str | None) -> bool:
    """Whether the daemon's API URL (None: $UCR_URL or the loopback default) names this machine
    (a loopback address or ``localhost``)."""
    import os  # noqa: PLC0415
    from urllib.parse import urlsplit  # noqa: PLC0415

    from host.api.guard import is_loopback  # noqa: PLC0415

    url = url or os.environ.get("UCR_URL") or "ws://127.0.0.1:8765"
    try:
        host = urlsplit(url if "//" in url else f"ws://{url}").hostname or ""
    except ValueError:
        return False
    return is_loopback(host)


class RobotFileError(RuntimeError):
    """The daemon answered, but the robot file to draw (FILE, or the one it names) does not
    load: its check errors (``path:line: message``) are in ``errors``."""

    def __init__(self, path: str, errors: list[str]) -> None:
        super().__init__(f"{path} does not load: " + "; ".join(errors))
        self.path = path
        self.errors = errors


class OfflineSource:
    """A U(C)RDF file, reloaded when it changes on disk; the sliders are the configuration."""

    mode = "offline"

    def __init__(
        self,
        path: str | Path,
        poll_s: float = 0.3,
        on_errors: Callable[[list[str]], None] | None = None,
    ):
        """``on_errors`` is called with the check errors (``path:line: ...``) whenever they
        change, from the first load on (``[]``: the file loads again)."""
        self.path = Path(path)
        self.poll_s = poll_s
        self.on_errors = on_errors
        self._reported: list[str] = []
        self.lock = threading.Lock()
        self.snap = Snapshot(robot_file=str(self.path))
        self.robot = None
        self._mtime: float | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="ucr-view-file", daemon=True)
        self._reload()

    def start(self) -> OfflineSource:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()

    def _stamp(self) -> float | None:
        try:
            st = self.path.stat()
            return st.st_mtime_ns + st.st_size
        except OSError:
            return None

    def _reload(self) -> None:
        self._mtime = self._stamp()
        try:
            robot = load(self.path)
        except UcrdfError as exc:
            errors = [str(d) for d in exc.diagnostics]
            with self.lock:
                self.snap.errors = errors
                self.snap.seq += 1
            self._report(errors)
            return
        self._report([])
        with self.lock:
            self.robot = robot
            s = self.snap
            s.errors = []
            s.robot_version += 1
            s.present = s.expected = list(robot.bendables)
            s.state = {n: dict(v) for n, v in s.state.items() if n in robot.bendables}
            s.status = {n: "ok" for n in robot.bendables}
            s.valid = {n: True for n in robot.bendables}
            s.topology_seq += 1
            s.seq += 1

    def _report(self, errors: list[str]) -> None:
        if self.on_errors is not None and errors != self._reported:
            self._reported = errors
            self.on_errors(errors)

    def set_target(self, name: str, kappa: float, phi: float) -> None:
        """Offline sliders drive FK directly."""
        with self.lock:
            self.snap.state[name] = {"kappa": kappa, "phi": phi}
            self.snap.t_received = time.monotonic()
            self.snap.seq += 1
            self.snap.sample_seq += 1

    def _run(self) -> None:
        while not self._stop.wait(self.poll_s):
            if self._stamp() != self._mtime:
                self._reload()


class LiveSource:
    """The daemon: topology, joint states, events and who has control, over its API.

    When the connection drops (daemon restarted, network gone) the page shows "daemon
    disconnected", every segment turns grey and the source reconnects by itself with back-off
    (host.api.reconnect: 0.5 s doubling up to 5 s); once back, the robot file is read again
    and the scene rebuilt (``snap.robot_version`` bumps)."""

    mode = "live"

    def __init__(
        self,
        url: str | None,
        token: str | None,
        robot_file: str | None = None,
        rate_hz=60.0,
        timeout: float = 5.0,
    ):
        """``timeout``: seconds to wait for the daemon's handshake and each reply."""
        self._token = token
        self.timeout = timeout
        self.client = connect(url, token=token, timeout=timeout, agent="ucr view")
        self.url = self.client_url = url
        #: the daemon runs on this machine: its monotonic stamps are on our clock (the latency
        #: figure is shown only then: the API gives no clock of the daemon's to estimate an
        #: offset from)
        self.local = daemon_is_local(url)
        self.rate_hz = rate_hz
        #: a page is open (:meth:`set_demand`): joint_states at ``rate_hz``, else
        #: :data:`IDLE_RATE_HZ` (what the daemon's API and this process spend on a view nobody
        #: looks at); the rate subscribed now is ``stream_rate_hz``
        self._demand = threading.Event()
        self._demand.set()
        self.stream_rate_hz: float | None = None
        self.lock = threading.Lock()
        self.snap = Snapshot(connected=True)
        self.robot = None
        #: the daemon's cFFC parameters (the slider drive's model), read once per connection
        self.ffc_params: FfcParams | None = None
        self._robot_file = robot_file
        self._stop = threading.Event()
        self._events: dict[str, tuple[str, float]] = {}  # bendable -> (status, until)
        self._topo_dirty = False
        self._faults: set[str] = set()  # segments the daemon reports in FAULT (status)
        self.reconnects = 0
        #: what the token may do: "control" or "read" (asked of the daemon: :meth:`_ask_scope`)
        self.scope = "control"
        #: how the scope was learnt: "session" (the daemon said) or "probe" (an older daemon)
        self.scope_from = ""
        #: our API connections' addresses as the daemon saw them (its ``session``'s ``peer``;
        #: the latest few): a cFFC input ``input_from`` one of them is this view's own
        self.own_peers: collections.deque[str] = collections.deque(maxlen=OWN_PEERS)
        #: the daemon's ``robot.description`` (compared with FILE), None until asked / unknown
        self._description: dict | None = None
        self._no_description = False  # the daemon has no robot.description op (older)
        try:
            self._topology_locked_refresh()
            self.scope, self.scope_from = self._ask_scope(self.client, self.own_peers)
        except BaseException:  # no reply in time, no robot file: do not leave it connected
            self.client.close()
            raise
        self._supervisor = threading.Thread(
            target=self._supervise, name="ucr-view-session", daemon=True
        )

    def start(self) -> LiveSource:
        self._supervisor.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        try:
            self.client.close()
        except Exception:  # noqa: BLE001 - closing a broken connection
            pass

    # -- sessions ------------------------------------------------------------------------------
    def _supervise(self) -> None:
        """One session per connection: the stream and status threads until the connection
        drops, then reconnect with back-off, until stopped."""
        while not self._stop.is_set():
            lost = threading.Event()
            client = self.client
            threads = [
                threading.Thread(target=self._stream, args=(client, lost), daemon=True,
                                 name="ucr-view-stream"),
                threading.Thread(target=self._poll_status, args=(client, lost), daemon=True,
                                 name="ucr-view-status"),
            ]  # fmt: skip
            for t in threads:
                t.start()
            while not (lost.is_set() or self._stop.is_set()):
                lost.wait(0.5)
            if self._stop.is_set():
                return
            try:
                client.close()
            except Exception:  # noqa: BLE001, S110 - already broken
                pass
            for t in threads:
                t.join(timeout=2.0)
            if not self._reconnect():
                return

    def _reconnect(self) -> bool:
        """Connect again (host.api.reconnect's back-off); True once connected and the robot
        re-read."""

        def attempt() -> Any:
            client = connect(self.url, token=self._token, timeout=self.timeout, agent="ucr view")
            self.client = client
            try:
                self.robot = None  # the daemon may run another file now: read it again
                self._description, self._no_description = None, False  # and another daemon
                self._topology_locked_refresh()
                # the daemon's token config may change
                self.scope, self.scope_from = self._ask_scope(client, self.own_peers)
            except Exception:  # not ready (rebuilding): retried
                try:
                    client.close()
                except Exception:  # noqa: BLE001, S110 - already broken
                    pass
                raise
            return client

        back = reconnect(attempt, self._stop, self._note_lost)
        if back is None:
            return False
        with self.lock:
            self.snap.connected = True
            self.snap.errors = []
            self.snap.seq += 1
            self.reconnects += 1
        log.warning("reconnected to the daemon (attempt %d)", back[1])
        return True

    def _note_lost(self, why: str, attempt: int, next_s: float) -> None:
        with self.lock:
            self.snap.connected = False
            why = f"{why} — reconnecting (attempt {attempt}, next in {next_s:.1f} s)"
            self.snap.errors = [f"daemon disconnected: {why}"]
            self.snap.seq += 1

    # -- scope ---------------------------------------------------------------------------------
    @classmethod
    def _ask_scope(cls, client: Any, peers: collections.deque | None = None) -> tuple[str, str]:
        """What this connection's token may do, as the daemon says it (``session``): "read" or
        "control", and "session". A daemon older than that op (any refusal of it, e.g.
        ``unknown_op``) is probed instead (:meth:`_probe_scope`, then "probe"). ``peers``
        gets the connection's address as the daemon sees it, when it says."""
        try:
            answer = client.call("session")
            scope = answer.get("scope")
            peer = answer.get("peer")
            if peers is not None and isinstance(peer, str) and peer not in peers:
                peers.append(peer)
        except ApiError as exc:
            if isinstance(exc, ConnectionError | TimeoutError):
                raise
            scope = None
        except AttributeError:  # not an object: not an answer
            scope = None
        if scope in ("read", "control"):
            return scope, "session"
        log.info("the daemon does not say its session's scope (an older daemon): probing it")
        return cls._probe_scope(client), "probe"

    @staticmethod
    def _probe_scope(client: Any) -> str:
        """What this connection's token may do, for a daemon without ``session``: a control-scope
        op that changes nothing, ``trajectory.upload_cancel`` of an upload no connection of ours
        holds: a read token gets ``forbidden`` (checked before the op runs, docs/api.md), a
        control token ``not_found``. "read" or "control"."""
        try:
            client.call("trajectory.upload_cancel", upload=SCOPE_PROBE_UPLOAD)
        except ApiError as exc:
            if exc.code == "forbidden":
                return "read"
            if isinstance(exc, ConnectionError | TimeoutError):
                raise
        return "control"

    # -- topology ------------------------------------------------------------------------------
    def _topology_locked_refresh(self) -> None:
        """Ask the daemon for its topology and apply it (the robot file read if not yet)."""
        self._apply_topology(self.client.topology())

    def _apply_topology(self, topo: dict) -> None:
        """The daemon's topology (a ``topology`` reply or push): which segments are present."""
        path = self._robot_file or topo.get("file")
        robot = self.robot
        errors: list[str] = []
        if robot is None:
            if not path:
                raise RuntimeError(
                    "the daemon did not say which U(C)RDF file it runs: pass it (ucr view FILE)"
                )
            try:
                robot = load(path)
            except UcrdfError as exc:
                raise RobotFileError(str(path), [str(d) for d in exc.diagnostics]) from None
        description = self._daemon_description(topo) if self._robot_file else None
        mismatch = self._mismatch(robot, topo, description)
        with self.lock:
            s = self.snap
            if self.robot is None:
                self.robot = robot
                s.robot_file = str(path)
                s.robot_version += 1
            s.expected = [n for n in topo.get("expected", []) if n in robot.bendables] or list(
                robot.bendables
            )
            s.present = [n for n in topo.get("controlled", []) if n in robot.bendables]
            s.errors = errors
            s.topology_seq += 1
            s.seq += 1
            self._recolour(time.monotonic())
            said, s.mismatch = s.mismatch, mismatch
        if mismatch and mismatch != said:
            log.warning("%s", mismatch)
        elif said and not mismatch:
            log.warning("%s matches the daemon's robot again: controls back", self._robot_file)

    def _daemon_description(self, topo: dict) -> dict | None:
        """The daemon's ``robot.description``, asked again only when ``topo`` names another
        robot, file or description sha256 than the one held (a topology push carries no sha256:
        the robot, file and reconnects tell); None from a daemon without it."""
        held = self._description
        desc = topo.get("description")
        sha = desc.get("sha256") if isinstance(desc, dict) else None
        if held is not None and (
            held.get("robot") == topo.get("robot")
            and held.get("file") == topo.get("file")
            and sha in (None, held.get("sha256"))
        ):
            return held
        if self._no_description:
            return None
        try:
            got = self.client.call("robot.description")
        except ApiError as exc:
            if isinstance(exc, ConnectionError | TimeoutError):
                raise
            if exc.code == "unknown_op":
                self._no_description = True  # an older daemon: not asked again
                log.info("the daemon does not describe its robot (older): FILE compared by "
                         "its bendables only")  # fmt: skip
            return None
        if not isinstance(got, dict) or not got.get("sha256"):
            return None
        self._description = got
        return got

    def _mismatch(self, robot: Any, topo: dict, description: dict | None = None) -> str:
        """Why the FILE given (``ucr view FILE``) is not the daemon's robot; "" if it is (or
        none was given). With the daemon's ``description`` (``robot.description``) the whole
        robot is compared (:func:`description_differences`). Without it (an older daemon): the
        robot's name and its bendables in chain order with the daemon's ``topology``
        (``robot``, ``expected``), and each bendable's model, length and limits with its
        ``segments``. Never by path: the daemon's file path names a file on the daemon's machine,
        relative to its working directory, which the same path here need not be."""
        if not self._robot_file:
            return ""
        if isinstance(description, dict) and description.get("sha256"):
            diffs = description_differences(robot, description)
            if not diffs:
                return ""
            return f"{self._robot_file} is not the daemon's robot: {'; '.join(diffs)}. {_REFUSED}"
        theirs = topo.get("file")
        from host.topology import chain_bendables  # noqa: PLC0415 - only with a FILE

        ours = chain_bendables(robot)
        expected = list(topo.get("expected") or [])
        name = topo.get("robot")
        if ours == expected and (not name or name == robot.name):
            content = _content_differences(robot, topo.get("segments") or [])
            if not content:
                return ""
            return (
                f"{self._robot_file} is not the daemon's robot: same names, but "
                f"{'; '.join(content)}. {_REFUSED}"
            )
        return (
            f"{self._robot_file} is not the daemon's robot: the daemon runs {name!r} "
            f"({theirs or 'file not named'}; bendables {', '.join(expected) or 'none'}), the "
            f"file describes {robot.name!r} (bendables {', '.join(ours) or 'none'}). {_REFUSED}"
        )

    # -- streams -------------------------------------------------------------------------------
    def set_demand(self, pages: bool) -> None:
        """Whether a page is open: the stream runs at ``rate_hz`` while one is, at
        :data:`IDLE_RATE_HZ` while none is (events and topology are never thinned)."""
        if pages:
            self._demand.set()
        else:
            self._demand.clear()

    def _subscribe(self, client: Any) -> tuple[Any, bool]:
        demand = self._demand.is_set()
        rate = self.rate_hz if demand else IDLE_RATE_HZ
        sub = client.subscribe(["joint_states", "events", "topology"], max_rate=rate)
        self.stream_rate_hz = rate
        return sub, demand

    def _stream(self, client: Any, lost: threading.Event) -> None:
        sub = None
        try:
            sub, demand = self._subscribe(client)
            while not (self._stop.is_set() or lost.is_set()):
                if self._demand.is_set() != demand:
                    # a page opened or the last one closed: the new rate's subscription first,
                    # then the old one ends (no event or topology push falls in between)
                    old, (sub, demand) = sub, self._subscribe(client)
                    old.close()
                msg = sub.get(timeout=DEMAND_CHECK_S)
                if msg is None:
                    continue
                kind = msg.get("kind")
                if kind == "joint_states":
                    self._on_joints(msg)
                elif kind == "event":
                    self._on_event(msg)
                elif kind == "topology":
                    self._on_topology(msg)
        except StopIteration:
            self._lost(ConnectionError("subscription closed"), lost)
        except (ConnectionError, ApiError, OSError) as exc:
            self._lost(exc, lost)
        finally:
            if sub is not None:
                with contextlib.suppress(Exception):
                    sub.close()

    def _on_topology(self, msg: dict) -> None:
        """A topology push carries the whole topology: applied at once, so the scene is
        rebuilt on its next update (the status thread retries if this fails)."""
        try:
            self._apply_topology(msg)
        except Exception:  # noqa: BLE001 - refreshed by the status thread instead
            log.debug("topology push not applied; the status poll refreshes it", exc_info=True)
            self._topo_dirty = True

    def _lost(self, exc: BaseException, lost: threading.Event | None = None) -> None:
        if self._stop.is_set():
            return
        with self.lock:
            s = self.snap
            s.connected = False
            s.errors = [f"daemon disconnected: {exc} — reconnecting"]
            s.valid = {n: False for n in s.valid}  # nothing is measured now: sliders stop
            s.status = {n: "missing" for n in s.expected}
            s.seq += 1
        if lost is not None:
            lost.set()

    def _on_joints(self, msg: dict) -> None:
        now = time.monotonic()
        with self.lock:
            s = self.snap
            for i, n in enumerate(msg.get("names", [])):
                k, p = msg["kappa"][i], msg["phi"][i]
                if k is not None and p is not None:
                    s.state[n] = {"kappa": float(k), "phi": float(p)}
                s.valid[n] = bool(msg["valid"][i])
            s.t_daemon = float(msg.get("t", 0.0))
            s.t_received = now
            s.seq += 1
            s.sample_seq += 1
            self._recolour(now)

    def _on_event(self, msg: dict) -> None:
        ev = msg.get("event", "")
        pos = msg.get("position")
        status = {"limit_clamped": "clamped", "servo_fault": "fault", "fault": "fault",
                  "watchdog_tripped": "fault"}.get(ev)  # fmt: skip
        with self.lock:
            names = self.snap.expected
            # segment events count positions from 1, like every position a user sees
            if status and isinstance(pos, int) and 1 <= pos <= len(names):
                self._events[names[pos - 1]] = (status, time.monotonic() + EVENT_HOLD_S)
            self.snap.control["last_event"] = msg.get("message") or ev

    def _recolour(self, now: float) -> None:
        s = self.snap
        for n in s.expected:
            st = "ok"
            if n not in s.present:
                st = "missing"
            elif not s.valid.get(n, False) or n in self._faults:
                st = "fault"  # no valid state, or in FAULT until explicitly cleared
            ev = self._events.get(n)
            if ev is not None and ev[1] > now and st == "ok":
                st = ev[0]
            s.status[n] = st

    def _poll_status(self, client: Any, lost: threading.Event) -> None:
        """Who has control (controllers, takeovers, goals), 5 times a second; the cFFC's
        parameters once per connection (a restarted daemon may have others)."""
        self.ffc_params = None
        while not (self._stop.wait(0.2) or lost.is_set()):
            try:
                st = client.status()
            except Exception as exc:  # noqa: BLE001 - shown on the page, retried
                if isinstance(exc, ConnectionError | OSError):
                    self._lost(exc, lost)
                    return
                continue
            with self.lock:
                present = list(self.snap.present)
            # a topology push, or a missed one: the status names other segments than we draw
            if self._topo_dirty or (
                st.get("state") == "connected" and st.get("segments", present) != present
            ):
                try:
                    self._topo_dirty = False
                    self._topology_locked_refresh()
                except ApiError:  # rebuilding right now: try again on the next poll
                    self._topo_dirty = True
            manual = list(st.get("manual_control") or [])
            ffc = None
            if manual or self.ffc_params is None:
                ffc, params = self._controllers(client, manual)
                if params is not None:
                    self.ffc_params = params
            goals = st.get("running_goals", [])
            goals = goals if isinstance(goals, list) else []
            with self.lock:
                known = self.snap.control.get("goal_from")
            if goals and (known is None or known[0] != goals[0]):
                known = (goals[0], self._goal_sender(client, goals[0]))  # once per goal
            with self.lock:
                self._faults = set(st.get("faults") or {})
                c = self.snap.control
                c["active"] = st.get("active_controllers", [])
                c["manual"] = manual
                c["goals"] = goals
                c["goal_from"] = known if goals else None
                c["state"] = st.get("state", "")
                c["ffc_input"] = ffc

    @staticmethod
    def _goal_sender(client: Any, goal: Any) -> dict | None:
        """Who sent a running goal, as the daemon names it (its status's ``from``: ``peer``,
        ``client``, ``for``); None when it does not say or cannot be asked now."""
        try:
            sender = client.trajectory_status(goal).get("from")
        except Exception:  # noqa: BLE001 - not known this time (asked again for the next goal)
            return None
        return sender if isinstance(sender, dict) else None

    @staticmethod
    def _controllers(
        client: Any, manual: list[str]
    ) -> tuple[tuple[float, float, float, dict | None] | None, FfcParams | None]:
        """From ``controllers.list``: when the manual cFFC's latest input was set, on our
        monotonic clock, and who sent it: ``(earliest, latest, asked, input_from)`` from its
        ``input_age_s`` (the daemon describes it between our request and its reply; None when it
        has no input now, none for longer than its deadman, or it cannot be read) and its
        ``input_from`` (the sender's API connection as the daemon saw it: ``peer``, ``client``,
        ``for``; None from a daemon that does not say, when the view tells its own
        inputs by their times, ``SliderDriver.sent_at``); and the parameters of the cFFC that
        ``ffc.input`` drives (the first active one, else the first; its defaults when the daemon
        does not say; None when the list could not be read)."""
        t_ask = time.monotonic()
        try:
            ctrls = client.controllers()
        except Exception:  # noqa: BLE001 - not known this time
            return None, None
        t_got = time.monotonic()
        ffcs = (
            [c for c in ctrls if isinstance(c, dict) and c.get("type") == "ffc"]
            if isinstance(ctrls, list)
            else []
        )
        driven = driven_ffc(ctrls)
        # a daemon that does not say (older, or no cFFC): the cFFC's defaults, not asked again
        params = (None if driven is None else FfcParams.from_describe(driven)) or FfcParams()
        for c in ffcs:
            if c.get("name") in manual:
                age = c.get("input_age_s")
                sender = c.get("input_from")
                sender = sender if isinstance(sender, dict) else None
                if isinstance(age, int | float):
                    return (t_ask - age - 0.001, t_got - age + 0.001, t_got, sender), params
        return None, params

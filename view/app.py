"""The page: a viser scene of the robot plus its controls, fed by a source (daemon or file).

One update thread polls the source's snapshot and pushes only what changed (tube vertices, link
poses, tendons, colours, trail) in one atomic viser batch; it rebuilds the scene when the robot file
reloads or the chain's topology changes. Facts a test or a person can read are printed on the page
(tube count and names, update rate, latency, who has control, last refusal).
"""

from __future__ import annotations

import collections
import copy
import logging
import math
import threading
import time
from typing import Any

import numpy as np
import trimesh
import viser
import viser.transforms as vtf

from ucrdf.ik import IKSolver
from view.control import MovePlanner, SliderDriver
from view.guard import GuardError, guarded_viser, page_guard, probe_refuses_foreign_host
from view.scene import SceneModel
from view.source import LiveSource, OfflineSource

log = logging.getLogger("ucr.view")

COLOURS = {
    "ok": (80, 150, 255),
    "clamped": (255, 165, 0),
    "fault": (230, 40, 40),
    "missing": (150, 150, 150),
}
TRAIL_POINTS = 300


def _wxyz(t: np.ndarray) -> np.ndarray:
    return vtf.SO3.from_matrix(t[:3, :3]).wxyz


class ViewApp:
    """The viser server, its scene and GUI, and the thread that keeps them current."""

    def __init__(
        self,
        source: LiveSource | OfflineSource,
        host: str = "127.0.0.1",
        port: int = 8080,
        allow_hosts: tuple[str, ...] = (),
        control: bool = True,
        rate_hz: float = 40.0,
        always_update: bool = False,
    ):
        self.source = source
        self.period = 1.0 / rate_hz
        # with no page connected the scene is not computed (nobody looks): the view then costs
        # only its API subscription; ``always_update`` keeps it current anyway (embedding, tests)
        self.always_update = always_update
        self.idle_skips = 0
        self.live = isinstance(source, LiveSource)
        self.control_enabled = control and self.live
        # set once the port is known (port 0: any free port); until then everything is refused
        guard: list = []
        self.server = guarded_viser(
            lambda: viser.ViserServer(host=host, port=port, verbose=False), guard, log.warning
        )
        actual = self.server.get_port()
        if port and actual != port:  # viser silently moves on to the next free port
            self.server.stop()
            raise OSError(f"port {port} already in use")
        guard.append(page_guard(host, actual, allow_hosts))
        why = probe_refuses_foreign_host(host, actual)
        if why is not None:  # the guard is not in the request path: never serve unguarded
            self.server.stop()
            raise GuardError(f"the page server is not guarded ({why}): not served")
        self.host, self.port = host, actual
        self.server.scene.set_up_direction("+z")  # U(C)RDF frames: z along the base segment
        self.server.scene.add_grid("/grid", width=1.0, height=1.0, cell_size=0.1)
        self.server.initial_camera.position = (1.5, -1.5, 1.2)
        self.server.initial_camera.look_at = (0.0, 0.0, 0.35)
        self.url = f"http://{'127.0.0.1' if host in ('0.0.0.0', '') else host}:{actual}"
        self.lock = threading.RLock()
        self.model: SceneModel | None = None
        self.nodes: dict[str, Any] = {}
        self.sliders: dict[str, tuple[Any, Any]] = {}
        self.trail: collections.deque = collections.deque(maxlen=TRAIL_POINTS)
        self.built: tuple = (-1, ())  # robot_version, present segments
        self.last_seq = -1
        self.pushes = 0
        self.rate = 0.0
        self.latency_ms: collections.deque = collections.deque(maxlen=200)
        self.refusal = ""
        self.facts: dict[str, Any] = {}
        self.visual_problems: list[str] = []  # visuals that could not be drawn (shown)
        self._colours: dict[str, tuple[int, int, int]] = {}  # tube colours on the page
        self._visual_links: set[str] = set()  # links whose frame carries visuals
        self._stop = threading.Event()
        self._gui_static()
        self.driver: SliderDriver | None = None
        self.planner: MovePlanner | None = None
        if self.control_enabled:
            assert isinstance(source, LiveSource)
            self.driver = SliderDriver(
                _CurrentClient(source),  # the source's client of the day (it reconnects)
                self._measured,
                self._rate_max,
                lambda: bool(self.server.get_clients()),
                self._refused,
            ).start()
        self._thread = threading.Thread(target=self._run, name="ucr-view-update", daemon=True)

    # -- lifecycle -------------------------------------------------------------------------------
    def start(self) -> ViewApp:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=3)
        if self.driver is not None:
            self.driver.close()
        self.source.stop()
        self.server.stop()

    # -- helpers used by the control side --------------------------------------------------------
    def _measured(self) -> dict[str, dict[str, float]]:
        with self.source.lock:
            s = self.source.snap
            return {n: dict(v) for n, v in s.state.items() if s.valid.get(n, False)}

    def _rate_max(self, name: str) -> float:
        m = self.model
        return m.limits(name)[1] if m is not None and name in m.robot.bendables else math.inf

    def _refused(self, why: str) -> None:
        self.refusal = why
        log.warning("%s", why)

    # -- GUI -------------------------------------------------------------------------------------
    def _gui_static(self) -> None:
        gui = self.server.gui
        kind = getattr(self.source, "mode", "offline")
        mode = "live: daemon" if self.live else f"{kind}: {self.source.snap.robot_file}"
        self.g_title = gui.add_markdown(f"**ucr view** — {mode}")
        self.g_facts = gui.add_markdown("scene: loading")
        self.g_control = gui.add_markdown("")
        self.g_errors = gui.add_markdown("")
        # wall-clock time (ms) the shown state was sampled by the daemon: the page-side latency
        # figure of benchmarks/bench_view.py reads it
        self.g_stamp = gui.add_markdown("sample: -")
        self.g_frames = gui.add_checkbox("Frames", initial_value=False)
        self.g_tendons = gui.add_checkbox("Tendons", initial_value=True)
        self.g_trail = gui.add_checkbox("Tip trail", initial_value=True)
        self.g_frames.on_update(lambda _e: self._visibility())
        self.g_tendons.on_update(lambda _e: self._visibility())
        self.g_trail.on_update(lambda _e: self._visibility())
        if self.control_enabled:
            self.g_stop = gui.add_button("Stop (hold)", color="red")
            self.g_stop.on_click(lambda _e: self.stop_motion("stop button"))
            self.g_plan = gui.add_markdown("Drag the tip gizmo to plan a move.")
            self.g_execute = gui.add_button("Execute move", disabled=True)
            self.g_execute.on_click(lambda _e: self.execute_move())
            self.g_handback = gui.add_button("Hand back control")
            self.g_handback.on_click(lambda _e: self._hand_back())
        self.slider_folder = gui.add_folder("Segments (κ 1/m, φ deg)")

    def _visibility(self) -> None:
        self.last_seq = -1  # the next update sets the poses of frames shown now
        with self.lock:
            for key, node in self.nodes.items():
                if key.startswith("frame:"):
                    node.show_axes = bool(self.g_frames.value)
                elif key.startswith("tendons:"):
                    node.visible = bool(self.g_tendons.value)
                elif key == "trail":
                    node.visible = bool(self.g_trail.value)

    def _build_sliders(self, model: SceneModel, state: dict) -> None:
        for k, p in self.sliders.values():
            k.remove()
            p.remove()
        self.sliders = {}
        if (self.live and not self.control_enabled) or getattr(self.source, "mode", "") == "replay":
            return  # view only (not on loopback, or a recording playing): no controls
        with self.slider_folder:
            for name in model.bendables:
                kmax, _ = model.limits(name)
                cur = state.get(name, {"kappa": 0.0, "phi": 0.0})
                k = self.server.gui.add_slider(
                    f"{name} κ", 0.0, round(kmax, 3), 0.01, round(min(cur["kappa"], kmax), 2)
                )
                p = self.server.gui.add_slider(
                    f"{name} φ", -180.0, 180.0, 1.0, round(math.degrees(cur["phi"]))
                )
                k.on_update(lambda e, n=name: self._slider(e, n))
                p.on_update(lambda e, n=name: self._slider(e, n))
                self.sliders[name] = (k, p)

    def _slider(self, event: Any, name: str) -> None:
        if event.client is None:
            return
        k, p = self.sliders[name]
        kappa, phi = float(k.value), math.radians(float(p.value))
        if isinstance(self.source, OfflineSource):
            self.source.set_target(name, kappa, phi)
        elif self.driver is not None:
            self.refusal = ""
            self.driver.set_target(name, kappa, phi)

    # -- control ---------------------------------------------------------------------------------
    def stop_motion(self, why: str) -> None:
        """Stop button: no more slider input, cancel running goals; the robot holds."""
        if self.driver is not None:
            self.driver.halt(why)
        client = getattr(self.source, "client", None)
        if client is None:
            return
        with self.source.lock:
            goals = list(self.source.snap.control.get("goals", []))
        for g in goals:
            try:
                client.cancel(g)
            except Exception as exc:  # noqa: BLE001 - shown on the page
                self._refused(f"cancel {g} refused: {exc}")

    def _hand_back(self) -> None:
        try:
            self.source.client.hand_back()
            if self.driver is not None:
                self.driver.owns_control = False
            self.refusal = ""
        except Exception as exc:  # noqa: BLE001 - shown on the page
            self._refused(f"hand back refused: {exc}")

    def _gizmo(self, event: Any) -> None:
        if event.client is None or self.planner is None:
            return
        target = np.asarray(event.target.position, dtype=float)
        res = self.planner.plan(target, self._measured())
        self._show_plan(target, res)

    def _show_plan(self, target: np.ndarray, res: Any) -> None:
        model = self.model
        if model is None:
            return
        ghost = model.frame({n: v for n, v in res.config.items() if isinstance(v, dict)})
        with self.lock, self.server.atomic():
            self.nodes["target"].position = target
            self.nodes["target"].visible = True
            for name, (verts, _f) in ghost.tubes.items():
                node = self.nodes.get(f"ghost:{name}")
                if node is not None:
                    node.vertices = verts
                    node.visible = True
        state = "reachable" if res.success else f"NOT reachable (best error {res.residual:.3f} m)"
        cfg = ", ".join(
            f"{n}: κ {v['kappa']:.2f} φ {math.degrees(v['phi']):.0f}°"
            for n, v in res.config.items()
            if isinstance(v, dict) and "kappa" in v
        )
        tx, ty, tz = target
        self.g_plan.content = (
            f"target ({tx:.3f}, {ty:.3f}, {tz:.3f}) m — {state}<br/>solution: {cfg}"
        )
        self.g_execute.disabled = False

    def execute_move(self) -> None:
        """Send the planned solution as one trajectory (after ending our own takeover)."""
        src = self.source
        if self.planner is None or not isinstance(src, LiveSource):
            return
        with src.lock:
            present = list(src.snap.present)
            manual = list(src.snap.control.get("manual", []))
        try:
            points = self.planner.trajectory(self._measured(), present, self._rate_max)
            if self.driver is not None:
                self.driver.halt("move executed")
                if manual and self.driver.owns_control:
                    src.client.hand_back()
                    self.driver.owns_control = False
            goal = src.client.send_trajectory(points, wait=False)
            self.refusal = ""
            self.g_plan.content = f"move {goal} sent ({points[0]['time_from_start']:.2f} s)"
        except Exception as exc:  # noqa: BLE001 - every refusal is shown on the page
            self._refused(f"move refused: {exc}")

    # -- scene -----------------------------------------------------------------------------------
    def _clear(self) -> None:
        for node in self.nodes.values():
            try:
                node.remove()
            except Exception:  # noqa: BLE001 - already gone on the page
                pass
        self.nodes = {}

    def _build(self, snap: Any, robot: Any) -> None:
        """(Re)create every scene node for the robot and the present segments."""
        scene = self.server.scene
        if self.model is None or self.model.robot is not robot:
            self.model = SceneModel(robot)
            self.visual_problems = []
            self.planner = MovePlanner(_solver(self.model)) if self.control_enabled else None
            self._build_sliders(self.model, snap.state)
            self.trail.clear()
        model = self.model
        self._clear()
        self._colours = {}
        self._visual_links = {v.link for v in model.visuals}
        frame = model.frame(snap.state)
        present = set(snap.present)
        for link, t in frame.links.items():
            self.nodes[f"frame:{link}"] = scene.add_frame(
                f"/robot/links/{link}", show_axes=bool(self.g_frames.value),
                axes_length=0.04, axes_radius=0.002, position=t[:3, 3], wxyz=_wxyz(t),
            )  # fmt: skip
        for i, vis in enumerate(model.visuals):
            self._add_visual(f"/robot/links/{vis.link}/visual{i}", vis)
        for name in model.bendables:
            verts, faces = frame.tubes[name]
            if name in present:
                self.nodes[f"tube:{name}"] = scene.add_mesh_simple(
                    f"/robot/tubes/{name}", verts, faces, color=COLOURS["ok"], side="double"
                )
                if name in frame.tendons:
                    self.nodes[f"tendons:{name}"] = scene.add_line_segments(
                        f"/robot/tendons/{name}", _segments(frame.tendons[name]),
                        (30, 30, 30), thickness=0.004, visible=bool(self.g_tendons.value),
                    )  # fmt: skip
            else:  # missing after a hot-plug: a grey outline where it was, not a tube
                self.nodes[f"missing:{name}"] = scene.add_mesh_simple(
                    f"/robot/missing/{name}", verts, faces, color=COLOURS["missing"],
                    wireframe=True, opacity=0.3,
                )  # fmt: skip
            if self.control_enabled:
                self.nodes[f"ghost:{name}"] = scene.add_mesh_simple(
                    f"/robot/ghost/{name}", verts, faces, color=(120, 220, 120), opacity=0.35,
                    visible=False,
                )  # fmt: skip
        self.nodes["trail"] = scene.add_point_cloud(
            "/robot/trail", np.zeros((1, 3), np.float32), (255, 80, 200), point_size=0.006,
            visible=bool(self.g_trail.value),
        )  # fmt: skip
        if self.control_enabled:
            self.nodes["target"] = scene.add_icosphere(
                "/robot/target", 0.012, (230, 40, 40), visible=False
            )
            gizmo = scene.add_transform_controls(
                "/robot/gizmo", scale=0.3, disable_rotations=True, position=frame.tip
            )
            gizmo.on_update(self._gizmo)
            self.nodes["gizmo"] = gizmo
        self.built = (snap.robot_version, tuple(snap.present))
        self.facts["tubes"] = sorted(n for n in model.bendables if n in present)

    def _add_visual(self, name: str, vis: Any) -> None:
        scene = self.server.scene
        t = vis.origin
        kw = {"position": t[:3, 3], "wxyz": _wxyz(t)}
        if vis.problem:
            self._visual_problem(vis, vis.problem)
            return
        if vis.kind == "box":
            node = scene.add_box(name, vis.color, vis.size, **kw)
        elif vis.kind == "cylinder":
            node = scene.add_cylinder(name, vis.size[0], vis.size[1], vis.color, **kw)
        elif vis.kind == "sphere":
            node = scene.add_icosphere(name, vis.size[0], vis.color, **kw)
        else:
            try:  # STL, OBJ, PLY, glTF... through trimesh; a file is untrusted input
                mesh = trimesh.load(vis.mesh, force="mesh")
                if not len(mesh.faces):
                    raise ValueError("no triangles")
            except Exception as exc:  # noqa: BLE001 - any loader failure: shown, not drawn
                self._visual_problem(vis, f"mesh {vis.mesh}: {type(exc).__name__}: {exc}")
                return
            mesh.apply_scale(vis.scale)
            if vis.color_given:  # the U(C)RDF's material colour, as URDF viewers apply it
                node = scene.add_mesh_simple(
                    name, np.asarray(mesh.vertices, np.float32),
                    np.asarray(mesh.faces, np.uint32), color=vis.color, **kw,
                )  # fmt: skip
            else:  # the file's own colours (or viser's default)
                node = scene.add_mesh_trimesh(name, mesh, **kw)
        self.nodes[f"visual:{name}"] = node

    def _visual_problem(self, vis: Any, why: str) -> None:
        text = f"link {vis.link}: {why} (not drawn)"
        log.warning("%s", text)
        if text not in self.visual_problems:
            self.visual_problems.append(text)

    def _update(self, snap: Any) -> None:
        model = self.model
        assert model is not None
        frame = model.frame(snap.state)
        self.trail.append(frame.tip.astype(np.float32))
        with self.server.atomic():
            # a link frame moves when shown or carrying visuals; hidden bare frames cost nothing
            shown = bool(self.g_frames.value)
            for link, t in frame.links.items():
                node = self.nodes.get(f"frame:{link}")
                if node is not None and (shown or link in self._visual_links):
                    node.position, node.wxyz = t[:3, 3], _wxyz(t)
            for name, (verts, _f) in frame.tubes.items():
                node = self.nodes.get(f"tube:{name}")
                if node is None:
                    continue
                node.vertices = verts
                colour = COLOURS.get(snap.status.get(name, "ok"), COLOURS["ok"])
                if self._colours.get(name) != colour:  # sent only when it changes
                    node.color = colour
                    self._colours[name] = colour
                tn = self.nodes.get(f"tendons:{name}")
                if tn is not None:
                    tn.points = _segments(frame.tendons[name])
            self.nodes["trail"].points = np.asarray(self.trail, dtype=np.float32)
            gizmo = self.nodes.get("gizmo")
            if gizmo is not None and self.planner is not None and self.planner.result is None:
                gizmo.position = frame.tip
        self.facts["tip"] = [round(float(v), 4) for v in frame.tip]

    def _text(self, snap: Any) -> None:
        lat = sorted(self.latency_ms)
        p50 = lat[len(lat) // 2] if lat else float("nan")
        tubes = self.facts.get("tubes", [])
        status = ", ".join(f"{n}: {snap.status.get(n, '?')}" for n in snap.expected)
        self.g_facts.content = (
            f"tubes: {len(tubes)} ({', '.join(tubes) or '-'}) · update {self.rate:.0f} Hz · "
            f"{'daemon' if self.live else 'slider'}→page {p50:.1f} ms (p50, until sent) · "
            f"pushes {self.pushes}<br/>status: {status or '-'}"
        )
        head = "**daemon:**" if self.live else "**check errors:**"
        errors = f"{head}<br/>" + "<br/>".join(snap.errors) if snap.errors else ""
        if self.visual_problems:
            errors += "<br/>**visuals:** " + "<br/>".join(self.visual_problems)
        self.g_errors.content = errors
        if self.live:
            self.g_control.content = _who(snap.control, self.driver) + (
                f"<br/>**refused:** {self.refusal}" if self.refusal else ""
            )

    def _run(self) -> None:
        t_rate, n_rate = time.monotonic(), 0
        t_text = 0.0
        due = time.monotonic()
        while True:
            due += self.period  # a fixed rate (the work's own time not added to the period)
            now = time.monotonic()
            if due < now:
                due = now  # late: no burst of catch-up updates
            if self._stop.wait(due - now):
                return
            if not (self.always_update or self.server.get_clients()):
                self.idle_skips += 1
                continue  # no page: nothing drawn; the first page gets the current scene
            with self.source.lock:
                snap = _copy(self.source.snap)
            robot = self.source.robot
            if self.live and not snap.connected and self.driver is not None:
                if self.driver.targets:
                    self.driver.halt("daemon disconnected")
                self.driver.owns_control = False  # a restarted daemon has no takeover of ours
            try:
                with self.lock:
                    if robot is not None:
                        key = (snap.robot_version, tuple(snap.present))
                        if key != self.built:
                            self._build(snap, robot)
                        if snap.seq != self.last_seq:
                            self.last_seq = snap.seq
                            self._update(snap)
                            self.pushes += 1
                            n_rate += 1
                            if snap.t_daemon or snap.t_received:
                                t0 = snap.t_daemon if self.live else snap.t_received
                                age = time.monotonic() - t0
                                self.latency_ms.append(age * 1e3)
                                self.g_stamp.content = f"sample: {(time.time() - age) * 1e3:.1f}"
                    now = time.monotonic()
                    if now - t_rate >= 1.0:
                        self.rate, t_rate, n_rate = n_rate / (now - t_rate), now, 0
                    if now - t_text >= 0.25:
                        t_text = now
                        self._text(snap)
            except Exception:  # noqa: BLE001 - keep serving; the page shows the last good scene
                log.exception("view update failed")


class _CurrentClient:
    """The live source's API client of the moment (a reconnect replaces it)."""

    def __init__(self, source: LiveSource) -> None:
        self._source = source

    def __getattr__(self, name: str) -> Any:
        return getattr(self._source.client, name)


def _copy(s: Any) -> Any:
    return copy.copy(s) if s is None else type(s)(**{
        k: (dict(v) if isinstance(v, dict) else list(v) if isinstance(v, list) else v)
        for k, v in s.__dict__.items()
    })  # fmt: skip


def _segments(paths: list[np.ndarray]) -> np.ndarray:
    """Polylines -> (N, 2, 3) line segments for viser."""
    segs = [np.stack([p[:-1], p[1:]], axis=1) for p in paths]
    return np.concatenate(segs).astype(np.float32)


def _solver(model: SceneModel):
    return IKSolver(model.kin, model.tip_link)


def _who(control: dict, driver: SliderDriver | None) -> str:
    """One line: who commands the robot now, and why."""
    active, manual, goals = (control.get(k, []) for k in ("active", "manual", "goals"))
    if manual:
        mine = driver is not None and driver.owns_control
        who = "this page (sliders)" if mine else "gamepad/teleop"
        line = f"**control:** {who} via {', '.join(manual)} (manual takeover; trajectories wait)"
    elif goals:
        line = f"**control:** trajectory {', '.join(goals)} ({', '.join(active)})"
    else:
        line = f"**control:** nobody moving; holding ({', '.join(active) or 'no controller'})"
    if driver is not None and driver.stopped_reason:
        line += f"<br/>sliders stopped: {driver.stopped_reason}"
    if control.get("last_event"):
        line += f"<br/>last event: {control['last_event']}"
    return line

"""The page: a viser scene of the robot plus its controls, fed by a source (daemon or file).

One update thread polls the source's snapshot and pushes only what changed (tube vertices, link
poses, tendons, colours, trail) in one atomic viser batch; it rebuilds the scene when the robot file
reloads or the chain's topology changes. Facts a test or a person can read are printed on the page
(tube count and names, update rate, latency, who has control, last refusal).

Controls (sliders, tip gizmo, buttons) are per page client: a live view gives them only to a page
that presents the page token (view/guard.py ``PageToken``: the URL the view prints); any other page
client gets the scene and a line saying why it has no controls. Every motion command from a page
is written to the audit log (``ucr.audit``) with that page client's id and address.
"""

from __future__ import annotations

import collections
import copy
import errno
import html
import logging
import math
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import trimesh
import viser
import viser.transforms as vtf

from host.api.audit import audit_logger
from host.api.client import on_behalf_of, sender_words
from host.listen import ListenError, check_listen, listen_failure
from ucrdf.ik import IKSolver
from view.control import MovePlanner, SliderDriver
from view.guard import (
    GuardError,
    PageGate,
    PageToken,
    guarded_viser,
    page_guard,
    peer_address,
    probe_refuses_foreign_host,
)
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
#: The tip trail gets a point when the tip has moved this far (m) from the last one: the trail
#: shows the path of the last TRAIL_POINTS such steps however long ago, not a time window that
#: collapses onto one point while the robot rests.
TRAIL_STEP_M = 0.002
#: What a page sees when the view's daemon token has the read scope.
READ_TOKEN_NOTE = (
    "**view only: read token** — the daemon API token this view uses has the `read` scope, so no "
    "page has controls (sliders, tip gizmo, buttons). Run `ucr view` with a control token to "
    "move the robot."
)
#: What a page client without the page token sees instead of the controls.
VIEW_ONLY_NOTE = (
    "**view only:** this page was not opened with the view's token, so it has no controls "
    "(sliders, tip gizmo, buttons). Open the URL `ucr view` printed "
    "(`http://…/?token=…`) to move the robot."
)
PLAN_HINT = "Drag the tip gizmo to plan a move."


@dataclass
class _Page:
    """One page client allowed to use the controls, and its own control handles."""

    client: Any
    peer: str
    plan: Any = None
    execute: Any = None
    folder: Any = None
    sliders: dict[str, tuple[Any, Any]] = field(default_factory=dict)
    #: per slider pair: the (κ, φ°) the server last showed on it (``ViewApp._follow_sliders``)
    shown: dict[str, tuple[float, float]] = field(default_factory=dict)
    gizmo: Any = None
    extra: list[Any] = field(default_factory=list)  # its other handles (buttons)
    toggles: dict[str, Any] = field(default_factory=dict)  # display checkboxes (controls only)

    @property
    def id(self) -> int:
        return int(self.client.client_id)


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
        port_option: str = "--port",
    ):
        """``port_option``: the option that sets ``port``, named in a port-in-use error."""
        self.source = source
        self.period = 1.0 / rate_hz
        # with no page connected the scene is not computed (nobody looks): the view then costs
        # only its API subscription; ``always_update`` keeps it current anyway (embedding, tests)
        self.always_update = always_update
        self.idle_skips = 0
        self.live = isinstance(source, LiveSource)
        #: the daemon told the source its token may only read (view/source.py _ask_scope)
        self.read_only = self.live and getattr(source, "scope", "control") == "read"
        self.control_enabled = control and self.live and not self.read_only
        #: the latency figure ages daemon-monotonic stamps on our clock: only for a local daemon
        self.latency_shown = not self.live or bool(getattr(source, "local", True))
        # pages get sliders: offline (FK only) and live with controls; never a replay or a
        # view-only live view
        self.has_controls = self.control_enabled or not (
            self.live or getattr(source, "mode", "") == "replay"
        )
        # the robot moves only for a page client presenting this (the URL printed has it)
        self.page_token = PageToken() if self.control_enabled else None
        # the guard is set once the port is known (port 0: any free port); until then everything
        # is refused
        self.gate = PageGate(self.page_token)
        check_listen(host, port, port_option)  # else viser waits forever
        self.server = guarded_viser(
            lambda: viser.ViserServer(host=host, port=port, verbose=False), self.gate, log.warning
        )
        actual = self.server.get_port()
        if port and actual != port:  # viser silently moves on to the next free port
            self.server.stop()
            taken = OSError(errno.EADDRINUSE, "in use")
            raise ListenError(errno.EADDRINUSE, listen_failure(host, port, taken, port_option))
        if self.page_token is not None and not isinstance(
            getattr(self.server._websock_server, "_live_connections", None), dict
        ):  # which page client presented the token is read there: fail closed
            self.server.stop()
            raise GuardError(
                "viser has no _live_connections (its internals changed; view/app.py supports "
                "the pinned viser): the page's credential cannot be checked, not served"
            )
        self.gate.arm(page_guard(host, actual, allow_hosts))
        why = probe_refuses_foreign_host(host, actual)
        if why is not None:  # the guard is not in the request path: never serve unguarded
            self.server.stop()
            raise GuardError(f"the page server is not guarded ({why}): not served")
        self.host, self.port = host, actual
        # viser lets any page client ask for a public share tunnel (share.viser.studio) to this
        # page: never (a page that can move hardware is not published by a visitor)
        self.server.request_share_url = self._no_share_url  # type: ignore[method-assign]
        self.server.gui.configure_theme(show_share_button=False)
        self.server.scene.set_up_direction("+z")  # U(C)RDF frames: z along the base segment
        self.server.scene.add_grid("/grid", width=1.0, height=1.0, cell_size=0.1)
        self.server.initial_camera.position = (1.5, -1.5, 1.2)
        self.server.initial_camera.look_at = (0.0, 0.0, 0.35)
        shown = "127.0.0.1" if host in ("0.0.0.0", "") else "[::1]" if host == "::" else host
        if ":" in shown and not shown.startswith("["):
            shown = f"[{shown}]"
        #: the page without the token: view only when the view has controls
        self.page_url = f"http://{shown}:{actual}/"
        #: the URL to open: with the page token when the page can move the robot
        self.url = self.page_url + (
            f"?{PageToken.QUERY}={self.page_token.secret}" if self.page_token else ""
        )
        self.pages: dict[int, _Page] = {}  # page clients with controls, by viser client id
        self.viewers: dict[int, str] = {}  # page clients without the token -> their address
        self.plan_text = PLAN_HINT
        self.lock = threading.RLock()
        self.model: SceneModel | None = None
        self.nodes: dict[str, Any] = {}
        self.trail: collections.deque = collections.deque(maxlen=TRAIL_POINTS)
        self.built: tuple = (-1, ())  # robot_version, present segments
        self.last_seq = -1
        self.pushes = 0
        self.rate = 0.0
        self.latency_ms: collections.deque = collections.deque(maxlen=200)
        self.last_sample = 0  # snap.sample_seq of the last sample counted in latency_ms
        #: who sent the manual cFFC's input: "page" (this view's sliders), "other" (another API
        #: client: gamepad/teleop), "" (not known: the takeover predates the view)
        self.manual_owner = ""
        #: that other client as the daemon names it (program, for whom, address), "" unknown
        self.manual_sender = ""
        self._ffc_seen = 0.0  # the last cFFC input observation used (its time asked)
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
                lambda: bool(self.pages),  # the deadman counts pages with controls only
                self._refused,
                kappa_max=self._kappa_max,
                clamped=self._clamped,
                ffc_params=lambda: source.ffc_params,
                pages=self._page_ids,  # a page's slider targets end when it closes
            ).start()
        self.server.on_client_connect(self._client_connected)
        self.server.on_client_disconnect(self._client_gone)
        self._thread = threading.Thread(target=self._run, name="ucr-view-update", daemon=True)

    # -- lifecycle -------------------------------------------------------------------------------
    def _no_share_url(self, verbose: bool = True) -> None:
        log.warning("refused a page's request for a public share URL (viser's share tunnel)")

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

    def _page_ids(self) -> list[int]:
        """The ids of the pages with controls connected now."""
        with self.lock:
            return list(self.pages)

    def _clamped(self, name: str) -> bool:
        """Whether the segment reports clamping its setpoints (its status colour: clamped)."""
        with self.source.lock:
            return self.source.snap.status.get(name) == "clamped"

    def _kappa_max(self, name: str) -> float:
        m = self.model
        return m.limits(name)[0] if m is not None and name in m.robot.bendables else math.inf

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
        self.g_title = gui.add_markdown(f"**ucr view** — {md(mode)}")
        self.g_facts = gui.add_markdown("scene: loading")
        self.g_control = gui.add_markdown("")
        self.g_errors = gui.add_markdown("")
        # wall-clock time (ms) the shown state was sampled by the daemon: the page-side latency
        # figure of benchmarks/bench_view.py reads it
        self.g_stamp = gui.add_markdown("sample: -")
        # display toggles (Frames, Tendons, Tip trail): the scene is shared by every page, so
        # only a page with controls gets them (_page_controls); a viewer cannot change them
        self.show = {"frames": False, "tendons": True, "trail": True}
        if self.read_only:
            gui.add_markdown(READ_TOKEN_NOTE)
        elif self.live and not self.control_enabled and kind != "replay":
            gui.add_markdown(
                "**view only:** served off loopback, so no page has controls; to control "
                "remotely, tunnel the loopback page (docs/view.md)."
            )

    # -- page clients ----------------------------------------------------------------------------
    def _connection(self, client: Any) -> Any:
        """The WebSocket (its request and peer) of a viser client; None if unknown."""
        conns = getattr(self.server._websock_server, "_live_connections", None)
        return conns.get(client.client_id) if isinstance(conns, dict) else None

    def _client_connected(self, client: Any) -> None:
        conn = self._connection(client)
        peer = peer_address(conn) if conn is not None else "?"
        if not self.has_controls:
            return
        mismatch = getattr(self.source.snap, "mismatch", "")
        if mismatch:  # FILE is not the daemon's robot: no page moves it through this view
            with self.lock:
                self.viewers[client.client_id] = peer
            try:
                client.gui.add_markdown(f"**controls refused:** {md(mismatch)}")
            except Exception:  # noqa: BLE001, S110 - the page went away meanwhile
                pass
            _audit(client.client_id, peer, "connect", "robot file mismatch: view only")
            return
        if self.page_token is not None:
            request = getattr(conn, "request", None)
            if request is None or not self.gate.has_token(request):
                with self.lock:
                    self.viewers[client.client_id] = peer
                try:
                    client.gui.add_markdown(VIEW_ONLY_NOTE)
                except Exception:  # noqa: BLE001, S110 - the page went away meanwhile
                    pass
                _audit(client.client_id, peer, "connect", "without the page token: view only")
                return
            _audit(client.client_id, peer, "connect", "with the page token: controls")
        page = _Page(client, peer)
        with self.lock:
            self.pages[page.id] = page
            if self.model is not None:
                with self.source.lock:
                    state = {n: dict(v) for n, v in self.source.snap.state.items()}
                self._page_controls(page, state, sliders=True, gizmo_at=self.model.frame(state).tip)

    def _client_gone(self, client: Any) -> None:
        with self.lock:
            page = self.pages.pop(client.client_id, None)
            peer = self.viewers.pop(client.client_id, None)
        if page is not None and self.page_token is not None:
            _audit(page.id, page.peer, "disconnect", "(controls)")
        elif peer is not None:
            _audit(client.client_id, peer, "disconnect", "(view only)")

    def _page_of(self, event: Any) -> _Page | None:
        """The page with controls an event came from (None: ignore the event)."""
        client = getattr(event, "client", None)
        return None if client is None else self.pages.get(client.client_id)

    def _page_controls(
        self, page: _Page, state: dict, sliders: bool, gizmo_at: np.ndarray | None
    ) -> None:
        """Give ``page`` its controls (buttons once; sliders when ``sliders``; the tip gizmo
        again at ``gizmo_at``). Under self.lock."""
        gui, model = page.client.gui, self.model
        if model is None:
            return
        try:
            if self.control_enabled and page.plan is None:
                stop = gui.add_button("Stop (hold)", color="red")
                stop.on_click(lambda e: self._stop_clicked(e))
                page.plan = gui.add_markdown(self.plan_text)
                page.execute = gui.add_button(
                    "Execute move", disabled=self.planner is None or self.planner.result is None
                )
                page.execute.on_click(lambda e: self._execute_clicked(e))
                handback = gui.add_button("Hand back control")
                handback.on_click(lambda e: self._hand_back_clicked(e))
                page.extra = [stop, handback]
            if not page.toggles:
                for key, label in (("frames", "Frames"), ("tendons", "Tendons"),
                                   ("trail", "Tip trail")):  # fmt: skip
                    box = gui.add_checkbox(label, initial_value=self.show[key])
                    box.on_update(lambda e, k=key: self._toggle(e, k))
                    page.toggles[key] = box
            if page.folder is None:
                page.folder = gui.add_folder("Segments (κ 1/m, φ deg)")
            if sliders or not page.sliders:
                self._page_sliders(page, model, state)
            if self.control_enabled and gizmo_at is not None:
                if page.gizmo is not None:
                    page.gizmo.remove()
                page.gizmo = page.client.scene.add_transform_controls(
                    "/robot/gizmo", scale=0.3, disable_rotations=True, position=gizmo_at
                )
                page.gizmo.on_update(self._gizmo)
        except Exception:  # noqa: BLE001 - a page that went away while its controls were made
            log.debug("controls for page client %d not made", page.id, exc_info=True)

    def _toggle(self, event: Any, key: str) -> None:
        """A display checkbox of a page with controls (the scene is shared: every page sees
        it; the other controlling pages' boxes follow). A page without controls has none."""
        page = self._page_of(event)
        if page is None or key not in page.toggles:
            return
        value = bool(page.toggles[key].value)
        with self.lock:
            self.show[key] = value
            for other in list(self.pages.values()):
                box = other.toggles.get(key)
                if other is not page and box is not None and bool(box.value) != value:
                    try:
                        box.value = value
                    except Exception:  # noqa: BLE001, S110 - a page that went away
                        pass
        self._visibility()

    def _visibility(self) -> None:
        self.last_seq = -1  # the next update sets the poses of frames shown now
        with self.lock:
            for key, node in self.nodes.items():
                if key.startswith("frame:"):
                    node.show_axes = self.show["frames"]
                elif key.startswith("tendons:"):
                    node.visible = self.show["tendons"]
                elif key == "trail":
                    node.visible = self.show["trail"]

    def _page_sliders(self, page: _Page, model: SceneModel, state: dict) -> None:
        for k, p in page.sliders.values():
            k.remove()
            p.remove()
        page.sliders = {}
        gui = page.client.gui
        with page.folder:
            for name in model.bendables:
                kmax, _ = model.limits(name)
                cur = state.get(name, {"kappa": 0.0, "phi": 0.0})
                k0, p0 = round(min(cur["kappa"], kmax), 2), round(math.degrees(cur["phi"]))
                k = gui.add_slider(f"{name} κ", 0.0, round(kmax, 3), 0.01, k0)
                p = gui.add_slider(f"{name} φ", -180.0, 180.0, 1.0, p0)
                page.shown[name] = (float(k0), float(p0))
                k.on_update(lambda e, n=name: self._slider(e, n))
                p.on_update(lambda e, n=name: self._slider(e, n))
                page.sliders[name] = (k, p)

    def _follow_sliders(self, snap: Any) -> None:
        """Live: each page's sliders show the measured κ, φ of their segment, except the one
        whose target that page set and the slider drive still holds: so after a trajectory, a
        gamepad or another page moved the robot, and while another page drives, they show
        where it is, and the slider touched next starts from there. A value set here is the
        server's, not a page's: ``_slider`` ignores it (no motion). Under self.lock."""
        driver, model = self.driver, self.model
        if driver is None or model is None:
            return
        with driver.lock:
            driven = dict(driver.target_page) if driver.targets else {}
        for page in list(self.pages.values()):
            for name, (k, p) in page.sliders.items():
                if name in driven and driven[name] in (page.id, None):
                    continue  # the page's own target stands (or one no page set)
                st = snap.state.get(name)
                if st is None or not snap.valid.get(name, False):
                    continue
                kmax, _ = model.limits(name)
                kappa = round(min(max(st["kappa"], 0.0), kmax), 2)
                phi = round(math.degrees(st["phi"]))
                try:
                    now_k, now_p = float(k.value), float(p.value)
                    if (now_k, now_p) != page.shown.get(name):
                        # the page moved it since: its callback sets a target (then this waits
                        # for the drive to end), or refused it; never overwritten under a hand
                        page.shown[name] = (now_k, now_p)
                        continue
                    if abs(now_k - kappa) >= 0.01:
                        k.value = now_k = kappa
                    if kappa >= 0.01 and abs(now_p - phi) >= 1.0:
                        p.value = now_p = (
                            phi  # (straight: φ means nothing, the slider keeps its own)
                        )
                    page.shown[name] = (float(now_k), float(now_p))
                except Exception:  # noqa: BLE001, S110 - a page that went away meanwhile
                    pass

    def _slider(self, event: Any, name: str) -> None:
        page = self._page_of(event)
        if page is None or name not in page.sliders:
            return
        k, p = page.sliders[name]
        kappa, phi = float(k.value), math.radians(float(p.value))
        if isinstance(self.source, OfflineSource):
            self.source.set_target(name, kappa, phi)
        elif self._mismatch_refused("slider"):
            return
        elif self.driver is not None:
            self.refusal = ""
            _audit(page.id, page.peer, "slider",
                   f"{name} κ {kappa:.2f} 1/m φ {math.degrees(phi):.0f}°")  # fmt: skip
            self.driver.set_target(name, kappa, phi, _label(page), page=page.id)

    def _mismatch_refused(self, what: str) -> bool:
        """Refuse ``what`` while the FILE given is not the daemon's robot (shown, logged)."""
        mismatch = getattr(self.source.snap, "mismatch", "")
        if mismatch:
            self._refused(f"{what} refused: {mismatch}")
        return bool(mismatch)

    def _stop_clicked(self, event: Any) -> None:
        page = self._page_of(event)
        if page is not None:
            _audit(page.id, page.peer, "stop", "stop button")
            self.stop_motion("stop button", page)

    def _execute_clicked(self, event: Any) -> None:
        page = self._page_of(event)
        if page is not None:
            self.execute_move(page)

    def _hand_back_clicked(self, event: Any) -> None:
        page = self._page_of(event)
        if page is not None:
            _audit(page.id, page.peer, "hand_back", "hand back control")
            self._hand_back(page)

    def _set_plan(self, text: str, executable: bool | None = None) -> None:
        """The plan line (and the Execute button's state) on every page with controls."""
        self.plan_text = text
        for page in list(self.pages.values()):
            try:
                if page.plan is not None:
                    page.plan.content = text
                if executable is not None and page.execute is not None:
                    page.execute.disabled = not executable
            except Exception:  # noqa: BLE001, S110 - a page that went away meanwhile
                pass

    # -- control ---------------------------------------------------------------------------------
    def stop_motion(self, why: str, page: _Page | None = None) -> None:
        """Stop button: no more slider input, cancel running goals; the robot holds. ``page``:
        the page that asked (the daemon's audit lines say it was for that page)."""
        label = None if page is None else _label(page)
        if self.driver is not None:
            self.driver.halt(why, label=label)
        client = getattr(self.source, "client", None)
        if client is None:
            return
        with self.source.lock:
            goals = list(self.source.snap.control.get("goals", []))
        for g in goals:
            try:
                with on_behalf_of(label):
                    client.cancel(g)
            except Exception as exc:  # noqa: BLE001 - shown on the page
                self._refused(f"cancel {g} refused: {exc}")

    def _hand_back(self, page: _Page | None = None) -> None:
        try:
            with on_behalf_of(None if page is None else _label(page)):
                self.source.client.hand_back()
            if self.driver is not None:
                self.driver.owns_control = False
            self.refusal = ""
        except Exception as exc:  # noqa: BLE001 - shown on the page
            self._refused(f"hand back refused: {exc}")

    def _gizmo(self, event: Any) -> None:
        if self._page_of(event) is None or self.planner is None:
            return
        if self._mismatch_refused("IK plan"):
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
        state = (
            "reachable"
            if res.success
            else f"NOT reachable (best error {res.residual:.3f} m): Execute move disabled, drag "
            "the target within reach"
        )
        cfg = ", ".join(
            f"{md(n)}: κ {v['kappa']:.2f} φ {math.degrees(v['phi']):.0f}°"
            for n, v in res.config.items()
            if isinstance(v, dict) and "kappa" in v
        )
        tx, ty, tz = target
        self._set_plan(
            f"target ({tx:.3f}, {ty:.3f}, {tz:.3f}) m — {state}<br/>solution: {cfg}",
            bool(res.success),
        )

    def execute_move(self, page: _Page | None = None) -> None:
        """Send the planned solution as one trajectory (after ending our own takeover);
        ``page``: the page client that asked (audited)."""
        src = self.source
        if self.planner is None or not isinstance(src, LiveSource):
            return
        if self._mismatch_refused("move"):
            return
        with self.planner.lock:
            planned = self.planner.result
        if planned is not None and not planned.success:  # the button is disabled; a raw client
            self._refused(
                f"move refused: the target is NOT reachable (best error {planned.residual:.3f} m)"
            )
            return
        with src.lock:
            present = list(src.snap.present)
            manual = list(src.snap.control.get("manual", []))
        label = None if page is None else _label(page)
        try:
            points = self.planner.trajectory(self._measured(), present, self._rate_max)
            if self.driver is not None:
                self.driver.halt("move executed", label=label)
                if manual and self.driver.owns_control:
                    with on_behalf_of(label):
                        src.client.hand_back()
                    self.driver.owns_control = False
            target = self.planner.executed[0] if self.planner.executed else None
            where = "" if target is None else " to ({:.3f}, {:.3f}, {:.3f}) m".format(*target)
            segs = ", ".join(
                f"{n} κ {v['kappa']:.2f} φ {math.degrees(v['phi']):.0f}°"
                for n, v in points[0]["segments"].items()
            )
            if page is not None:
                _audit(page.id, page.peer, "move", f"tip{where}: {segs}")
            with on_behalf_of(label):
                goal = src.client.send_trajectory(points, wait=False)
            self.refusal = ""
            self._set_plan(f"move {md(goal)} sent ({points[0]['time_from_start']:.2f} s)")
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
        new_model = self.model is None or self.model.robot is not robot
        if new_model:
            self.model = SceneModel(robot)
            self.visual_problems = []
            self.planner = MovePlanner(_solver(self.model)) if self.control_enabled else None
            self.trail.clear()
        model = self.model
        self._clear()
        self._colours = {}
        self._visual_links = {v.link for v in model.visuals}
        frame = model.frame(snap.state)
        present = set(snap.present)
        for link, t in frame.links.items():
            self.nodes[f"frame:{link}"] = scene.add_frame(
                f"/robot/links/{link}", show_axes=self.show["frames"],
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
                        (30, 30, 30), thickness=0.004, visible=self.show["tendons"],
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
            visible=self.show["trail"],
        )  # fmt: skip
        if self.control_enabled:
            self.nodes["target"] = scene.add_icosphere(
                "/robot/target", 0.012, (230, 40, 40), visible=False
            )
        for page in list(self.pages.values()):  # each page's sliders and tip gizmo
            self._page_controls(page, snap.state, sliders=new_model, gizmo_at=frame.tip)
        if new_model:
            self._set_plan(PLAN_HINT, False)
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
        tip = frame.tip.astype(np.float32)
        if not self.trail or float(np.linalg.norm(tip - self.trail[-1])) > TRAIL_STEP_M:
            self.trail.append(tip)  # a point per TRAIL_STEP_M moved: at rest it keeps its path
        with self.server.atomic():
            # a link frame moves when shown or carrying visuals; hidden bare frames cost nothing
            shown = self.show["frames"]
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
            if self.planner is not None and self.planner.result is None:
                connected = self.server.get_clients()  # not a page whose close is in flight
                for page in list(self.pages.values()):
                    if page.gizmo is not None and page.id in connected:
                        page.gizmo.position = frame.tip
        self.facts["tip"] = [round(float(v), 4) for v in frame.tip]

    def _text(self, snap: Any) -> None:
        lat = sorted(self.latency_ms)
        p50 = lat[len(lat) // 2] if lat else float("nan")
        tubes = self.facts.get("tubes", [])
        status = ", ".join(f"{md(n)}: {md(snap.status.get(n, '?'))}" for n in snap.expected)
        latency = (
            f"{'daemon' if self.live else 'slider'}→page {p50:.1f} ms (p50, until sent)"
            if self.latency_shown
            else "daemon→page latency not shown (daemon on another machine: its clock is not ours)"
        )
        self.g_facts.content = (
            f"tubes: {len(tubes)} ({md(', '.join(tubes)) or '-'}) · update {self.rate:.0f} Hz · "
            f"{latency} · "
            f"pushes {self.pushes}<br/>status: {status or '-'}"
        )
        head = "**daemon:**" if self.live else "**check errors:**"
        errors = f"{head}<br/>" + "<br/>".join(md(e) for e in snap.errors) if snap.errors else ""
        if getattr(snap, "mismatch", ""):
            errors = f"**robot file mismatch:** {md(snap.mismatch)}" + (
                f"<br/>{errors}" if errors else ""
            )
        if self.visual_problems:
            errors += "<br/>**visuals:** " + "<br/>".join(md(v) for v in self.visual_problems)
        self.g_errors.content = errors
        if self.live:
            self.g_control.content = _who(
                snap.control, self.driver, self.manual_owner, self.manual_sender,
                self._goal_by(snap.control),
            ) + (f"<br/>**refused:** {md(self.refusal)}" if self.refusal else "")  # fmt: skip

    def _goal_by(self, control: dict) -> str:
        """Who sent the running goal, in words ("" not known): this view (its Execute move:
        one of its own API connections) or another client as the daemon names it."""
        known = control.get("goal_from")
        sender = known[1] if isinstance(known, tuple) and len(known) == 2 else None
        if not isinstance(sender, dict):
            return ""
        if self._sent_by_us(sender):
            return "this view's page (Execute move)"
        return sender_words(sender)

    def _sent_by_us(self, sender: Any) -> bool | None:
        """Whether a command the daemon names (a cFFC's ``input_from``, a goal's ``from``) came
        from one of this view's own API connections (their ``session`` peers); None when that
        cannot be told (no sender or address said, or no peer of ours known)."""
        own_peers = getattr(self.source, "own_peers", ())
        if not (isinstance(sender, dict) and sender.get("peer") and own_peers):
            return None
        return sender["peer"] in own_peers

    def _whose_input(self, control: dict) -> None:
        """Who holds the manual control now (``manual_owner``), from the daemon's status (a cFFC
        holds a manual takeover) and its latest input (``ffc_input``): who sent it, as the daemon
        names it (``input_from``: one of this view's API connections, or another client's), or,
        from a daemon that does not say, when it was set (one of this view's calls then, or not).
        Another client's input while the sliders stream overrides the page: the sliders stop
        (no zero input sent over the other's) and the clash is shown under refused."""
        driver = self.driver
        assert driver is not None
        if not control.get("manual"):
            self.manual_owner = self.manual_sender = ""
            driver.owns_control = False
            return
        seen = control.get("ffc_input")
        if not seen or seen[2] <= self._ffc_seen:
            return  # nothing new (no input now: whoever sent the last one keeps control)
        self._ffc_seen = seen[2]
        sender = seen[3] if len(seen) > 3 else None
        ours = self._sent_by_us(sender)
        if ours is None:  # the daemon does not say who: by the times of our own calls
            ours = driver.sent_at(seen[0], seen[1])
        if ours:
            self.manual_owner, self.manual_sender = "page", ""
            driver.owns_control = True
            return
        self.manual_owner = "other"
        self.manual_sender = sender_words(sender)
        driver.owns_control = False
        driver.forget_setpoints()  # the other client moved the cFFC's setpoint
        if driver.targets:
            who = self.manual_sender or "another client (gamepad/teleop)"
            why = (
                f"page slider input overridden: {who} is streaming ffc.input to the same "
                "cFFC; the sliders stopped (hand back or wait, then move a slider again)"
            )
            driver.halt(why, send_zero=False)
            self._refused(why)

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
            pages = bool(self.server.get_clients())
            demand = getattr(self.source, "set_demand", None)  # a live source: its stream rate
            if demand is not None:
                demand(pages or self.always_update)
            if not (self.always_update or pages):
                self.idle_skips += 1
                continue  # no page: nothing drawn; the first page gets the current scene
            with self.source.lock:
                snap = _copy(self.source.snap)
            robot = self.source.robot
            if self.live and not snap.connected and self.driver is not None:
                if self.driver.targets:
                    self.driver.halt("daemon disconnected")
                self.driver.owns_control = False  # a restarted daemon has no takeover of ours
                self.driver.forget_setpoints()
            if self.driver is not None and getattr(snap, "mismatch", "") and self.driver.targets:
                self.driver.halt("the robot file does not match the daemon's robot")
            if self.driver is not None:
                self._whose_input(snap.control)
                if (
                    self.driver.stopped_reason
                    and not self.driver.targets
                    and (snap.control.get("goals") or self.manual_owner == "other")
                ):  # another source took control since: the old stop reason is history
                    self.driver.stopped_reason = ""
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
                            t0 = snap.t_daemon if self.live else snap.t_received
                            if snap.sample_seq != self.last_sample and t0 and self.latency_shown:
                                # a new sample (a daemon message's stamp, an offline slider
                                # move): its age; a file reload or a reconnect is none
                                self.last_sample = snap.sample_seq
                                age = time.monotonic() - t0
                                self.latency_ms.append(age * 1e3)
                                self.g_stamp.content = f"sample: {(time.time() - age) * 1e3:.1f}"
                    now = time.monotonic()
                    if now - t_rate >= 1.0:
                        self.rate, t_rate, n_rate = n_rate / (now - t_rate), now, 0
                    if now - t_text >= 0.25:
                        t_text = now
                        self._text(snap)
                        self._follow_sliders(snap)
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


_MD_SPECIAL = str.maketrans({c: "\\" + c for c in "\\`*_[]~"})


def md(text: Any) -> str:
    """``text`` (a file's content, the daemon's or an event's words: untrusted) as literal text
    in the page's markdown: markdown punctuation backslash-escaped, then ``<``, ``>``, ``&`` as
    HTML entities, so ``<tendon>`` reads as such and no tag or link is made from it."""
    return html.escape(str(text).translate(_MD_SPECIAL), quote=False)


def _segments(paths: list[np.ndarray]) -> np.ndarray:
    """Polylines -> (N, 2, 3) line segments for viser."""
    segs = [np.stack([p[:-1], p[1:]], axis=1) for p in paths]
    return np.concatenate(segs).astype(np.float32)


def _label(page: _Page) -> str:
    """Whom a page's requests are for, in the daemon's audit lines (``for=…``): this view's page
    id and the page's address, as the view's own audit lines name it."""
    return f"view page={page.id} peer={page.peer}"


def _audit(page: int, peer: str, op: str, summary: str) -> None:
    """One audit line (``ucr.audit``, as the daemon's) for what a page client did."""
    audit_logger().info("view page=%s peer=%s op=%s %s", page, peer, op, summary[:500])


def _solver(model: SceneModel):
    return IKSolver(model.kin, model.tip_link)


def _who(
    control: dict,
    driver: SliderDriver | None,
    owner: str = "",
    sender: str = "",
    goal_by: str = "",
) -> str:
    """One line: who commands the robot now, and why (``owner``: who sent the manual cFFC's
    latest input, see ViewApp._whose_input; ``sender``: that other client, named; ``goal_by``:
    who sent the running goal, see ViewApp._goal_by)."""
    active, manual, goals = (control.get(k, []) for k in ("active", "manual", "goals"))
    if manual:
        if not owner and driver is not None and driver.owns_control:
            owner = "page"  # our input just took over (the next status poll confirms it)
        who = {
            "page": "this view's page sliders",
            "other": md(sender) or "another API client (gamepad/teleop)",  # sender: untrusted
        }.get(owner, "a manual source (gamepad/teleop)")
        line = (
            f"**control:** {who} via {md(', '.join(manual))} (manual takeover; trajectories wait)"
        )
    elif goals:
        line = f"**control:** trajectory {md(', '.join(goals))} ({md(', '.join(active))})"
        if goal_by:
            line += f" from {md(goal_by)}"  # goal_by: a client's own words (untrusted)
    else:
        line = f"**control:** nobody moving; holding ({md(', '.join(active)) or 'no controller'})"
    if driver is not None and driver.stopped_reason:
        line += f"<br/>sliders stopped: {md(driver.stopped_reason)}"
    if control.get("last_event"):
        line += f"<br/>last event: {md(control['last_event'])}"
    return line

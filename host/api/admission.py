"""Who may hold a connection to a server of the project: caps counted from the TCP accept.

Every listener that authenticates in its opening handshake (the daemon's API, the Foxglove door)
admits its connections here before any work: :class:`Admission` caps connections still in their
handshake (*pending*, with eviction of the oldest that got least far) apart from accepted ones and
per remote address; :func:`admitted_connections` makes a websockets ``ServerConnection`` class that
is admitted at its TCP accept (with TLS, before its TLS handshake). The browser guard (Origin,
Host, path) that each handshake passes next is :mod:`host.api.guard`; docs/api.md "Limits"
describes both.
"""

from __future__ import annotations

import array
import asyncio
import fcntl
import logging
import ssl
import sys
import termios
from collections import OrderedDict
from collections.abc import Callable
from typing import Any, ClassVar

from host.api.guard import is_loopback


class TcpCounts:
    """TCP connections open per peer address and in all, for the caps a server applies the
    moment a connection is made, before any work on it (the API server, the Foxglove door).
    Loopback peers count only in the total: every local client shares 127.0.0.1."""

    def __init__(self) -> None:
        self.total = 0
        self.by_ip: dict[str, int] = {}

    def admit(self, ip: str, max_total: int, max_per_peer: int) -> bool:
        """Count a new connection from ``ip``; False (nothing counted) above either cap."""
        n = self.by_ip.get(ip, 0)
        if self.total >= max_total or (n >= max_per_peer and not is_loopback(ip)):
            return False
        self.total += 1
        self.by_ip[ip] = n + 1
        return True

    def release(self, ip: str) -> None:
        """A connection :meth:`admit` counted has gone."""
        self.total -= 1
        left = self.by_ip.get(ip, 1) - 1
        if left > 0:
            self.by_ip[ip] = left
        else:
            self.by_ip.pop(ip, None)


#: silent pending connections whose socket :meth:`Admission.arrive` asks about (``unread``) per
#: arrival, at most: one that has bytes waiting moves on to :data:`TALKING`, so each is asked once
PEEK_LIMIT = 8

#: how far a pending connection got with its opening handshake (see :class:`Admission`)
#: (in the order they are evicted in; :data:`REFUSING`: its token was found wrong, it only waits
#: out the back-off's hold before its refusal)
REFUSING, SILENT, TALKING, AUTHORIZING, VERIFIED = 0, 1, 2, 3, 4


class Admission:
    """Who may hold a connection to a server that authenticates in its opening handshake.

    A connection is *pending* from its TCP accept (with TLS, its TLS handshake included: see
    :func:`admitted_connections`) until its handshake is accepted (the guard and the token passed:
    :meth:`promote`), then *open*. The two are capped apart:

    - pending: ``max_pending``. A new connection is never refused for it: when it is full, the
      oldest pending connection that got least far is evicted (closed) instead: first those
      whose token was found wrong and that only wait out the token back-off's hold before their
      refusal (:data:`REFUSING`), then those that sent nothing yet, then those that sent part of
      a request, then those whose request is being authorized, last those whose token was found
      valid and that wait out the hold (:data:`VERIFIED`): a flood of wrong tokens, each held,
      evicts only itself. A real client sends its request at once and finishes in
      milliseconds; an idle or trickling socket never does, so a flood of them only evicts
      itself. "Sent nothing" is what the server has read: a loaded server accepts a burst of
      connections before it reads any of them, so a client whose request waits unread in its
      socket looked silent and was evicted first. Before a silent one is evicted, its socket is
      asked (``unread``, up to :data:`PEEK_LIMIT` per arrival); one with bytes waiting counts
      as talking.
    - open: ``max_open`` in all; the last ``reserve`` of them only for control
      (``promote(conn, control=True)``). Connections that have not authenticated never count
      here, so they cannot use up the slots kept for control.
    - per remote address (pending and open together): ``max_per_peer``; loopback peers count
      only in the totals, every local client sharing 127.0.0.1.
    """

    def __init__(self, max_open: int, max_pending: int, max_per_peer: int, reserve: int = 0):
        self.max_open, self.max_pending = max_open, max(1, max_pending)
        self.max_per_peer, self.reserve = max_per_peer, reserve
        self.tcp = TcpCounts()
        self._pending: tuple[OrderedDict, ...] = tuple(OrderedDict() for _ in range(VERIFIED + 1))
        self._stage: dict[object, int] = {}
        self.opened: set[object] = set()

    @property
    def pending(self) -> int:
        return len(self._stage)

    def arrive(
        self, conn: object, ip: str, unread: Callable[[object], bool] | None = None
    ) -> tuple[bool, object | None]:
        """A TCP connection was accepted: (admitted, the pending connection to evict or None).
        Refused (nothing counted) only above the per-peer cap. ``unread(c)``: whether a pending
        connection has received bytes the server has not read yet (its socket asked)."""
        if not self.tcp.admit(ip, sys.maxsize, self.max_per_peer):
            return False, None
        victim = None
        if len(self._stage) >= self.max_pending:
            victim = self._victim(unread)
        self._stage[conn] = SILENT
        self._pending[SILENT][conn] = None
        return True, victim

    def _victim(self, unread: Callable[[object], bool] | None) -> object | None:
        """Take the oldest pending connection that got least far out of the count (a silent one
        whose request waits unread moves on to :data:`TALKING` instead)."""
        asked = 0
        for number, stage in enumerate(self._pending):
            while stage:
                oldest = next(iter(stage))
                if number == SILENT and unread is not None and asked < PEEK_LIMIT:
                    asked += 1
                    if unread(oldest):
                        self.advance(oldest, TALKING)
                        continue
                del stage[oldest]
                del self._stage[oldest]
                return oldest
        return None

    def advance(self, conn: object, stage: int) -> None:
        """A pending connection got further (:data:`TALKING`, :data:`AUTHORIZING`), or its token
        was checked (:data:`VERIFIED`, :data:`REFUSING`: set whatever the stage was)."""
        now = self._stage.get(conn)
        if now is not None and (stage > now or stage in (REFUSING, VERIFIED)) and stage != now:
            del self._pending[now][conn]
            self._pending[stage][conn] = None
            self._stage[conn] = stage

    def is_pending(self, conn: object) -> bool:
        return conn in self._stage

    def promote(self, conn: object, control: bool) -> bool:
        """Its handshake is accepted: count it open if there is room (for ``control``, up to
        ``max_open``; else up to ``max_open - reserve``). False: no room, or it is no longer
        pending (evicted or gone meanwhile); it stays pending until it closes."""
        limit = self.max_open if control else self.max_open - self.reserve
        stage = self._stage.get(conn)
        if stage is None or len(self.opened) >= limit:
            return False
        del self._stage[conn]
        del self._pending[stage][conn]
        self.opened.add(conn)
        return True

    def leave(self, conn: object, ip: str) -> None:
        """A connection :meth:`arrive` admitted has closed."""
        self.tcp.release(ip)
        stage = self._stage.pop(conn, None)
        if stage is not None:
            del self._pending[stage][conn]
        self.opened.discard(conn)


class _Quiet(logging.LoggerAdapter):
    """The logger of an evicted connection: its failed handshake is counted, not logged."""

    def log(self, level: int, msg: object, *args: object, **kwargs: object) -> None:
        pass


#: the ``logger`` an :class:`Admission` server gives a connection it evicts (API, Foxglove door)
QUIET_LOG = _Quiet(logging.getLogger("websockets.server"), {})


def peer_ip(addr: Any) -> str:
    """The IP of a peer address (``(host, port, …)``); "?" for unknown transports, which then
    share one bucket."""
    try:
        return str(addr[0])
    except Exception:  # noqa: BLE001
        return "?"


class _TlsHold(asyncio.Protocol):
    """Stands in for a connection while ``loop.start_tls`` sets its TLS up: what the TLS layer
    hands on between the end of the handshake and the connection taking over (the request may
    come in the same packet as the client's last handshake message) is kept and replayed, then
    everything goes to the connection itself."""

    def __init__(self) -> None:
        self.target: asyncio.Protocol | None = None
        self.kept: list[tuple[str, Any]] = []

    def data_received(self, data: bytes) -> None:
        self._pass("data_received", data)

    def eof_received(self) -> None:
        self._pass("eof_received", None)

    def connection_lost(self, exc: Exception | None) -> None:
        self._pass("connection_lost", exc)

    # flow control: a pause the TLS layer signals before the hand-over reaches the connection
    # with it (else the connection would get a resume it never paused for)
    def pause_writing(self) -> None:
        self._pass("pause_writing", None)

    def resume_writing(self) -> None:
        self._pass("resume_writing", None)

    def _pass(self, event: str, arg: Any) -> None:
        if self.target is None:
            self.kept.append((event, arg))
        elif event in ("eof_received", "pause_writing", "resume_writing"):
            getattr(self.target, event)()
        else:
            getattr(self.target, event)(arg)

    def hand_over(self, target: asyncio.Protocol) -> None:
        self.target = target
        for event, arg in self.kept:
            self._pass(event, arg)
        self.kept.clear()


def _has_unread(conn: Any) -> bool:
    """Whether bytes wait unread in a pending connection's socket (its request, if it is a real
    client that the server has not got to yet): the kernel's count (FIONREAD), one system call;
    False where it cannot be asked."""
    transport = conn.ucr_tcp if conn.ucr_tcp is not None else getattr(conn, "transport", None)
    try:
        count = array.array("i", [0])
        fcntl.ioctl(transport.get_extra_info("socket").fileno(), termios.FIONREAD, count)
    except Exception:  # noqa: BLE001 - closed meanwhile, no socket (a test transport)
        return False
    return count[0] > 0


def admitted_connections(
    base: type,
    admission: Admission,
    refused: Callable[[str], None],
    evicted: Callable[[], None],
    *,
    tls: ssl.SSLContext | None = None,
    tls_timeout: float = 5.0,
    tls_close_timeout: float = 10.0,
) -> type:
    """``base`` (a websockets ``ServerConnection`` class) admitted by ``admission`` before any
    work, as every listener of the project admits them (the API server, the Foxglove door): above
    the per-peer cap the TCP connection is aborted (``refused(ip)``); a connection that makes room
    evicts the oldest pending one that got least far (``evicted()`` counts it); bytes received
    move a pending connection to :data:`TALKING`. Subclasses add their own bookkeeping in
    :meth:`ucr_admitted` and :meth:`ucr_gone`; ``ucr_ip`` is None for a connection not (or no
    longer) admitted.

    ``tls``: the server's TLS context, given here instead of to ``serve``: the server then
    accepts plain TCP, so a connection is admitted (counted pending and per peer) at its TCP
    accept, and only then upgraded (``loop.start_tls``, at most ``tls_timeout`` s; its TLS close
    at most ``tls_close_timeout`` s, websockets' default ``close_timeout``). Given to
    ``serve``, asyncio does the TLS handshake before the connection exists: a socket that never
    sent a ClientHello was in no cap, thousands of them held a descriptor each. A connection in
    its TLS handshake is pending and :data:`SILENT` (evicted first but for :data:`REFUSING`).

    With ``tls``, the server sends no TLS 1.3 session tickets (``tls.num_tickets`` is set to 0
    here): they were the only records it sent between the handshake and the client's request,
    and a client that reads on one thread while it writes on another on the same TLS connection
    (websockets' sync client: the project's own, the tests') now and then lost its upgrade
    request to them (OpenSSL forbids that concurrent use): the request never left, the client
    waited out its open timeout, the server logged "did not receive a valid HTTP request".
    Resumption would only save a reconnecting client one handshake."""
    if tls is not None:
        tls.num_tickets = 0

    class Admitted(base):  # type: ignore[misc, valid-type]
        ucr_ip: str | None = None
        ucr_tcp: asyncio.Transport | None = None  # the TCP transport, while TLS is set up
        ucr_in_tls: ClassVar[set[Any]] = set()  # the connections in their TLS handshake

        def connection_made(self, transport: Any) -> None:
            ip = peer_ip(transport.get_extra_info("peername"))
            admitted, victim = admission.arrive(self, ip, _has_unread)
            if victim is not None:  # the oldest pending one that got least far
                victim.ucr_evict()
            if not admitted:
                refused(ip)
                transport.abort()
                return
            self.ucr_ip = ip
            self.ucr_admitted()
            if tls is None:
                super().connection_made(transport)
            else:
                self.ucr_tcp = transport
                self.ucr_in_tls.add(self)  # (which also keeps its task alive)
                self.ucr_tls_task = asyncio.get_running_loop().create_task(
                    self._ucr_start_tls(transport)
                )

        async def _ucr_start_tls(self, tcp: asyncio.Transport) -> None:
            """The TLS handshake; then the connection starts (its opening handshake) on the
            TLS transport, or, if the handshake failed, timed out or it was evicted, is gone."""
            hold = _TlsHold()
            app = None
            try:
                app = await asyncio.get_running_loop().start_tls(
                    tcp, hold, tls, server_side=True,
                    ssl_handshake_timeout=tls_timeout, ssl_shutdown_timeout=tls_close_timeout,
                )  # fmt: skip
            except Exception:  # noqa: BLE001 - not TLS (a plain ws:// client), reset, timed out
                pass
            finally:  # (also when cancelled: the loop ends)
                self.ucr_tcp = None
                self.ucr_in_tls.discard(self)
                if app is None or app.is_closing() or self.ucr_ip is None:  # evicted: None
                    (tcp if app is None else app).abort()
                    self._ucr_release()
                    app = None
            if app is not None:
                app.set_protocol(self)
                super().connection_made(app)
                hold.hand_over(self)

        @classmethod
        def ucr_abort_tls(cls) -> None:
            """Abort the connections still in their TLS handshake (the server stops: websockets
            closes only those whose opening handshake has started)."""
            for conn in list(cls.ucr_in_tls):
                conn.ucr_tcp.abort()

        def _ucr_release(self) -> bool:
            """Uncount it (once); False if it was not (or no longer) counted."""
            ip = self.ucr_ip
            if ip is None:
                return False
            self.ucr_ip = None
            admission.leave(self, ip)
            self.ucr_gone()
            return True

        def connection_lost(self, exc: Exception | None) -> None:
            if self._ucr_release():  # (else refused in connection_made: nothing was set up)
                super().connection_lost(exc)

        def ucr_admitted(self) -> None:
            """Admitted, before the handshake starts (a subclass's bookkeeping)."""

        def ucr_gone(self) -> None:
            """Closed after it was admitted (a subclass's bookkeeping)."""

        def ucr_evict(self) -> None:
            """Close this pending connection now. Its handshake task ends as for any connection
            lost in its handshake (so it unregisters itself: cancelling it before its first step
            leaked it in the server's handlers), but without the error and traceback websockets
            logs for that: one per evicted socket. One still in its TLS handshake has no
            handshake task yet: it is uncounted now, its TCP connection aborted (its TLS task
            then ends)."""
            evicted()
            self.logger = QUIET_LOG
            if self.ucr_tcp is not None:
                self.ucr_tcp.abort()
                self._ucr_release()
            else:
                self.transport.abort()

        def data_received(self, data: bytes) -> None:
            admission.advance(self, TALKING)
            super().data_received(data)

    return Admitted

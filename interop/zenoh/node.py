"""A ROS 2 node on a Zenoh session, as rmw_zenoh makes one: a node liveliness token, and per
publisher or subscription a Zenoh publisher/subscriber on the topic's key expression plus its own
liveliness token (so ``ros2 topic list`` and ``ros2 node info`` show it). Messages are CDR bytes
encoded by :mod:`interop.ros2`; each publication carries rmw_zenoh's attachment.

TRANSIENT_LOCAL publishers are Zenoh advanced publishers with a cache of ``depth`` samples,
publisher detection and sporadic sample-miss heartbeats, as rmw_zenoh declares them, so a
late-joining ROS 2 subscription (an advanced subscriber querying history) still receives
/robot_description, and one that missed a sample learns it from the next heartbeat.

A service answers every request it can match with a response of its own type: a request it
refuses (too large, not decodable, too many waiting, a handler failure) gets the service's
"refused" response (``refusal``), because rmw_zenoh's client only logs an error reply and its
caller would wait forever. Only a request without a valid rmw_zenoh attachment, whose reply no
rmw_zenoh client could match to its call, is answered with a Zenoh error reply.
"""

from __future__ import annotations

import queue
import sys
import threading
import time
from collections.abc import Callable
from typing import Any

from interop.ros2 import services
from interop.ros2.type_hash import service_type_hash, type_hash
from interop.zenoh import rmw

Callback = Callable[[bytes, "rmw.Attachment | None"], None]
Handler = Callable[[Any], dict]
Refusal = Callable[[str], dict]  # reason -> the service's response saying "refused"
MAX_REQUEST_BYTES = 64 * 1024  # a service request's CDR (default); larger ones are refused unread
MAX_DEFERRED = 64  # requests of a deferred service waiting for their answer (get_result)
# rmw_zenoh_cpp (src/detail/rmw_publisher_data.cpp): a RELIABLE + TRANSIENT_LOCAL publisher
# sends a sporadic sample-miss heartbeat every SAMPLE_MISS_DETECTION_HEARTBEAT_PERIOD = 500 ms
# (sent only when something was published since the last one)
MISS_HEARTBEAT_S = 0.5


class RmwPublisher:
    """One ROS 2 publisher. ``publish`` is thread-safe."""

    def __init__(
        self, node: RmwNode, topic: str, typename: str, qos: rmw.Qos, type_hash_: str = ""
    ) -> None:
        import zenoh  # noqa: PLC0415
        import zenoh.ext  # noqa: PLC0415

        self.fqn = rmw.fully_qualified(node.id.namespace, topic)
        self.typename = typename
        self.qos = qos
        self.hash = type_hash_ or type_hash(typename)
        self.key = rmw.topic_key(node.id.domain_id, self.fqn, typename, self.hash)
        self.entity_id = node.next_entity_id()
        self.gid = rmw.gid(node.id.zid, node.id.node_id, self.entity_id)
        self._seq = 0
        self._lock = threading.Lock()
        if qos.transient_local:
            reliable = qos.reliability == rmw.RELIABLE
            self._pub = zenoh.ext.declare_advanced_publisher(
                node.session,
                self.key,
                cache=zenoh.ext.CacheConfig(max_samples=qos.depth),
                publisher_detection=True,
                sample_miss_detection=(
                    zenoh.ext.MissDetectionConfig(sporadic_heartbeat=MISS_HEARTBEAT_S)
                    if reliable
                    else None
                ),
            )
        else:
            self._pub = node.session.declare_publisher(
                self.key,
                congestion_control=zenoh.CongestionControl.DROP,  # never wait for a slow peer
            )
        self.token_key = rmw.endpoint_token(
            node.id, self.entity_id, rmw.PUBLISHER, self.fqn, typename, self.hash, qos
        )
        self._token = node.liveliness.declare_token(self.token_key)
        self.published = 0

    def matching(self) -> bool:
        """Whether some subscriber on the network matches this topic now (Zenoh's matching
        status; a latched topic: always, its cache serves late joiners from what was put)."""
        if self.qos.transient_local:
            return True
        try:
            return bool(self._pub.matching_status.matching)
        except Exception:  # noqa: BLE001 - cannot tell (a closing session): publish, as before
            return True

    def publish(self, data: bytes, t_ns: int | None = None) -> None:
        """Send CDR ``data`` with an attachment stamped ``t_ns`` (default: now)."""
        with self._lock:
            self._seq += 1
            att = rmw.Attachment(self._seq, time.time_ns() if t_ns is None else t_ns, self.gid)
            self._pub.put(data, attachment=att.encode())
            self.published += 1

    def close(self) -> None:
        for ent in (self._token, self._pub):
            try:
                ent.undeclare()
            except Exception:  # noqa: BLE001, S110 - the session may be closing already
                pass


class RmwSubscription:
    """One ROS 2 subscription; ``callback(cdr_bytes, attachment or None)`` runs on a Zenoh
    thread and must not block.

    With ``unattributed`` (the command subscription), a sample without a valid rmw_zenoh
    attachment is not delivered: ``unattributed(why)`` is called instead (Zenoh thread, must not
    block) and it is counted in ``refused``. Every ROS 2 publisher attaches one (rmw_zenoh drops
    samples without); a plain Zenoh ``put`` does not, and a command must name its publisher's
    GID in the audit. Without ``unattributed`` such a sample is delivered with ``None``."""

    def __init__(
        self,
        node: RmwNode,
        topic: str,
        typename: str,
        callback: Callback,
        qos: rmw.Qos,
        unattributed: Callable[[str], None] | None = None,
    ) -> None:
        self.fqn = rmw.fully_qualified(node.id.namespace, topic)
        self.typename = typename
        self.hash = type_hash(typename)
        self.key = rmw.topic_key(node.id.domain_id, self.fqn, typename, self.hash)
        self.entity_id = node.next_entity_id()
        self.received = 0
        self.bad_attachments = 0
        self.refused = 0

        def on_sample(sample: Any) -> None:
            self.received += 1
            att = None
            why = "no rmw_zenoh attachment"
            if sample.attachment is not None:
                try:
                    att = rmw.Attachment.decode(sample.attachment.to_bytes())
                except ValueError as exc:
                    self.bad_attachments += 1
                    why = f"bad rmw_zenoh attachment: {exc}"
            if att is None and unattributed is not None:
                self.refused += 1
                unattributed(why)
                return
            callback(sample.payload.to_bytes(), att)

        self._sub = node.session.declare_subscriber(self.key, on_sample)
        self.token_key = rmw.endpoint_token(
            node.id, self.entity_id, rmw.SUBSCRIPTION, self.fqn, typename, self.hash, qos
        )
        self._token = node.liveliness.declare_token(self.token_key)

    def close(self) -> None:
        for ent in (self._token, self._sub):
            try:
                ent.undeclare()
            except Exception:  # noqa: BLE001, S110
                pass


def _finish(query: Any) -> None:
    """End a query (Zenoh sends the final reply when the query is dropped)."""
    try:
        query.drop()
    except Exception:  # noqa: BLE001, S110 - already finished
        pass


class RmwService:
    """One ROS 2 service server, as rmw_zenoh makes one: a Zenoh queryable (complete) on the
    service's key expression and an ``SS`` liveliness token.

    A request must carry rmw_zenoh's attachment (sequence number, client GID); the reply carries
    the same sequence number and GID with its own time stamp, so the client matches it.
    ``handler(request)`` runs on one worker thread (it may call the daemon; Zenoh's threads never
    wait) and returns the response as a dict; at most ``qos.depth`` requests wait.

    Refused, never reaching the handler: a request over ``max_request_bytes``, one that is not
    decodable CDR, one beyond the queue ("busy"); and a request whose handler failed. Each gets
    ``refusal(reason)``, a normal response of the service's type saying so (Trigger: success
    false and the reason; SendGoal: not accepted; CancelGoal: ERROR_REJECTED), because
    rmw_zenoh's client only logs an error reply and leaves its caller waiting. A request without
    a valid attachment (no sequence number and GID to echo: no rmw_zenoh client sent it, none
    could match a reply) and every refusal of a service without ``refusal`` are answered with a
    Zenoh error reply (``reply_err``) carrying the reason."""

    def __init__(
        self,
        node: RmwNode,
        name: str,
        srvtype: str,
        handler: Handler,
        qos: rmw.Qos,
        *,
        deferred: bool = False,
        type_hash_: str = "",
        codecs: tuple[Any, Any] | None = None,
        refusal: Refusal | None = None,
        max_request_bytes: int = MAX_REQUEST_BYTES,
    ) -> None:
        self.fqn = rmw.fully_qualified(node.id.namespace, name)
        self.srvtype = srvtype if codecs else services.full_name(srvtype)
        self.hash = type_hash_ or service_type_hash(self.srvtype)
        self.key = rmw.topic_key(node.id.domain_id, self.fqn, self.srvtype, self.hash)
        self.entity_id = node.next_entity_id()
        self.handler = handler
        self.deferred = deferred
        self.refusal = refusal
        self.max_request_bytes = max_request_bytes
        self._pending = threading.BoundedSemaphore(MAX_DEFERRED)
        self._req, self._resp = codecs or services.codecs(self.srvtype)
        self._queue: queue.Queue[Any] = queue.Queue(maxsize=max(1, qos.depth))
        self._stop = threading.Event()
        self.answered = 0
        self.refused = 0
        self._thread = threading.Thread(
            target=self._run, name=f"ucr-zenoh-srv-{self.entity_id}", daemon=True
        )
        self._thread.start()
        self._queryable = node.session.declare_queryable(self.key, self._on_query, complete=True)
        self.token_key = rmw.endpoint_token(
            node.id, self.entity_id, rmw.SERVICE, self.fqn, self.srvtype, self.hash, qos
        )
        self._token = node.liveliness.declare_token(self.token_key)

    def _on_query(self, query: Any) -> None:
        """Zenoh thread: check the envelope, queue the request (never block here)."""
        try:
            if query.attachment is None:
                raise ValueError("no rmw_zenoh attachment (sequence number, client GID)")
            att = rmw.Attachment.decode(query.attachment.to_bytes())
        except Exception as exc:  # noqa: BLE001 - any byte from the network is untrusted
            self._error(query, f"bad request: {exc}")
            _finish(query)
            return
        try:
            data = query.payload.to_bytes() if query.payload is not None else b""
            if len(data) > self.max_request_bytes:
                self._refuse(
                    query,
                    att,
                    f"request of {len(data)} bytes refused unread (at most "
                    f"{self.max_request_bytes} bytes)",
                )
                _finish(query)
                return
            self._queue.put_nowait((query, att, data))
        except queue.Full:
            self._refuse(query, att, "busy: too many requests waiting, try again")
            _finish(query)
        except Exception as exc:  # noqa: BLE001 - any byte from the network is untrusted
            self._refuse(query, att, f"bad request: {exc}")
            _finish(query)

    def _error(self, query: Any, text: str) -> None:
        """A Zenoh error reply (rmw_zenoh's client only logs it): for a request without a valid
        attachment, which no rmw_zenoh client could match a reply to, and for every refusal of a
        service without ``refusal``."""
        import zenoh  # noqa: PLC0415

        self.refused += 1
        try:
            query.reply_err(zenoh.ZBytes(f"{self.fqn}: {text}".encode()))
        except Exception:  # noqa: BLE001, S110 - the client may be gone
            pass

    def _refuse(self, query: Any, att: rmw.Attachment, text: str) -> None:
        """Answer with the service's own "refused" response (an error reply without one)."""
        if self.refusal is None:
            self._error(query, text)
            return
        try:
            payload = self._resp.encode(self.refusal(f"{self.fqn}: {text}"))
        except Exception as exc:  # noqa: BLE001 - a refusal that cannot be encoded
            self._error(query, f"{text} (and no response: {type(exc).__name__})")
            return
        self.refused += 1
        self._reply(query, att, payload, refusal=True)

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                query, att, data = self._queue.get(timeout=0.2)
            except queue.Empty:
                continue
            if self.deferred:
                self.handle_deferred(query, att, data)
                del query
                continue
            try:
                self.handle(query, att, data)
            finally:
                _finish(query)  # the client's get() ends only when the query is dropped
                del query

    def handle(self, query: Any, att: rmw.Attachment, data: bytes) -> None:
        """Decode, answer, reply (worker thread)."""
        try:
            request = self._req.decode(data)
        except Exception as exc:  # noqa: BLE001 - untrusted bytes
            self._refuse(query, att, f"request is not decodable CDR ({type(exc).__name__})")
            return
        try:
            payload = self._resp.encode(self.handler(request))
        except Exception as exc:  # noqa: BLE001 - a handler bug must not kill the server
            print(f"ucr zenoh: service {self.fqn} failed: {exc!r}", file=sys.stderr, flush=True)
            self._refuse(query, att, f"failed: {type(exc).__name__}")
            return
        self._reply(query, att, payload)

    def _reply(
        self, query: Any, att: rmw.Attachment, payload: bytes, *, refusal: bool = False
    ) -> None:
        reply_att = rmw.Attachment(att.sequence, time.time_ns(), att.gid)
        try:
            query.reply(self.key, payload, attachment=reply_att.encode())
            self.answered += not refusal
        except Exception:  # noqa: BLE001, S110 - the client may be gone
            pass

    def handle_deferred(self, query: Any, att: rmw.Attachment, data: bytes) -> None:
        """``handler(request, respond)``: ``respond(dict)`` may come later, from any thread
        (once; later calls are ignored). At most :data:`MAX_DEFERRED` wait."""
        try:
            request = self._req.decode(data)
        except Exception as exc:  # noqa: BLE001 - untrusted bytes
            self._refuse(query, att, f"request is not decodable CDR ({type(exc).__name__})")
            _finish(query)
            return
        if not self._pending.acquire(blocking=False):
            self._refuse(query, att, "busy: too many requests waiting for their answer")
            _finish(query)
            return
        held = [query]

        def respond(response: dict) -> None:
            if not held:
                return
            q = held.pop()
            try:
                self._reply(q, att, self._resp.encode(response))
            except Exception as exc:  # noqa: BLE001
                self._refuse(q, att, f"failed: {type(exc).__name__}")
            finally:
                _finish(q)
                self._pending.release()

        try:
            self.handler(request, respond)
        except Exception as exc:  # noqa: BLE001 - a handler bug must not kill the server
            print(f"ucr zenoh: service {self.fqn} failed: {exc!r}", file=sys.stderr, flush=True)
            if held:
                self._refuse(held[0], att, f"failed: {type(exc).__name__}")
                respond_err = held.pop()
                _finish(respond_err)
                self._pending.release()

    def close(self) -> None:
        for ent in (self._token, self._queryable):
            try:
                ent.undeclare()
            except Exception:  # noqa: BLE001, S110
                pass
        self._stop.set()
        self._thread.join(timeout=5)


class GraphWatch:
    """The liveliness tokens matching ``key_exprs`` that sessions other than this one hold: a
    liveliness subscriber with history (the tokens already in the graph, then each one declared
    or withdrawn later). ``on_join(key)`` runs on a Zenoh thread for each token declared after
    :meth:`settle`."""

    def __init__(self, session: Any, key_exprs: list[str]) -> None:
        import zenoh  # noqa: PLC0415

        self._put = zenoh.SampleKind.PUT
        self.own = str(session.info.zid())
        self.session = session
        self.keys: dict[str, None] = {}  # insertion-ordered set
        self.on_join: Callable[[str], None] | None = None
        self._lock = threading.Lock()
        self._subs = [
            session.liveliness().declare_subscriber(k, self._on_sample, history=True)
            for k in key_exprs
        ]

    def _on_sample(self, sample: Any) -> None:
        key = str(sample.key_expr)
        parts = key.split("/")
        if len(parts) > 2 and parts[2] == self.own:
            return
        with self._lock:
            if sample.kind == self._put:
                self.keys[key] = None
                hook = self.on_join
            else:
                self.keys.pop(key, None)
                hook = None
        if hook is not None:
            hook(key)

    def settle(self, timeout: float, done: Callable[[list[str]], bool]) -> list[str]:
        """Wait until ``done(keys)`` or ``timeout`` s (tokens of the sessions this one is connected
        to reach it shortly after the connection: there is no "that was all" to wait for); at
        once when this session is connected to no router and no peer. The tokens seen."""
        end = time.monotonic() + timeout
        while True:
            keys = self.current()
            if done(keys) or time.monotonic() >= end:
                return keys
            info = self.session.info
            if not list(info.routers_zid()) and not list(info.peers_zid()):
                return keys
            time.sleep(0.02)

    def current(self) -> list[str]:
        with self._lock:
            return list(self.keys)

    def close(self) -> None:
        for sub in self._subs:
            try:
                sub.undeclare()
            except Exception:  # noqa: BLE001, S110 - the session may be closing already
                pass


class RmwNode:
    """A node in ``namespace`` on an open Zenoh ``session`` (the caller owns the session)."""

    def __init__(self, session: Any, *, name: str, namespace: str, domain_id: int = 0) -> None:
        if not 0 <= domain_id <= rmw.DOMAIN_ID_MAX:
            raise ValueError(f"ROS domain id {domain_id}: must be 0..{rmw.DOMAIN_ID_MAX}")
        self.session = session
        self.liveliness = session.liveliness()
        self.id = rmw.NodeId(
            domain_id=domain_id,
            zid=str(session.info.zid()),
            node_id=0,
            namespace=rmw.check_namespace(namespace),
            name=rmw.check_node_name(name),
        )
        self._entity = 0
        self.entities: list[RmwPublisher | RmwSubscription | RmwService] = []
        self._token = self.liveliness.declare_token(rmw.node_token(self.id))

    def next_entity_id(self) -> int:
        self._entity += 1
        return self._entity

    def publisher(
        self, topic: str, typename: str, qos: rmw.Qos = rmw.DEFAULT_QOS, type_hash_: str = ""
    ) -> RmwPublisher:
        pub = RmwPublisher(self, topic, typename, qos, type_hash_)
        self.entities.append(pub)
        return pub

    def subscription(
        self,
        topic: str,
        typename: str,
        callback: Callback,
        qos: rmw.Qos = rmw.DEFAULT_QOS,
        unattributed: Callable[[str], None] | None = None,
    ) -> RmwSubscription:
        sub = RmwSubscription(self, topic, typename, callback, qos, unattributed)
        self.entities.append(sub)
        return sub

    def service(
        self,
        name: str,
        srvtype: str,
        handler: Any,
        qos: rmw.Qos = rmw.SERVICE_QOS,
        **kw: Any,
    ) -> RmwService:
        srv = RmwService(self, name, srvtype, handler, qos, **kw)
        self.entities.append(srv)
        return srv

    def close(self) -> None:
        """Withdraw every entity and the node from the graph."""
        for ent in reversed(self.entities):
            ent.close()
        self.entities.clear()
        try:
            self._token.undeclare()
        except Exception:  # noqa: BLE001, S110
            pass

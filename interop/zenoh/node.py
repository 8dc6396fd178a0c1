"""A ROS 2 node on a Zenoh session, as rmw_zenoh makes one: a node liveliness token, and per
publisher or subscription a Zenoh publisher/subscriber on the topic's key expression plus its own
liveliness token (so ``ros2 topic list`` and ``ros2 node info`` show it). Messages are CDR bytes
encoded by :mod:`interop.ros2`; each publication carries rmw_zenoh's attachment.

TRANSIENT_LOCAL publishers are Zenoh advanced publishers with a cache of ``depth`` samples and
publisher detection, as rmw_zenoh declares them, so a late-joining ROS 2 subscription (an
advanced subscriber querying history) still receives /robot_description.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

from interop.ros2.type_hash import type_hash
from interop.zenoh import rmw

Callback = Callable[[bytes, "rmw.Attachment | None"], None]


class RmwPublisher:
    """One ROS 2 publisher. ``publish`` is thread-safe."""

    def __init__(self, node: RmwNode, topic: str, typename: str, qos: rmw.Qos) -> None:
        import zenoh  # noqa: PLC0415
        import zenoh.ext  # noqa: PLC0415

        self.fqn = rmw.fully_qualified(node.id.namespace, topic)
        self.typename = typename
        self.qos = qos
        self.hash = type_hash(typename)
        self.key = rmw.topic_key(node.id.domain_id, self.fqn, typename, self.hash)
        self.entity_id = node.next_entity_id()
        self.gid = rmw.gid(node.id.zid, node.id.node_id, self.entity_id)
        self._seq = 0
        self._lock = threading.Lock()
        if qos.transient_local:
            self._pub = zenoh.ext.declare_advanced_publisher(
                node.session,
                self.key,
                cache=zenoh.ext.CacheConfig(max_samples=qos.depth),
                publisher_detection=True,
                sample_miss_detection=zenoh.ext.MissDetectionConfig(),
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
    thread and must not block."""

    def __init__(
        self, node: RmwNode, topic: str, typename: str, callback: Callback, qos: rmw.Qos
    ) -> None:
        self.fqn = rmw.fully_qualified(node.id.namespace, topic)
        self.typename = typename
        self.hash = type_hash(typename)
        self.key = rmw.topic_key(node.id.domain_id, self.fqn, typename, self.hash)
        self.entity_id = node.next_entity_id()
        self.received = 0
        self.bad_attachments = 0

        def on_sample(sample: Any) -> None:
            self.received += 1
            att = None
            if sample.attachment is not None:
                try:
                    att = rmw.Attachment.decode(sample.attachment.to_bytes())
                except ValueError:
                    self.bad_attachments += 1
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
        self.entities: list[RmwPublisher | RmwSubscription] = []
        self._token = self.liveliness.declare_token(rmw.node_token(self.id))

    def next_entity_id(self) -> int:
        self._entity += 1
        return self._entity

    def publisher(self, topic: str, typename: str, qos: rmw.Qos = rmw.DEFAULT_QOS) -> RmwPublisher:
        pub = RmwPublisher(self, topic, typename, qos)
        self.entities.append(pub)
        return pub

    def subscription(
        self, topic: str, typename: str, callback: Callback, qos: rmw.Qos = rmw.DEFAULT_QOS
    ) -> RmwSubscription:
        sub = RmwSubscription(self, topic, typename, callback, qos)
        self.entities.append(sub)
        return sub

    def close(self) -> None:
        """Withdraw every entity and the node from the graph."""
        for ent in reversed(self.entities):
            ent.close()
        self.entities.clear()
        try:
            self._token.undeclare()
        except Exception:  # noqa: BLE001, S110
            pass

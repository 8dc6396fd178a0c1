"""rmw_zenoh's wire format, as its design document specifies it (ros2/rmw_zenoh docs/design.md):
topic key expressions, liveliness-token key expressions for the ROS 2 graph, the compact QoS
string, the publication attachment and ROS name rules. Pure functions, no Zenoh session here.

- data key: ``<domain_id>/<fully_qualified_name>/<dds_type_name>/<type_hash>``
- node token: ``@ros2_lv/<domain>/<zid>/<node_id>/<node_id>/NN/<enclave>/<namespace>/<node>``
- endpoint token: ``…/<node_id>/<entity_id>/<MP|MS|SS|SC>/<enclave>/<namespace>/<node>/
  <mangled_fqn>/<dds_type_name>/<type_hash>/<qos>`` (mangled: every ``/`` replaced by ``%``;
  an empty namespace or enclave is ``%``)
- attachment: int64 sequence number, int64 source timestamp (ns since the UNIX epoch), uint8 GID
  length (16), the GID; all little-endian.
"""

from __future__ import annotations

import hashlib
import re
import struct
from dataclasses import dataclass

from interop import ros2

DISTROS = ("jazzy", "kilted", "lyrical", "rolling")  # rmw_zenoh with RIHS01 type hashes

ADMIN_SPACE = "@ros2_lv"
NODE, PUBLISHER, SUBSCRIPTION, SERVICE, CLIENT = "NN", "MP", "MS", "SS", "SC"
GID_SIZE = 16
DOMAIN_ID_MAX = 232  # ROS 2's largest domain id

# rmw QoS enum values (rmw/types.h) and rmw_zenoh's defaults, which the QoS string leaves out
RELIABLE, BEST_EFFORT = 1, 2
TRANSIENT_LOCAL, VOLATILE = 1, 2
KEEP_LAST, KEEP_ALL = 1, 2
_DEFAULT_DEPTH = 42

_TOKEN = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
_ATTACHMENT = struct.Struct("<qqB")


class RosNameError(ValueError):
    """Not a valid ROS 2 name (topic, namespace, node)."""


def dds_type_name(typename: str) -> str:
    """``sensor_msgs/msg/JointState`` -> ``sensor_msgs::msg::dds_::JointState_`` (also
    ``pkg/srv/Service`` -> ``pkg::srv::dds_::Service_``; ``pkg/Type`` is a message)."""
    parts = typename.split("/")
    if len(parts) == 3 and parts[1] in ("srv", "action"):
        pkg, kind, name = parts
    else:
        pkg, kind, name = ros2.full_name(typename).split("/")
    return f"{pkg}::{kind}::dds_::{name}_"


def ros_type_name(dds: str) -> str:
    """Inverse of :func:`dds_type_name`."""
    parts = dds.split("::")
    if len(parts) != 4 or parts[2] != "dds_" or not parts[3].endswith("_"):
        raise ValueError(f"not a DDS type name: {dds!r}")
    return f"{parts[0]}/{parts[1]}/{parts[3][:-1]}"


def mangle(name: str) -> str:
    """A name inside a liveliness token: ``/`` -> ``%``; empty -> ``%``."""
    return name.replace("/", "%") if name else "%"


def check_namespace(ns: str) -> str:
    """A valid absolute ROS namespace (``/`` or ``/a/b``), else :class:`RosNameError`."""
    if ns in ("", "/"):
        return "/"
    if not ns.startswith("/"):
        ns = "/" + ns
    parts = ns[1:].split("/")
    if not all(_TOKEN.fullmatch(p) for p in parts):
        raise RosNameError(
            f"invalid ROS namespace {ns!r}: use letters, digits and '_' separated by '/', "
            "no part starting with a digit"
        )
    return ns


def namespace_for(robot_name: str) -> str:
    """The namespace of a robot from its U(C)RDF name: every character a ROS name cannot hold
    becomes ``_`` (``soft-robot 3`` -> ``/soft_robot_3``; a leading digit gets a ``_``)."""
    token = re.sub(r"[^A-Za-z0-9_]", "_", robot_name.strip()) or "robot"
    if token[0].isdigit():
        token = "_" + token
    return "/" + token


def check_node_name(name: str) -> str:
    if not _TOKEN.fullmatch(name):
        raise RosNameError(f"invalid ROS node name {name!r}: letters, digits and '_' only")
    return name


def check_controller_name(name: str) -> str:
    """A controller name: one ROS name token (a ros2_control controller is a node of the robot's
    namespace). Its topic and action are relative to the namespace, so ``/x`` (absolute, outside
    the namespace), ``a/b`` and ``~x`` are refused."""
    if not _TOKEN.fullmatch(name):
        raise RosNameError(
            f"invalid controller name {name!r}: letters, digits and '_', not starting with a "
            "digit (its topics stay inside the robot's namespace: no '/')"
        )
    return name


def fully_qualified(namespace: str, name: str) -> str:
    """Topic ``name`` (absolute, or relative to ``namespace``) as a fully qualified name."""
    if name.startswith("/"):
        fqn = name
    else:
        fqn = namespace.rstrip("/") + "/" + name
    parts = fqn[1:].split("/")
    if not all(_TOKEN.fullmatch(p) for p in parts):
        raise RosNameError(f"invalid ROS topic name {fqn!r}")
    return fqn


def topic_key(domain_id: int, fqn: str, typename: str, type_hash: str) -> str:
    """The Zenoh key expression a topic's data travels on."""
    return f"{domain_id}/{fqn.lstrip('/')}/{dds_type_name(typename)}/{type_hash}"


@dataclass(frozen=True)
class Qos:
    """The QoS fields ucr uses; deadline, lifespan and liveliness stay at rmw_zenoh's defaults."""

    reliability: int = RELIABLE
    durability: int = VOLATILE
    history: int = KEEP_LAST
    depth: int = 10

    def encode(self) -> str:
        """rmw_zenoh's compact QoS string: fields equal to its defaults are left empty."""
        rel = "" if self.reliability == RELIABLE else str(self.reliability)
        dur = "" if self.durability == VOLATILE else str(self.durability)
        hist = "" if self.history == KEEP_LAST else str(self.history)
        depth = "" if self.depth == _DEFAULT_DEPTH else str(self.depth)
        return f"{rel}:{dur}:{hist},{depth}:,:,:,,"

    @property
    def transient_local(self) -> bool:
        return self.durability == TRANSIENT_LOCAL


DEFAULT_QOS = Qos()
SERVICE_QOS = Qos()  # rmw_qos_profile_services_default: reliable, volatile, keep last 10
LATCHED_QOS = Qos(durability=TRANSIENT_LOCAL, depth=1)  # robot_state_publisher's description


def decode_qos(text: str) -> Qos:
    """Parse the compact QoS string (the fields ucr uses)."""
    parts = text.split(":")
    if len(parts) != 6:
        raise ValueError(f"not an rmw_zenoh QoS string: {text!r}")
    hist, _, depth = parts[2].partition(",")
    return Qos(
        reliability=int(parts[0]) if parts[0] else RELIABLE,
        durability=int(parts[1]) if parts[1] else VOLATILE,
        history=int(hist) if hist else KEEP_LAST,
        depth=int(depth) if depth else _DEFAULT_DEPTH,
    )


@dataclass(frozen=True)
class NodeId:
    """Where a node lives in the ROS 2 graph."""

    domain_id: int
    zid: str
    node_id: int
    namespace: str
    name: str
    enclave: str = ""


def node_token(node: NodeId) -> str:
    """Liveliness key expression announcing a node."""
    ns = "%" if node.namespace in ("", "/") else mangle(node.namespace)
    return (
        f"{ADMIN_SPACE}/{node.domain_id}/{node.zid}/{node.node_id}/{node.node_id}/{NODE}/"
        f"{mangle(node.enclave)}/{ns}/{node.name}"
    )


def node_query(domain_id: int, namespace: str, name: str) -> str:
    """Liveliness key expression matching every node ``<namespace>/<name>`` of the domain (any
    session, node id and enclave)."""
    ns = "%" if namespace in ("", "/") else mangle(namespace)
    return f"{ADMIN_SPACE}/{domain_id}/*/*/*/{NODE}/*/{ns}/{name}"


def server_query(domain_id: int, fqn: str) -> str:
    """Liveliness key expression matching every server of the service ``fqn`` in the domain."""
    return f"{ADMIN_SPACE}/{domain_id}/*/*/*/{SERVICE}/*/*/*/{mangle(fqn)}/**"


def parse_node_token(key: str) -> tuple[str, str, str] | None:
    """A node token's (zid, namespace, name), or None for anything else."""
    parts = key.split("/")
    if len(parts) != 9 or parts[0] != ADMIN_SPACE or parts[5] != NODE:
        return None
    return parts[2], "/" if parts[7] == "%" else parts[7].replace("%", "/"), parts[8]


def endpoint_token(
    node: NodeId, entity_id: int, kind: str, fqn: str, typename: str, type_hash: str, qos: Qos
) -> str:
    """Liveliness key expression announcing a publisher, subscription, service or client."""
    if kind not in (PUBLISHER, SUBSCRIPTION, SERVICE, CLIENT):
        raise ValueError(f"unknown entity kind {kind!r}")
    ns = "%" if node.namespace in ("", "/") else mangle(node.namespace)
    return (
        f"{ADMIN_SPACE}/{node.domain_id}/{node.zid}/{node.node_id}/{entity_id}/{kind}/"
        f"{mangle(node.enclave)}/{ns}/{node.name}/{mangle(fqn)}/{dds_type_name(typename)}/"
        f"{type_hash}/{qos.encode()}"
    )


@dataclass(frozen=True)
class Endpoint:
    """A parsed endpoint liveliness token."""

    domain_id: int
    zid: str
    node_id: int
    entity_id: int
    kind: str
    namespace: str
    node: str
    topic: str
    typename: str
    type_hash: str
    qos: Qos


def parse_endpoint_token(key: str) -> Endpoint | None:
    """An endpoint token's fields, or None for a node token or anything else."""
    parts = key.split("/")
    if len(parts) != 13 or parts[0] != ADMIN_SPACE or parts[5] == NODE:
        return None
    try:
        return Endpoint(
            domain_id=int(parts[1]),
            zid=parts[2],
            node_id=int(parts[3]),
            entity_id=int(parts[4]),
            kind=parts[5],
            namespace="/" if parts[7] == "%" else parts[7].replace("%", "/"),
            node=parts[8],
            topic=parts[9].replace("%", "/"),
            typename=ros_type_name(parts[10]),
            type_hash=parts[11],
            qos=decode_qos(parts[12]),
        )
    except ValueError:
        return None


def gid(zid: str, node_id: int, entity_id: int) -> bytes:
    """A 16-byte GID unique to one entity of one session (stable for its lifetime)."""
    return hashlib.sha256(f"{zid}/{node_id}/{entity_id}".encode()).digest()[:GID_SIZE]


@dataclass(frozen=True)
class Attachment:
    """rmw_zenoh's per-message attachment."""

    sequence: int
    timestamp_ns: int
    gid: bytes

    def encode(self) -> bytes:
        if len(self.gid) > 255:
            raise ValueError("GID longer than 255 bytes")
        return _ATTACHMENT.pack(self.sequence, self.timestamp_ns, len(self.gid)) + self.gid

    @classmethod
    def decode(cls, data: bytes) -> Attachment:
        """Parse an attachment; ValueError when it is short or its GID length lies."""
        if len(data) < _ATTACHMENT.size:
            raise ValueError(f"attachment of {len(data)} bytes: too short")
        seq, ts, n = _ATTACHMENT.unpack_from(data)
        g = bytes(data[_ATTACHMENT.size : _ATTACHMENT.size + n])
        if len(g) != n:
            raise ValueError(f"attachment GID length {n} but {len(g)} bytes follow")
        return cls(seq, ts, g)

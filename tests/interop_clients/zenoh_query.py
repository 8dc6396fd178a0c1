"""A raw Zenoh query as a ROS 2 service client sends one, and an isolated session, for the
service tests."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager


def query(session, key: str, payload: bytes, attachment: bytes | None) -> list:
    """One query; its replies as ("ok", bytes, attachment bytes) / ("err", text, None)."""
    out = []
    kw = {"payload": payload, "timeout": 10.0}
    if attachment is not None:
        kw["attachment"] = attachment
    for reply in session.get(key, **kw):
        if reply.ok is not None:
            att = reply.ok.attachment.to_bytes() if reply.ok.attachment is not None else None
            out.append(("ok", reply.ok.payload.to_bytes(), att))
        else:
            out.append(("err", reply.err.payload.to_bytes().decode(), None))
    return out


@contextmanager
def isolated_session() -> Iterator:
    """A Zenoh peer session that listens nowhere and finds no one (no scouting): the tests'
    servers and clients meet inside it."""
    import zenoh  # noqa: PLC0415 - the 'ros2' extra; the test modules skip without it

    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("listen/endpoints", "[]")
    conf.insert_json5("connect/endpoints", "[]")
    conf.insert_json5("scouting/multicast/enabled", "false")
    with zenoh.open(conf) as s:
        yield s

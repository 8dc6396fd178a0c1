"""A raw Zenoh query as a ROS 2 service client sends one, for the service tests."""

from __future__ import annotations


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

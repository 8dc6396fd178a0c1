"""Sending a trajectory above the API's request limit: ``trajectory.upload`` chunks, then
``trajectory.send`` with the last one (docs/api.md "trajectory.upload")."""

from __future__ import annotations

import json
import threading
from collections.abc import Callable
from typing import Any

from host.api.client_errors import ApiError, ApiTimeoutError
from host.api.client_json import plain_json, unencodable
from host.api.schema import MAX_REQUEST_BYTES

CHUNK_BYTES = MAX_REQUEST_BYTES - 4096  # waypoints per request, JSON bytes (room for the rest)
_COMPACT = (",", ":")

Call = Callable[..., Any]


def send_in_chunks(
    call: Call, points: list[dict], params: dict, reply_s: float, lock: threading.Lock
) -> Any:
    """``trajectory.send`` of ``points`` through ``call`` (a client's :meth:`call`), uploaded in
    chunks first when they do not fit one request; the send's result.

    Threads sending long trajectories through one client take turns (``lock``): the server
    serves one request of a connection at a time anyway, and holds at most
    ``schema.MAX_UPLOADS`` uploads per connection. A trajectory that fits one request needs no
    turn."""
    chunks = chunks_of(points, CHUNK_BYTES)
    if len(chunks) == 1:
        return call("trajectory.send", timeout=reply_s, points=chunks[0], **params)
    with lock:
        return _upload_then_send(call, chunks, params, reply_s)


def _upload_then_send(call: Call, chunks: list[list[dict]], params: dict, reply_s: float) -> Any:
    upload = None
    try:
        for chunk in chunks[:-1]:
            extra = {} if upload is None else {"upload": upload}
            upload = call("trajectory.upload", points=chunk, **extra)["upload"]
        if upload is not None:
            params = {**params, "upload": upload}
        return call("trajectory.send", timeout=reply_s, points=chunks[-1], **params)
    except ApiTimeoutError:
        # The server may still hold the waypoints sent so far: free them now rather than after
        # its 60 s idle limit (a refused chunk or send already ended the upload).
        if upload is not None:
            cancel_upload(call, upload)
        raise


def cancel_upload(call: Call, upload: int) -> bool:
    """End an unfinished upload; False if the server no longer had it or did not answer."""
    try:
        call("trajectory.upload_cancel", upload=upload)
    except ApiError:
        return False
    return True


def chunks_of(points: list[dict], limit: int) -> list[list[dict]]:
    """Split waypoints into lists whose JSON stays below ``limit`` bytes (at least one each)."""
    out: list[list[dict]] = [[]]
    size = 0
    for i, p in enumerate(points):
        try:
            text = json.dumps(p, allow_nan=False, separators=_COMPACT, default=plain_json)
        except (TypeError, ValueError) as exc:  # before any chunk went: no upload left behind
            where = unencodable(p, f"points[{i}]") or str(exc)
            raise ApiError("invalid_params", f"cannot encode request: {where}") from None
        n = len(text.encode()) + 1
        if out[-1] and size + n > limit:
            out.append([])
            size = 0
        out[-1].append(p)
        size += n
    return out

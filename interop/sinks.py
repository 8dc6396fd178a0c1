"""Where encoded ROS 2 messages go: an MCAP file, the Foxglove server, a viewer.

A sink takes messages already CDR-encoded (so a recording replays byte for byte and a live feed
encodes each message once for every sink). :class:`Fanout` encodes a
:class:`~interop.topics.Message` once and hands the bytes to each sink; a sink that fails is
reported and dropped, never allowed to stop the others; its owner learns of it through
``on_drop`` (``ucr record`` stops when its file fails).
"""

from __future__ import annotations

import logging
import sys
from collections.abc import Callable, Iterable, Mapping
from typing import Protocol

from interop import ros2
from interop.topics import Message

Channel = tuple[str, str, str]  # (topic, typename, schema text)

log = logging.getLogger(__name__)


class Sink(Protocol):
    """A consumer of encoded messages. ``typename`` is ``pkg/msg/Type``; its definition text is
    ``interop.ros2.definition(typename)`` (or the schema a recording carried)."""

    def write(self, topic: str, typename: str, schema: str, data: bytes, t_ns: int) -> None: ...

    def tick(self) -> None:
        """Called often (>= 10 Hz) even when no message flows: flush, re-send latched data."""

    def close(self) -> None: ...

    # optional: ``advertise(channels: list[Channel]) -> None``, the topics to come, before their
    # first message (a live server's clients subscribe to what is advertised: the Foxglove sink)


def channels_of(topics: Mapping[str, str]) -> list[Channel]:
    """(topic, typename, schema text) of each ``topic -> ROS 2 type``, as :meth:`Fanout.publish`
    writes them."""
    out = []
    for topic, typename in topics.items():
        c = ros2.codec(typename)
        out.append((topic, c.name, c.schema_text))
    return out


class Fanout:
    """Encode once, write to every sink. A sink that fails is closed and dropped; the others go
    on. ``on_drop(sink, exc)`` is then called instead of the default one line on stderr."""

    def __init__(
        self, sinks: list[Sink], on_drop: Callable[[Sink, Exception], None] | None = None
    ) -> None:
        self.sinks = list(sinks)
        self.messages = 0
        self.on_drop = on_drop

    def publish(self, m: Message) -> None:
        c = ros2.codec(m.typename)
        self.write(m.topic, c.name, c.schema_text, c.encode(m.msg), m.t_ns)

    def advertise(self, channels: Iterable[Channel]) -> None:
        """Announce the topics to come to every sink that advertises (the others learn a topic
        from its first message)."""
        channels = list(channels)
        for s in list(self.sinks):
            adv = getattr(s, "advertise", None)
            if adv is None:
                continue
            try:
                adv(channels)
            except Exception as exc:  # noqa: BLE001 - one broken sink never stops the others
                self._drop(s, exc)

    def wants(self, topic: str) -> bool:
        """Whether any sink would take a message on ``topic`` now: a sink without ``wants``
        (a recording) takes everything; a Zenoh sink only while a subscriber matches. The feed
        asks before it computes and encodes a periodic topic (FK, CDR: most of its CPU)."""
        for s in self.sinks:
            wants = getattr(s, "wants", None)
            if wants is None:
                return True
            try:
                if wants(topic):
                    return True
            except Exception:  # noqa: BLE001 - it cannot tell: send, as before
                return True
        return False

    def write(self, topic: str, typename: str, schema: str, data: bytes, t_ns: int) -> None:
        self.messages += 1
        for s in list(self.sinks):
            try:
                s.write(topic, typename, schema, data, t_ns)
            except Exception as exc:  # noqa: BLE001 - one broken sink never stops the others
                self._drop(s, exc)

    def tick(self) -> None:
        for s in list(self.sinks):
            try:
                s.tick()
            except Exception as exc:  # noqa: BLE001
                self._drop(s, exc)

    def _drop(self, sink: Sink, exc: Exception) -> None:
        log.debug("sink failed", exc_info=exc)
        self.sinks.remove(sink)
        try:
            sink.close()
        except Exception:  # noqa: BLE001, S110 - already failed
            pass
        if self.on_drop is not None:
            self.on_drop(sink, exc)
        else:
            print(f"ucr: {type(sink).__name__} stopped: {type(exc).__name__}: {exc}",
                  file=sys.stderr)  # fmt: skip

    def close(self) -> None:
        for s in self.sinks:
            s.close()

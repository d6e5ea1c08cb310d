"""Reading the intact part of a damaged MCAP file (a recording cut short: power loss, a full disk, a copy
interrupted), which ``rosbags`` refuses because the file's end (footer, summary) is missing.

:class:`SalvagedMcap` streams the file's records with the ``mcap`` package's stream reader (schemas, channels and
messages, chunks decompressed) up to the first damaged or missing record, and offers the subset of ``rosbags``'
``AnyReader`` interface the project uses (``connections``, ``messages``, ``deserialize``, ``start_time``,
``end_time``, ``is2``, ``close``), deserialising CDR with the ROS 2 type store.
"""
from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class SalvagedConnection:
    """A channel of the file: topic, message type (``pkg/msg/Name``), the channel id and its readable messages."""

    topic: str
    msgtype: str
    id: int
    msgcount: int


class SalvagedMcap:
    """The readable part of a damaged MCAP file (module docstring).

    Args:
        path: the ``.mcap`` file.
        typestore: a ``rosbags`` type store for ``deserialize`` (ROS 2 CDR).

    Attributes:
        damage: why reading stopped (the stream reader's error), or None when the records ended cleanly.
        message_count: messages readable before the damage.
    """

    is2 = True

    def __init__(self, path: str | Path, typestore) -> None:
        self.path = Path(path)
        self.typestore = typestore
        self.damage: str | None = None
        channels: dict[int, tuple[str, str]] = {}   # id -> (topic, message type)
        counts: dict[int, int] = {}
        self.start_time, self.end_time = None, None
        for record in self._records():
            kind = type(record).__name__
            if kind == "Channel":
                channels[record.id] = (record.topic, self._schemas.get(record.schema_id, ""))
            elif kind == "Message" and record.channel_id in channels:
                counts[record.channel_id] = counts.get(record.channel_id, 0) + 1
                t = int(record.log_time)
                self.start_time = t if self.start_time is None else min(self.start_time, t)
                self.end_time = t if self.end_time is None else max(self.end_time, t)
        self.connections = [SalvagedConnection(topic, msgtype, k, counts.get(k, 0))
                            for k, (topic, msgtype) in channels.items() if msgtype]
        self.message_count = sum(counts.values())
        if self.start_time is None:
            raise ValueError(f"{self.path}: no readable message before the damage ({self.damage})")

    def _records(self) -> Iterator:
        """Every record up to the damage (schemas are remembered as they pass)."""
        from mcap.stream_reader import StreamReader

        self._schemas: dict[int, str] = {}
        with self.path.open("rb") as f:
            records = StreamReader(f).records
            while True:
                try:
                    record = next(records)
                except StopIteration:
                    return
                except Exception as err:   # noqa: BLE001 - the damage: truncated record, bad magic, bad chunk
                    self.damage = f"{type(err).__name__}: {err}" if str(err) else type(err).__name__
                    return
                if type(record).__name__ == "Schema":
                    self._schemas[record.id] = record.name
                yield record

    def messages(self, connections: list | None = None, start: int | None = None,
                 stop: int | None = None) -> Iterator[tuple[SalvagedConnection, int, bytes]]:
        """``(connection, log time ns, raw CDR)`` of the given connections (all when empty), in file order,
        with ``start <= log time < stop``."""
        wanted = {c.id: c for c in (connections or self.connections)}
        for record in self._records():
            if type(record).__name__ != "Message" or record.channel_id not in wanted:
                continue
            t = int(record.log_time)
            if (start is None or t >= start) and (stop is None or t < stop):
                yield wanted[record.channel_id], t, bytes(record.data)

    def deserialize(self, raw: bytes, msgtype: str):
        return self.typestore.deserialize_cdr(raw, msgtype)

    def close(self) -> None:
        """Nothing held open between passes."""

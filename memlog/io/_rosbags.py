"""What the ROS 1 and ROS 2 bag readers share: a rosbags reader and its connection table."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

from memlog.io.base import LogReader
from memlog.io.records import ChannelInfo, RawMessage
from memlog.io.types import LogInfo

__all__ = ["RosbagsLog", "msgdef_text"]


def msgdef_text(conn: Any) -> tuple[str, str]:
    md = getattr(conn, "msgdef", None)
    if md is None:
        return "", "msg"
    data = getattr(md, "data", md)
    fmt = getattr(getattr(md, "format", None), "name", "MSG")
    return (data if isinstance(data, str) else str(data)), fmt.lower()


class RosbagsLog(LogReader):
    """What the ROS 1 and ROS 2 bag readers share: a rosbags reader (None when the bag is read
    by a fallback) and the channel table built from its connections."""

    _reader: Any
    _chans: dict[int, ChannelInfo]

    def close(self) -> None:
        if self._reader is not None:
            self._reader.close()

    def channels(self) -> list[ChannelInfo]:
        return list(self._chans.values())

    def message_counts(self) -> dict[int, int] | None:
        if self._reader is None:
            return None
        return {c.id: c.msgcount for c in self._reader.connections}

    def _fill_time_range(self, info: LogInfo) -> None:
        if self._reader is not None and self._reader.message_count:
            info.start_ns, info.end_ns = self._reader.start_time, self._reader.end_time - 1

    def _rosbags_messages(self, topics: set[str] | None, start_ns: int | None, end_ns: int | None) -> Iterator[RawMessage]:
        conns = [c for c in self._reader.connections if topics is None or c.topic in topics]
        if not conns:
            return
        try:
            for conn, ts, raw in self._reader.messages(connections=conns, start=start_ns, stop=end_ns):
                yield RawMessage(self._chans[conn.id], ts, ts, 0, bytes(raw))
        except Exception as exc:
            self.report.truncated = True
            self.warn(f"{self.path}: bag is damaged ({type(exc).__name__}: {exc}); read everything before it")

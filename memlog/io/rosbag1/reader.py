"""ROS 1 bags (v2.0) through rosbags, streaming raw message bytes (ROS 1 serialization).

A bag whose index is damaged (a truncated recording) is read with a small sequential record
scanner up to the damage; it merges the chunks' messages back into log-time order.
"""

from __future__ import annotations

import bz2
import heapq
import io
import os
import struct
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any

from memlog.errors import LogReadError
from memlog.io._rosbags import RosbagsLog, msgdef_text
from memlog.io.base import LogReader
from memlog.io.records import ChannelInfo, RawMessage, SchemaInfo

__all__ = ["Ros1BagLog"]


def _ros1_name(msgtype: str) -> str:
    parts = msgtype.split("/")
    return f"{parts[0]}/{parts[-1]}" if len(parts) == 3 else msgtype


class Ros1BagLog(RosbagsLog):
    """A ROS 1 bag (v2.0). Messages keep their ROS 1 serialization."""

    format = "ros1bag"
    profile = "ros1"

    def __init__(self, path: str | os.PathLike[str]) -> None:
        super().__init__(path)
        from rosbags.rosbag1 import Reader

        self._reader: Any = None
        self._chans: dict[int, ChannelInfo] = {}
        try:
            self._reader = Reader(Path(self.path))
            self._reader.open()
        except Exception as exc:
            self._reader = None
            self.warn(f"{self.path}: bag index unreadable ({exc}); reading records sequentially up to the damage")
            self._scan = _Ros1Scanner(self.path, self)
            self._chans = self._scan.channels()
            return
        for c in self._reader.connections:
            text, _ = msgdef_text(c)
            meta = {"md5sum": str(c.digest)}
            ext = getattr(c, "ext", None)
            if ext is not None and getattr(ext, "callerid", None):
                meta["callerid"] = str(ext.callerid)
            if ext is not None and getattr(ext, "latching", None) is not None:
                meta["latching"] = str(int(ext.latching))
            schema = SchemaInfo(_ros1_name(c.msgtype), "ros1msg", text.encode())
            self._chans[c.id] = ChannelInfo(c.id, c.topic, "ros1", schema, meta)

    def _iter_messages(
        self, topics: set[str] | None, start_ns: int | None, end_ns: int | None, log_time_order: bool
    ) -> Iterator[RawMessage]:
        if self._reader is None:
            yield from self._scan.messages(topics, start_ns, end_ns)
        else:
            yield from self._rosbags_messages(topics, start_ns, end_ns)


class _Ros1Scanner:
    """Sequential ROS 1 bag v2.0 record reader, used when the index is unusable."""

    def __init__(self, path: str, owner: LogReader) -> None:
        self.path = path
        self.owner = owner
        self._chans: dict[int, ChannelInfo] | None = None

    @staticmethod
    def _fields(header: bytes) -> dict[str, bytes]:
        out: dict[str, bytes] = {}
        pos = 0
        while pos + 4 <= len(header):
            (n,) = struct.unpack_from("<I", header, pos)
            pos += 4
            key, _, val = header[pos : pos + n].partition(b"=")
            out[key.decode(errors="replace")] = val
            pos += n
        return out

    @staticmethod
    def _records(fh: IO[bytes] | Any) -> Iterator[tuple[dict[str, bytes], bytes]]:
        while True:
            head = fh.read(4)
            if not head:
                return
            if len(head) < 4:
                raise EOFError("record header cut off")
            (hlen,) = struct.unpack("<I", head)
            header = fh.read(hlen)
            dl = fh.read(4)
            if len(header) < hlen or len(dl) < 4:
                raise EOFError("record cut off")
            (dlen,) = struct.unpack("<I", dl)
            data = fh.read(dlen)
            if len(data) < dlen:
                raise EOFError("record data cut off")
            yield _Ros1Scanner._fields(header), data

    def _walk(self) -> Iterator[tuple[int, int, dict[str, bytes], bytes]]:
        """Yield (group, op, fields, data) of connection and message records, chunks expanded;
        ``group`` counts chunks (records outside chunks form groups of their own)."""
        group = 0
        with open(self.path, "rb") as fh:
            if not fh.readline().startswith(b"#ROSBAG V2.0"):
                raise LogReadError(f"{self.path}: not a ROS 1 bag v2.0")
            try:
                for fields, data in self._records(fh):
                    op = fields.get("op", b"\x00")[0]
                    if op == 0x05:
                        comp = fields.get("compression", b"none").decode()
                        if comp == "bz2":
                            data = bz2.decompress(data)
                        elif comp == "lz4":
                            import lz4.frame

                            data = lz4.frame.decompress(data)
                        group += 1
                        for f2, d2 in self._records(io.BytesIO(data)):
                            yield group, f2.get("op", b"\x00")[0], f2, d2
                    elif op in (0x02, 0x07):
                        group += 1
                        yield group, op, fields, data
            except Exception as exc:
                rep = self.owner.report
                if not rep.truncated:
                    rep.truncated = True
                    rep.bytes_read = fh.tell()
                    self.owner.warn(
                        f"{self.path}: bag is truncated or damaged near byte {fh.tell()} ({exc}); "
                        "read everything before it"
                    )

    def _conn(self, fields: dict[str, bytes], data: bytes) -> ChannelInfo:
        (cid,) = struct.unpack("<I", fields["conn"])
        d = self._fields(data)
        msgtype = d.get("type", b"").decode()
        meta = {"md5sum": d.get("md5sum", b"").decode()}
        if "callerid" in d:
            meta["callerid"] = d["callerid"].decode()
        if "latching" in d:
            meta["latching"] = d["latching"].decode()
        schema = SchemaInfo(msgtype, "ros1msg", d.get("message_definition", b""))
        return ChannelInfo(cid, fields["topic"].decode(), "ros1", schema, meta)

    def channels(self) -> dict[int, ChannelInfo]:
        if self._chans is None:
            self._chans = {}
            for _group, op, fields, data in self._walk():
                if op == 0x07:
                    ch = self._conn(fields, data)
                    self._chans.setdefault(ch.id, ch)
        return self._chans

    def messages(self, topics: set[str] | None, start_ns: int | None, end_ns: int | None) -> Iterator[RawMessage]:
        """Messages in log-time order: each chunk's messages are sorted, and chunks are merged
        with a heap that releases a message once a later chunk starts after it (chunks of a
        recording start in time order, so at most two chunks are held at once)."""
        chans = self.channels()
        heap: list[tuple[int, int, RawMessage]] = []
        order = 0
        group = -1
        pending: list[tuple[int, int, RawMessage]] = []

        def flush() -> Iterator[RawMessage]:
            if not pending:
                return
            low = min(t for t, _, _ in pending)
            while heap and heap[0][0] <= low:
                yield heapq.heappop(heap)[2]
            for item in pending:
                heapq.heappush(heap, item)
            pending.clear()

        for g, op, fields, data in self._walk():
            if op != 0x02:
                continue
            if g != group:
                yield from flush()
                group = g
            (cid,) = struct.unpack("<I", fields["conn"])
            sec, nsec = struct.unpack("<II", fields["time"])
            t = sec * 1_000_000_000 + nsec
            ch = chans.get(cid)
            if ch is None or (topics is not None and ch.topic not in topics):
                continue
            if (start_ns is not None and t < start_ns) or (end_ns is not None and t >= end_ns):
                continue
            pending.append((t, order, RawMessage(ch, t, t, 0, data)))
            order += 1
        yield from flush()
        while heap:
            yield heapq.heappop(heap)[2]

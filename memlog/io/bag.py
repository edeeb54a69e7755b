"""ROS 1 and ROS 2 bags through rosbags, streaming raw message bytes.

A ROS 1 bag whose index is damaged (a truncated recording) is read with a small
sequential record scanner up to the damage; a ROS 2 sqlite3 bag that rosbags cannot open
is read row by row straight from the database (read-only, immutable) up to the damage.
"""

from __future__ import annotations

import bz2
import os
import sqlite3
import struct
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any

from memlog.errors import LogReadError
from memlog.io.base import LogReader
from memlog.io.records import ChannelInfo, RawMessage, SchemaInfo
from memlog.io.types import LogInfo

__all__ = ["Ros1BagLog", "Ros2BagLog"]


def _ros1_name(msgtype: str) -> str:
    parts = msgtype.split("/")
    return f"{parts[0]}/{parts[-1]}" if len(parts) == 3 else msgtype


def _msgdef_text(conn: Any) -> tuple[str, str]:
    md = getattr(conn, "msgdef", None)
    if md is None:
        return "", "msg"
    data = getattr(md, "data", md)
    fmt = getattr(getattr(md, "format", None), "name", "MSG")
    return (data if isinstance(data, str) else str(data)), fmt.lower()


class _RosbagsLog(LogReader):
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


class Ros1BagLog(_RosbagsLog):
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
            text, _ = _msgdef_text(c)
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

    def _walk(self) -> Iterator[tuple[int, dict[str, bytes], bytes]]:
        """Yield (op, fields, data) of connection and message records, chunks expanded."""
        import io

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
                        for f2, d2 in self._records(io.BytesIO(data)):
                            yield f2.get("op", b"\x00")[0], f2, d2
                    elif op in (0x02, 0x07):
                        yield op, fields, data
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
            for op, fields, data in self._walk():
                if op == 0x07:
                    ch = self._conn(fields, data)
                    self._chans.setdefault(ch.id, ch)
        return self._chans

    def messages(self, topics: set[str] | None, start_ns: int | None, end_ns: int | None) -> Iterator[RawMessage]:
        chans = self.channels()
        for op, fields, data in self._walk():
            if op != 0x02:
                continue
            (cid,) = struct.unpack("<I", fields["conn"])
            sec, nsec = struct.unpack("<II", fields["time"])
            t = sec * 1_000_000_000 + nsec
            ch = chans.get(cid)
            if ch is None or (topics is not None and ch.topic not in topics):
                continue
            if (start_ns is not None and t < start_ns) or (end_ns is not None and t >= end_ns):
                continue
            yield RawMessage(ch, t, t, 0, data)


class Ros2BagLog(_RosbagsLog):
    """A ROS 2 bag directory (sqlite3 or mcap storage). Messages keep their CDR bytes."""

    format = "ros2bag"
    profile = "ros2"

    def __init__(self, path: str | os.PathLike[str]) -> None:
        super().__init__(path)
        from rosbags.rosbag2 import Reader

        self._reader: Any = None
        self._chans: dict[int, ChannelInfo] = {}
        self._fallback: list[Path] = []
        try:
            self._reader = Reader(Path(self.path))
            self._reader.open()
            conns = self._reader.connections
        except Exception as exc:
            self._reader = None
            dbs = sorted(Path(self.path).glob("*.db3"))
            if not dbs:
                raise LogReadError(f"{self.path}: ROS 2 bag does not open: {exc}") from exc
            self.warn(f"{self.path}: bag does not open cleanly ({exc}); reading its sqlite3 rows up to the damage")
            self._fallback = dbs
            conns = self._fallback_connections()
        for c in conns:
            self._chans[c.id] = self._channel(c)

    def _channel(self, c: Any) -> ChannelInfo:
        text, fmt = _msgdef_text(c)
        enc = "ros2idl" if fmt == "idl" else "ros2msg"
        if not text.strip():
            from rosbags.typesys import Stores, get_typestore

            try:
                text, _ = get_typestore(Stores.ROS2_HUMBLE).generate_msgdef(c.msgtype, ros_version=2)
            except Exception:
                text = ""
        meta: dict[str, str] = {}
        ext = getattr(c, "ext", None)
        qos = getattr(ext, "offered_qos_profiles", None)
        if isinstance(qos, str) and qos:
            meta["offered_qos_profiles"] = qos
        ser = getattr(ext, "serialization_format", "cdr") or "cdr"
        return ChannelInfo(c.id, c.topic, ser, SchemaInfo(c.msgtype, enc, text.encode()), meta)

    def _fallback_connections(self) -> list[Any]:
        from types import SimpleNamespace

        out: list[Any] = []
        for db in self._fallback:
            con = sqlite3.connect(f"file:{db}?immutable=1", uri=True)
            try:
                for tid, name, typ, ser in con.execute("SELECT id, name, type, serialization_format FROM topics"):
                    if not any(o.topic == name for o in out):
                        out.append(SimpleNamespace(id=tid, topic=name, msgtype=typ, msgdef=None,
                                                   ext=SimpleNamespace(serialization_format=ser)))
            except sqlite3.DatabaseError as exc:
                raise LogReadError(
                    f"{db}: sqlite3 database is damaged ({exc}); sqlite cannot read any of it "
                    "(a bag cut off mid-file loses its page index)"
                ) from exc
            finally:
                con.close()
        return out

    def _iter_messages(
        self, topics: set[str] | None, start_ns: int | None, end_ns: int | None, log_time_order: bool
    ) -> Iterator[RawMessage]:
        if self._reader is None:
            yield from self._fallback_messages(topics, start_ns, end_ns)
        else:
            yield from self._rosbags_messages(topics, start_ns, end_ns)

    def _fallback_messages(
        self, topics: set[str] | None, start_ns: int | None, end_ns: int | None
    ) -> Iterator[RawMessage]:
        by_topic = {c.topic: c for c in self._chans.values()}
        for db in self._fallback:
            con = sqlite3.connect(f"file:{db}?immutable=1", uri=True)
            names = {tid: name for tid, name in con.execute("SELECT id, name FROM topics")}
            last = -1
            try:
                while True:  # rowid pages, so a damaged page stops only the rest
                    rows = con.execute(
                        "SELECT id, topic_id, timestamp, data FROM messages WHERE id > ? ORDER BY id LIMIT 256",
                        (last,),
                    ).fetchall()
                    if not rows:
                        break
                    for rid, tid, ts, data in rows:
                        last = rid
                        name = names.get(tid)
                        if name is None or (topics is not None and name not in topics):
                            continue
                        if (start_ns is not None and ts < start_ns) or (end_ns is not None and ts >= end_ns):
                            continue
                        yield RawMessage(by_topic[name], ts, ts, 0, bytes(data))
            except sqlite3.DatabaseError as exc:
                self.report.truncated = True
                self.warn(f"{db}: database damaged after message row {last} ({exc}); read everything before it")
            finally:
                con.close()

"""ROS 2 bags (sqlite3 or mcap storage) through rosbags, streaming raw CDR bytes.

A sqlite3 bag that rosbags cannot open is read row by row straight from the database
(read-only, immutable) up to the damage.
"""

from __future__ import annotations

import os
import sqlite3
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from memlog.errors import LogReadError
from memlog.io._rosbags import RosbagsLog, msgdef_text
from memlog.io.records import ChannelInfo, RawMessage, SchemaInfo

__all__ = ["Ros2BagLog"]


class Ros2BagLog(RosbagsLog):
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
        text, fmt = msgdef_text(c)
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

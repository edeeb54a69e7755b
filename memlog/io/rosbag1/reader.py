"""ROS 1 bags (v2.0), streaming raw message bytes (ROS 1 serialization).

Messages are always read from the data: a record scanner walks the chunks in file order,
decompresses each to no more than the size it declares, and merges their messages back into
log-time order. The bag's index (read with rosbags) gives message counts, per-topic times and the
connection definitions, but only when it proves itself against a walk over the file's record
headers (chunk positions, connection and chunk counts in the bag header, counts per chunk); an
index that does not is reported and the connections come from the data. Damage inside the file
is skipped to the next chunk the index or the walk knows; an interrupted recording (no index, a
cut, a zero-filled tail) is read up to the damage and reported.
"""

from __future__ import annotations

import os
import struct
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

from memlog.io._damage import check_regular_file, damage_place, decompress, merge_groups
from memlog.io._rosbags import msgdef_text
from memlog.io.base import LogReader
from memlog.io.records import ChannelInfo, RawMessage, SchemaInfo
from memlog.io.types import LogInfo

__all__ = ["Ros1BagLog"]

_MAGIC = b"#ROSBAG V2.0\n"
_OP_MSG, _OP_BAG, _OP_IDX, _OP_CHUNK, _OP_INFO, _OP_CONN = 0x02, 0x03, 0x04, 0x05, 0x06, 0x07
_MAX_HEADER = 1 << 24  # a record header (field list) larger than this is damage


def _ros1_name(msgtype: str) -> str:
    parts = msgtype.split("/")
    return f"{parts[0]}/{parts[-1]}" if len(parts) == 3 else msgtype


class _Bad(Exception):
    """A record that cannot be what it claims, at byte ``pos``."""

    def __init__(self, pos: int, reason: str) -> None:
        super().__init__(reason)
        self.pos, self.reason = pos, reason


def _kv(block: bytes, pos: int) -> dict[str, bytes]:
    """``name=value`` fields, each prefixed by its uint32 length (record headers and connection data)."""
    out: dict[str, bytes] = {}
    at = 0
    while at < len(block):
        if at + 4 > len(block):
            raise _Bad(pos, "record header ends inside a field length")
        (n,) = struct.unpack_from("<I", block, at)
        at += 4
        if at + n > len(block) or b"=" not in block[at : at + n]:
            raise _Bad(pos, "record header field is damaged")
        key, _, val = block[at : at + n].partition(b"=")
        out[key.decode(errors="replace")] = val
        at += n
    return out


def _fields(header: bytes, pos: int) -> dict[str, bytes]:
    out = _kv(header, pos)
    if "op" not in out or len(out["op"]) != 1:
        raise _Bad(pos, "record has no op field")
    return out


def _u32(fields: dict[str, bytes], key: str, pos: int) -> int:
    v = fields.get(key)
    if v is None or len(v) != 4:
        raise _Bad(pos, f"record field {key!r} is missing or damaged")
    return int(struct.unpack("<I", v)[0])


def _time(fields: dict[str, bytes], key: str, pos: int) -> int:
    v = fields.get(key)
    if v is None or len(v) != 8:
        raise _Bad(pos, f"record field {key!r} is missing or damaged")
    sec, nsec = struct.unpack("<II", v)
    return int(sec) * 1_000_000_000 + int(nsec)


@dataclass
class _Skeleton:
    """What the record headers of the file say (bodies skipped)."""

    header: dict[str, bytes] | None = None
    chunks: list[int] = field(default_factory=list)
    index_start: int | None = None
    index_conns: int = 0
    chunk_infos: int = 0
    damage: _Bad | None = None


class _Ros1Scanner:
    """Sequential ROS 1 bag v2.0 record reader over one open file."""

    def __init__(self, path: str, owner: LogReader, size: int) -> None:
        self.path, self.owner, self.size = path, owner, size
        self.resync: list[int] = []  # chunk positions known from the index, to skip damage with
        self._chans: dict[int, ChannelInfo] | None = None

    @staticmethod
    def _record(buf: IO[bytes] | _BytesReader, pos: int, end: int, skip_data: bool = False) -> tuple[dict[str, bytes], bytes, int]:
        """The record at ``pos`` (``buf`` positioned there): fields, data (b"" when skipped), next pos."""
        head = buf.read(4)
        if len(head) < 4:
            raise _Bad(pos, "the file ends inside a record")
        (hlen,) = struct.unpack("<I", head)
        if hlen == 0 or hlen > _MAX_HEADER or pos + 8 + hlen > end:
            raise _Bad(pos, f"no valid record (header length {hlen})")
        header = buf.read(hlen)
        dl = buf.read(4)
        if len(header) < hlen or len(dl) < 4:
            raise _Bad(pos, "the file ends inside a record")
        (dlen,) = struct.unpack("<I", dl)
        nxt = pos + 8 + hlen + dlen
        if nxt > end:
            raise _Bad(pos, f"record claims {dlen} data bytes, past the end")
        fields = _fields(header, pos)
        if skip_data:
            buf.seek(dlen, os.SEEK_CUR)
            return fields, b"", nxt
        data = buf.read(dlen)
        if len(data) < dlen:
            raise _Bad(pos, "the file ends inside a record")
        return fields, data, nxt

    def skeleton(self) -> _Skeleton:
        """Walk the record headers: bag header, chunks, index section."""
        sk = _Skeleton()
        with open(self.path, "rb") as fh:
            if fh.read(len(_MAGIC)) != _MAGIC:
                sk.damage = _Bad(0, "not a ROS 1 bag v2.0")
                return sk
            pos = len(_MAGIC)
            try:
                while pos < self.size:
                    fh.seek(pos)
                    fields, _, nxt = self._record(fh, pos, self.size, skip_data=True)
                    op = fields["op"][0]
                    if op == _OP_BAG:
                        sk.header = fields
                    elif op == _OP_CHUNK:
                        sk.chunks.append(pos)
                    elif op in (_OP_CONN, _OP_INFO):
                        if sk.index_start is None:
                            sk.index_start = pos
                        if op == _OP_CONN:
                            sk.index_conns += 1
                        else:
                            sk.chunk_infos += 1
                    pos = nxt
                if sk.header is None:
                    raise _Bad(pos, "the bag header record is missing")
            except _Bad as exc:
                sk.damage = exc
        return sk

    def _chunk_records(self, fields: dict[str, bytes], data: bytes, pos: int) -> Iterator[tuple[dict[str, bytes], bytes]]:
        comp = fields.get("compression", b"none").decode(errors="replace")
        size = _u32(fields, "size", pos)
        if comp == "none" and size != len(data):
            self.owner.report.index_damaged = True
            self.owner.warn(f"{self.path}: chunk at byte {pos} declares {size} bytes, holds {len(data)}; "
                            "reading what it holds")
        raw = decompress(comp, data, size) if comp != "none" else data
        buf = _BytesReader(raw)
        at = 0
        while at < len(raw):
            f2, d2, at = self._record(buf, at, len(raw))
            yield f2, d2

    def walk(self, chunks: set[int] | None = None) -> Iterator[tuple[int, dict[str, bytes], bytes]]:
        """(chunk number, fields, data) of message and connection records, chunks expanded, in
        file order (records outside chunks get chunk number -1). Damage is reported; the walk
        goes on at the next chunk the index knows, or stops."""
        rep = self.owner.report
        with open(self.path, "rb") as fh:
            pos = len(_MAGIC)
            n_chunk = 0
            while pos < self.size:
                fh.seek(pos)
                try:
                    fields, data, nxt = self._record(fh, pos, self.size)
                except _Bad as exc:
                    later = [p for p in self.resync if p > pos]
                    if not rep.truncated:
                        rep.truncated = True
                        rep.bytes_read = exc.pos
                        left = f"; going on at the next chunk (byte {later[0]})" if later else "; read everything before it"
                        self.owner.warn(f"{self.path}: bag is truncated or damaged {damage_place(fh, exc.pos, self.size)}"
                                        f" ({exc.reason}){left}")
                    if not later:
                        return
                    pos = later[0]
                    continue
                op = fields["op"][0]
                if op == _OP_CHUNK and chunks is not None and pos not in chunks:
                    pass  # the trusted index says it holds none of the wanted connections
                elif op == _OP_CHUNK:
                    n_chunk += 1
                    try:
                        for f2, d2 in self._chunk_records(fields, data, pos):
                            yield n_chunk, f2, d2
                    except (_Bad, ValueError, OSError, EOFError) as exc:
                        rep.skipped_chunks += 1
                        why = exc.reason if isinstance(exc, _Bad) else f"{type(exc).__name__}: {exc}"
                        self.owner.warn(f"{self.path}: chunk at byte {pos} is damaged ({why}); skipped the rest of it")
                elif op in (_OP_MSG, _OP_CONN):
                    yield -1, fields, data
                pos = nxt

    def conn(self, fields: dict[str, bytes], data: bytes, pos: int = 0) -> ChannelInfo:
        cid = _u32(fields, "conn", pos)
        topic = fields.get("topic")
        if topic is None:
            raise _Bad(pos, "connection record has no topic")
        d = _kv(data, pos)
        msgtype = d.get("type", b"").decode(errors="replace")
        meta = {"md5sum": d.get("md5sum", b"").decode(errors="replace")}
        if "callerid" in d:
            meta["callerid"] = d["callerid"].decode(errors="replace")
        if "latching" in d:
            meta["latching"] = d["latching"].decode(errors="replace")
        schema = SchemaInfo(msgtype, "ros1msg", d.get("message_definition", b""))
        return ChannelInfo(cid, topic.decode(errors="replace"), "ros1", schema, meta)

    def channels(self) -> dict[int, ChannelInfo]:
        """Connections found in the data (a full pass; used when the index is not trusted)."""
        if self._chans is None:
            self._chans = {}
            for _n, fields, data in self.walk():
                if fields["op"][0] == _OP_CONN:
                    try:
                        ch = self.conn(fields, data)
                    except _Bad:
                        continue
                    self._chans.setdefault(ch.id, ch)
        return self._chans

    def messages(self, chans: dict[int, ChannelInfo], topics: set[str] | None, start_ns: int | None,
                 end_ns: int | None, chunks: set[int] | None = None) -> Iterator[RawMessage]:
        """Messages in log-time order (chunks merged)."""
        rep = self.owner.report

        def groups() -> Iterator[list[tuple[int, RawMessage]]]:
            group: list[tuple[int, RawMessage]] = []
            current = None
            for n, fields, data in self.walk(chunks):
                if n != current or n == -1:
                    yield group
                    group, current = [], n
                op = fields["op"][0]
                if op == _OP_CONN:
                    if self._chans is None:  # trusted index: the data's connection record wins
                        try:
                            ch = self.conn(fields, data)
                        except _Bad:
                            continue
                        old = chans.get(ch.id)
                        if old is not None and (old.topic, old.msgtype, old.metadata.get("md5sum")) != (
                                ch.topic, ch.msgtype, ch.metadata.get("md5sum")):
                            rep.index_damaged = True
                            self.owner.warn(f"{self.path}: the index describes connection {ch.id} as {old.topic!r} "
                                            f"({old.msgtype}), the data as {ch.topic!r} ({ch.msgtype}): using the data's")
                            chans[ch.id] = ch
                        elif old is None:
                            chans[ch.id] = ch
                    continue
                try:
                    cid = _u32(fields, "conn", 0)
                    t = _time(fields, "time", 0)
                except _Bad as exc:
                    rep.bad_messages += 1
                    self.owner.warn(f"{self.path}: message record in chunk {n} is damaged ({exc.reason}); skipped")
                    continue
                found = chans.get(cid)
                if found is None:
                    rep.bad_messages += 1
                    self.owner.warn(f"{self.path}: message on unknown connection {cid} at log time {t}: skipped")
                    continue
                if (topics is not None and found.topic not in topics) or (start_ns is not None and t < start_ns) or (
                        end_ns is not None and t >= end_ns):
                    continue
                group.append((t, RawMessage(found, t, t, 0, data)))
            yield group

        yield from merge_groups(groups())


class _BytesReader:
    """The read/seek subset of a file over bytes, without copying them into a BytesIO."""

    def __init__(self, data: bytes) -> None:
        self._view = memoryview(data)
        self._at = 0

    def read(self, n: int) -> bytes:
        out = bytes(self._view[self._at : self._at + n])
        self._at += len(out)
        return out

    def seek(self, n: int, whence: int = 0) -> int:
        self._at = n if whence == 0 else self._at + n
        return self._at


class Ros1BagLog(LogReader):
    """A ROS 1 bag (v2.0). Messages keep their ROS 1 serialization."""

    format = "ros1bag"
    profile = "ros1"

    def __init__(self, path: str | os.PathLike[str]) -> None:
        super().__init__(path)
        size = check_regular_file(self.path).st_size
        self._scan = _Ros1Scanner(self.path, self, size)
        self._reader: Any = None
        self._chans: dict[int, ChannelInfo] = {}
        sk = self._scan.skeleton()
        problems = self._open_index(sk)
        known = sorted(ci.pos for ci in getattr(self._reader, "chunk_infos", []) if isinstance(ci.pos, int))
        self._scan.resync = sorted(set(sk.chunks) | set(known))
        if sk.damage is not None:
            self.report.truncated = True
            self.report.bytes_read = sk.damage.pos
            later = [p for p in self._scan.resync if p > sk.damage.pos]
            self.warn(f"{self.path}: bag is truncated or damaged {damage_place_s(self, sk.damage.pos)} "
                      f"({sk.damage.reason}); the index is not used: reading the records before it"
                      + (f" and the {len(later)} chunk(s) the index knows after it" if later else ""))
        elif sk.index_start is None:
            self.report.truncated = True
            self.report.bytes_read = size
            self.warn(f"{self.path}: bag has no index section (an interrupted recording?): reading its records")
        elif problems is not None:
            self.report.index_damaged = True
            self.warn(f"{self.path}: bag index unusable ({problems}); reading the records themselves")
        if problems is None and sk.damage is None and sk.index_start is not None and self._reader is not None:
            for c in self._reader.connections:
                self._chans[c.id] = self._channel(c)
            return
        if self._reader is not None:
            self._reader.close()
            self._reader = None
        self._chans = self._scan.channels()

    def _open_index(self, sk: _Skeleton) -> str | None:
        """Open the index with rosbags; None when it matches the walk, else why not."""
        from rosbags.rosbag1 import Reader

        try:
            self._reader = Reader(Path(self.path))
            self._reader.open()
        except Exception as exc:  # noqa: BLE001 - rosbags raises several kinds on a damaged index
            self._reader = None
            return f"{type(exc).__name__}: {exc}"
        hdr = sk.header or {}
        try:
            index_pos = struct.unpack("<Q", hdr.get("index_pos", b""))[0]
            conn_count = _u32(hdr, "conn_count", 0)
            chunk_count = _u32(hdr, "chunk_count", 0)
        except (struct.error, _Bad):
            return "the bag header's fields are damaged"
        infos = getattr(self._reader, "chunk_infos", [])
        problems = []
        if conn_count != sk.index_conns or chunk_count != sk.chunk_infos:
            problems.append(f"the bag header counts {conn_count} connections and {chunk_count} chunks, the index "
                            f"section holds {sk.index_conns} and {sk.chunk_infos}")
        if sk.chunks and index_pos != sk.index_start:
            problems.append(f"the bag header puts the index at byte {index_pos}, it starts at {sk.index_start}")
        if sorted(ci.pos for ci in infos) != sk.chunks:
            problems.append(f"the index lists {len(infos)} chunks, the file holds {len(sk.chunks)}")
        indexed = sum(len(v) for v in getattr(self._reader, "indexes", {}).values())
        if sum(sum(ci.connection_counts.values()) for ci in infos) != indexed:
            problems.append("the chunk infos and the index data disagree on message counts")
        return "; ".join(problems) or None

    @staticmethod
    def _channel(c: Any) -> ChannelInfo:
        text, _ = msgdef_text(c)
        meta = {"md5sum": str(c.digest)}
        ext = getattr(c, "ext", None)
        if ext is not None and getattr(ext, "callerid", None):
            meta["callerid"] = str(ext.callerid)
        if ext is not None and getattr(ext, "latching", None) is not None:
            meta["latching"] = str(int(ext.latching))
        schema = SchemaInfo(_ros1_name(c.msgtype), "ros1msg", text.encode())
        return ChannelInfo(c.id, c.topic, "ros1", schema, meta)

    def close(self) -> None:
        if self._reader is not None:
            self._reader.close()
            self._reader = None

    def channels(self) -> list[ChannelInfo]:
        return list(self._chans.values())

    def message_counts(self) -> dict[int, int] | None:
        if self._reader is None:
            return None
        return {c.id: c.msgcount for c in self._reader.connections}

    def topic_times(self, topic: str) -> Any:
        """Log times of ``topic`` from the bag's index data records (no chunk is read)."""
        import numpy as np

        if self._reader is None:
            return None
        times = [e.time for c in self._reader.connections if c.topic == topic for e in self._reader.indexes.get(c.id, ())]
        return np.sort(np.asarray(times, dtype=np.int64))

    def _fill_time_range(self, info: LogInfo) -> None:
        if self._reader is not None and self._reader.message_count:
            info.start_ns, info.end_ns = self._reader.start_time, self._reader.end_time - 1

    def _iter_messages(
        self, topics: set[str] | None, start_ns: int | None, end_ns: int | None, log_time_order: bool
    ) -> Iterator[RawMessage]:
        full = self._reader is not None and start_ns is None and end_ns is None
        seen: list[tuple[int, int]] = []
        chunks = None
        if self._reader is not None and (topics is not None or start_ns is not None or end_ns is not None):
            ids = {c.id for c in self._chans.values() if topics is None or c.topic in topics}
            chunks = {ci.pos for ci in self._reader.chunk_infos if ids & set(ci.connection_counts)
                      and (start_ns is None or ci.end_time > start_ns) and (end_ns is None or ci.start_time < end_ns)}
        for m in self._scan.messages(self._chans, topics, start_ns, end_ns, chunks):
            if full:
                seen.append((m.channel.id, m.log_time))
            yield m
        if full and self.report.ok:
            self._check_index_times(seen, topics)

    def _check_index_times(self, seen: list[tuple[int, int]], topics: set[str] | None) -> None:
        """After a full read: the index's (connection, time) entries must be the data's."""
        from collections import Counter

        ids = {c.id for c in self._chans.values() if topics is None or c.topic in topics}
        index = Counter((cid, e.time) for cid, entries in self._reader.indexes.items() if cid in ids for e in entries)
        if index != Counter(seen):
            self.report.index_damaged = True
            self.warn(f"{self.path}: the bag's index data records do not match its messages "
                      f"({sum((index - Counter(seen)).values())} index entries have no such message); "
                      "the messages were read from the data")


def damage_place_s(log: Ros1BagLog, pos: int) -> str:
    with open(log.path, "rb") as fh:
        return damage_place(fh, pos, os.path.getsize(log.path))

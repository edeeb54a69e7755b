"""ROS 1 bags (v2.0), streaming raw message bytes (ROS 1 serialization).

Messages are always read from the data: a record scanner walks the chunks in file order,
decompresses each to no more than the size it declares, and merges their messages back into
log-time order. The bag's index (read with rosbags) gives message counts, per-topic times and the
connection definitions, but only when it proves itself against a walk over the file's record
headers (chunk positions, connection and chunk counts in the bag header, counts per chunk); an
index that does not is reported and the data is **scanned once** when the bag is opened: the
connections, every chunk's time range, the message counts and the frame tables
(:mod:`memlog.io.frame_table`) then come from that scan, kept for the next reader of the same
file (:mod:`memlog.io._opened`), and later reads go only to the chunks a time window needs.
Damage inside the file is skipped to the next chunk the index or the walk knows; an interrupted
recording (no index, a cut, a zero-filled tail) is read up to the damage and reported.
"""

from __future__ import annotations

import copy
import os
import struct
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import numpy as np

from memlog.io._damage import check_regular_file, damage_place, decompress, merge_groups
from memlog.io.spool import ChunkSpool
from memlog.io._opened import counted_scan, file_key, holder, learned, release
from memlog.io._rosbags import msgdef_text
from memlog.io.base import LogReader
from memlog.io.camera import camera_kind
from memlog.io.frame_table import FrameTable
from memlog.io.records import ChannelInfo, RawMessage, ReadReport, SchemaInfo
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

    def _chunk_data(self, fields: dict[str, bytes], data: bytes, pos: int) -> bytes:
        """The uncompressed records of the chunk record at ``pos``."""
        comp = fields.get("compression", b"none").decode(errors="replace")
        size = _u32(fields, "size", pos)
        if comp == "none" and size != len(data):
            self.owner.report.index_damaged = True
            self.owner.warn(f"{self.path}: chunk at byte {pos} declares {size} bytes, holds {len(data)}; "
                            "reading what it holds")
        return decompress(comp, data, size) if comp != "none" else data

    def _expand_raw(self, pos: int, raw: bytes) -> Iterator[tuple[int, int, dict[str, bytes], bytes]]:
        """(container, offset, fields, data) of the records of a chunk's uncompressed records ``raw``."""
        buf = _BytesReader(raw)
        at = 0
        while at < len(raw):
            f2, d2, nxt = self._record(buf, at, len(raw))
            yield pos, at, f2, d2
            at = nxt

    def walk(self, chunks: set[int] | None = None) -> Iterator[tuple[int, int, dict[str, bytes], bytes]]:
        """(container, offset, fields, data) of message and connection records, chunks expanded,
        in file order: the container is the chunk's file position and the offset the record's
        position in its uncompressed data (a record outside chunks: its own position, offset -1).
        ``chunks``: read only the records at these positions (found by the index or the scan: no
        other byte of the file is read); else every record from the start. Damage is reported;
        the walk goes on at the next chunk the index knows, or stops."""
        rep = self.owner.report
        with open(self.path, "rb") as fh:
            if chunks is not None:
                spool = self.owner.spool()
                for pos in sorted(chunks):
                    kept = spool.get(pos) if spool is not None else None
                    if isinstance(kept, tuple):  # read by an earlier pass of this job (memlog.io.spool)
                        yield from self._expand_raw(pos, kept[0])
                        continue
                    fh.seek(pos)
                    try:
                        fields, data, _ = self._record(fh, pos, self.size)
                    except _Bad as exc:
                        if rep.count("skipped_chunks", pos):
                            self.owner.warn(f"{self.path}: record at byte {pos} is damaged ({exc.reason}); skipped")
                        continue
                    yield from self._expand(pos, fields, data, spool)
                return
            pos = len(_MAGIC)
            while pos < self.size:
                fh.seek(pos)
                try:
                    fields, data, nxt = self._record(fh, pos, self.size)
                except _Bad as exc:
                    later = [p for p in self.resync if p > pos]
                    rep.truncated = True
                    rep.bytes_read = exc.pos if rep.bytes_read is None else min(rep.bytes_read, exc.pos)
                    left = f"; going on at the next chunk (byte {later[0]})" if later else "; read everything before it"
                    self.owner.warn(f"{self.path}: bag is truncated or damaged {damage_place(fh, exc.pos, self.size)}"
                                    f" ({exc.reason}){left}")
                    if not later:
                        return
                    pos = later[0]
                    continue
                yield from self._expand(pos, fields, data, self.owner.spool())
                pos = nxt

    def _expand(self, pos: int, fields: dict[str, bytes], data: bytes, spool: ChunkSpool | None = None
                ) -> Iterator[tuple[int, int, dict[str, bytes], bytes]]:
        """The message and connection records of the record at ``pos`` (a chunk's, expanded; a chunk
        read whole is kept in ``spool``)."""
        op = fields["op"][0]
        if op == _OP_CHUNK:
            try:
                raw = self._chunk_data(fields, data, pos)
                yield from self._expand_raw(pos, raw)
                if spool is not None:
                    spool.put(pos, raw, False)  # (ROS 1 bags have no checksums)
            except (_Bad, ValueError, OSError, EOFError) as exc:
                self.owner.report.count("skipped_chunks", pos)
                why = exc.reason if isinstance(exc, _Bad) else f"{type(exc).__name__}: {exc}"
                self.owner.warn(f"{self.path}: chunk at byte {pos} is damaged ({why}); skipped the rest of it")
        elif op in (_OP_MSG, _OP_CONN):
            yield pos, -1, fields, data

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

    def messages(self, chans: dict[int, ChannelInfo], topics: set[str] | None, start_ns: int | None,
                 end_ns: int | None, chunks: set[int] | None = None, *,
                 correct_index: bool = True) -> Iterator[RawMessage]:
        """Messages in log-time order (chunks merged). ``correct_index``: the connections come
        from the index, and a connection record in the data that says otherwise wins (reported)."""
        rep = self.owner.report

        def groups() -> Iterator[list[tuple[int, RawMessage]]]:
            group: list[tuple[int, RawMessage]] = []
            current = None
            for container, at, fields, data in self.walk(chunks):
                if container != current or at < 0:
                    yield group
                    group, current = [], container
                op = fields["op"][0]
                if op == _OP_CONN:
                    if correct_index:  # trusted index: the data's connection record wins
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
                    if rep.count("bad_messages", (container, at)):
                        self.owner.warn(f"{self.path}: message record at byte {at} of the chunk at byte {container} "
                                        f"is damaged ({exc.reason}); skipped")
                    continue
                found = chans.get(cid)
                if found is None:
                    if rep.count("bad_messages", (container, at)):
                        self.owner.warn(f"{self.path}: message on unknown connection {cid} at log time {t}: skipped")
                    continue
                if (topics is not None and found.topic not in topics) or (start_ns is not None and t < start_ns) or (
                        end_ns is not None and t >= end_ns):
                    continue
                group.append((t, RawMessage(found, t, t, 0, data, (container, max(at, 0)))))
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


@dataclass
class _Learned:
    """What opening (and scanning) one bag learned; shared by its readers in a process."""

    said: set[str] = field(default_factory=set)
    chans: dict[int, ChannelInfo] = field(default_factory=dict)
    trusted: bool = False  # the bag's index proved itself and drives the reads
    resync: list[int] = field(default_factory=list)
    counts: dict[int, int] | None = None
    # chunk position -> (first, last log time, connection ids): the index's or the scan's
    chunks: dict[int, tuple[int, int, frozenset[int]]] = field(default_factory=dict)
    entries: dict[int, list[tuple[int, int, int]]] = field(default_factory=dict)  # index: conn -> (time, chunk, offset)
    ranges: dict[int, list[int]] = field(default_factory=dict)  # log-time range per connection
    time_range: tuple[int, int] | None = None
    tables: dict[str, FrameTable] = field(default_factory=dict)
    report: ReadReport | None = None

    @property
    def scanned(self) -> bool:
        """Whether the records were scanned to learn this (kept on disk for other processes)."""
        return not self.trusted

    def close(self) -> None:
        pass


class Ros1BagLog(LogReader):
    """A ROS 1 bag (v2.0). Messages keep their ROS 1 serialization."""

    format = "ros1bag"
    profile = "ros1"

    def __init__(self, path: str | os.PathLike[str]) -> None:
        super().__init__(path)
        size = check_regular_file(self.path).st_size
        self._scan = _Ros1Scanner(self.path, self, size)
        self._key: Any = None
        key = file_key("ros1bag", self.path)
        self._holder = holder()
        self._l, new = learned(key, self._learn)
        self._key = key
        self._said = self._l.said
        self._scan.resync = self._l.resync
        if not new and self._l.report is not None:
            self._learned_before(self._l.report)

    def _learn(self) -> _Learned:
        self._l = lrn = _Learned()
        self._said = lrn.said
        sk = self._scan.skeleton()
        reader, problems = self._open_index(sk)
        known = sorted(ci.pos for ci in getattr(reader, "chunk_infos", []) if isinstance(ci.pos, int))
        lrn.resync = self._scan.resync = sorted(set(sk.chunks) | set(known))
        size = self._scan.size
        if sk.damage is not None:
            self.report.truncated = True
            self.report.bytes_read = sk.damage.pos
            later = [p for p in lrn.resync if p > sk.damage.pos]
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
        try:
            if problems is None and sk.damage is None and sk.index_start is not None and reader is not None:
                self._from_index(reader)
            else:
                self._scan_data()
        finally:
            if reader is not None:
                reader.close()
        lrn.report = copy.deepcopy(self.report)
        return lrn

    def _from_index(self, reader: Any) -> None:
        """What the trusted index says: connections, counts, chunks and every message's place."""
        lrn = self._l
        lrn.trusted = True
        for c in reader.connections:
            lrn.chans[c.id] = self._channel(c)
        lrn.counts = {c.id: c.msgcount for c in reader.connections}
        lrn.chunks = {ci.pos: (ci.start_time, ci.end_time, frozenset(ci.connection_counts))
                      for ci in reader.chunk_infos}
        lrn.entries = {cid: [(e.time, e.chunk_pos, e.offset) for e in entries]
                       for cid, entries in reader.indexes.items()}
        if reader.message_count:
            lrn.time_range = (reader.start_time, reader.end_time - 1)
        for cid, entries in lrn.entries.items():
            if entries:
                times = [t for t, _, _ in entries]
                lrn.ranges[cid] = [min(times), max(times)]
        by_topic: dict[str, list[tuple[int, int, int]]] = {}
        for cid, ch in lrn.chans.items():
            if camera_kind(ch.msgtype):
                by_topic.setdefault(ch.topic, []).extend(lrn.entries.get(cid, []))
        lrn.tables = {t: _table(e) for t, e in by_topic.items()}

    def _scan_data(self) -> None:
        """The one scan of an unindexed or damaged bag: connections, every readable message's
        place (frame tables), counts and the time range of every chunk."""
        counted_scan(os.path.realpath(self.path))
        lrn = self._l
        counts: dict[int, int] = {}
        by_topic: dict[str, list[tuple[int, int, int]]] = {}
        for container, at, fields, data in self._scan.walk():
            op = fields["op"][0]
            if op == _OP_CONN:
                try:
                    ch = self._scan.conn(fields, data)
                except _Bad:
                    continue
                lrn.chans.setdefault(ch.id, ch)
                continue
            try:
                cid = _u32(fields, "conn", 0)
                t = _time(fields, "time", 0)
            except _Bad:
                continue  # reported when the messages are read
            known = lrn.chans.get(cid)
            if known is None:
                continue
            counts[cid] = counts.get(cid, 0) + 1
            r = lrn.ranges.setdefault(cid, [t, t])
            r[0], r[1] = min(r[0], t), max(r[1], t)
            lo, hi, ids = lrn.chunks.get(container, (t, t, frozenset()))
            lrn.chunks[container] = (min(lo, t), max(hi, t + 1), ids | {cid})
            if camera_kind(known.msgtype):
                by_topic.setdefault(known.topic, []).append((t, container, max(at, 0)))
        lrn.counts = counts
        if lrn.ranges:
            lrn.time_range = (min(r[0] for r in lrn.ranges.values()), max(r[1] for r in lrn.ranges.values()))
        for ch in lrn.chans.values():
            if camera_kind(ch.msgtype):
                by_topic.setdefault(ch.topic, [])
        lrn.tables = {t: _table(e) for t, e in by_topic.items()}

    def _open_index(self, sk: _Skeleton) -> tuple[Any, str | None]:
        """The index opened with rosbags (None when it does not open) and None when it matches
        the walk, else why not."""
        from rosbags.rosbag1 import Reader

        try:
            reader = Reader(Path(self.path))
            reader.open()
        except Exception as exc:  # noqa: BLE001 - rosbags raises several kinds on a damaged index
            return None, f"{type(exc).__name__}: {exc}"
        hdr = sk.header or {}
        try:
            index_pos = struct.unpack("<Q", hdr.get("index_pos", b""))[0]
            conn_count = _u32(hdr, "conn_count", 0)
            chunk_count = _u32(hdr, "chunk_count", 0)
        except (struct.error, _Bad):
            return reader, "the bag header's fields are damaged"
        infos = getattr(reader, "chunk_infos", [])
        problems = []
        if conn_count != sk.index_conns or chunk_count != sk.chunk_infos:
            problems.append(f"the bag header counts {conn_count} connections and {chunk_count} chunks, the index "
                            f"section holds {sk.index_conns} and {sk.chunk_infos}")
        if sk.chunks and index_pos != sk.index_start:
            problems.append(f"the bag header puts the index at byte {index_pos}, it starts at {sk.index_start}")
        if sorted(ci.pos for ci in infos) != sk.chunks:
            problems.append(f"the index lists {len(infos)} chunks, the file holds {len(sk.chunks)}")
        indexed = sum(len(v) for v in getattr(reader, "indexes", {}).values())
        if sum(sum(ci.connection_counts.values()) for ci in infos) != indexed:
            problems.append("the chunk infos and the index data disagree on message counts")
        return reader, "; ".join(problems) or None

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
        if self._key is not None:
            release(self._key, self._holder)
            self._key = None

    def channels(self) -> list[ChannelInfo]:
        return list(self._l.chans.values())

    def message_counts(self) -> dict[int, int] | None:
        return dict(self._l.counts) if self._l.counts is not None else None

    def frame_table(self, topic: str) -> FrameTable:
        return self._l.tables.setdefault(topic, _table([]))

    def _fill_time_range(self, info: LogInfo) -> None:
        lrn = self._l
        if lrn.time_range is not None:
            info.start_ns, info.end_ns = lrn.time_range
        self._widen_topic_ranges(info, lrn.ranges)

    def _iter_messages(
        self, topics: set[str] | None, start_ns: int | None, end_ns: int | None, log_time_order: bool
    ) -> Iterator[RawMessage]:
        lrn = self._l
        full = lrn.trusted and start_ns is None and end_ns is None
        seen: list[tuple[int, int]] = []
        chunks = None
        if topics is not None or start_ns is not None or end_ns is not None:
            ids = {c.id for c in lrn.chans.values() if topics is None or c.topic in topics}
            chunks = {pos for pos, (lo, hi, conns) in lrn.chunks.items() if ids & conns
                      and (start_ns is None or hi > start_ns) and (end_ns is None or lo < end_ns)}
        for m in self._scan.messages(lrn.chans, topics, start_ns, end_ns, chunks, correct_index=lrn.trusted):
            if full:
                seen.append((m.channel.id, m.log_time))
            yield m
        if full and self.report.ok:
            self._check_index_times(seen, topics)

    def _check_index_times(self, seen: list[tuple[int, int]], topics: set[str] | None) -> None:
        """After a full read: the index's (connection, time) entries must be the data's."""
        from collections import Counter

        lrn = self._l
        ids = {c.id for c in lrn.chans.values() if topics is None or c.topic in topics}
        index = Counter((cid, t) for cid, entries in lrn.entries.items() if cid in ids for t, _, _ in entries)
        if index != Counter(seen):
            self.report.index_damaged = True
            self.warn(f"{self.path}: the bag's index data records do not match its messages "
                      f"({sum((index - Counter(seen)).values())} index entries have no such message); "
                      "the messages were read from the data")


def _table(entries: list[tuple[int, int, int]]) -> FrameTable:
    a = np.asarray(entries, dtype=np.int64).reshape(-1, 3)
    return FrameTable(a[:, 0], a[:, 1], a[:, 2])


def damage_place_s(log: Ros1BagLog, pos: int) -> str:
    with open(log.path, "rb") as fh:
        return damage_place(fh, pos, os.path.getsize(log.path))

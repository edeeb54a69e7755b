"""MCAP reader: any profile, streamed chunk by chunk, robust to damage.

The data is the truth; the summary (index) is a shortcut taken only when it proves itself:

* the summary section is read with its CRC (footer ``summary_crc``); one that fails it or does
  not parse is ignored;
* its chunk index must list exactly the chunks a walk over the data section's record headers
  finds (offsets only; the walk reads each record's 9-byte header and skips the body);
* every chunk is read at its offset with the length its own record header gives, decompressed
  to no more than the size it declares, and checked against its CRC.

When the index passes, chunks are read through it (filtered by channel and time) and merged in
log-time order, and the frame tables (:mod:`memlog.io.frame_table`) come from its message
indexes (checked: channel, count, times and offsets within their chunk). When it does not, or
there is no summary (a cut or unfinished recording), the data is **scanned once** when the log
is opened, up to the damage (plus any intact chunk the index knows past it): every chunk is
decompressed and checked, and the scan keeps where each readable chunk and top-level message
lies, the channels, the message counts and the frame tables; every later read seeks to the
chunks it needs (:mod:`memlog.io._opened` keeps the scan for the next reader of the same file).
A chunk whose CRC does not match is reported and skipped; the rest is read. A zero-filled tail
is named where the zeros start.
"""

from __future__ import annotations

import copy
import heapq
import logging
import os
import struct
from collections import OrderedDict
from collections.abc import Iterator
from collections.abc import Set as AbstractSet
from dataclasses import dataclass, field
from typing import IO, Any

from mcap.records import Attachment as McapAttachment
from mcap.records import Channel, Header, Message, Metadata, Schema
from mcap.summary import Summary

import numpy as np

from memlog.errors import LogReadError
from memlog.io._damage import MAX_CHUNK_BYTES, check_regular_file, damage_place
from memlog.io._opened import file_key, holder, learned, release
from memlog.io.base import LogReader
from memlog.io.camera import camera_kind
from memlog.io.frame_table import FrameTable
from memlog.io.mcap.records import (
    CHUNK_HEAD,
    KNOWN_OPS,
    MAGIC,
    OP_ATTACHMENT,
    OP_CHUNK,
    OP_DATA_END,
    OP_FOOTER,
    OP_HEADER,
    OP_MESSAGE,
    OP_MESSAGE_INDEX,
    OP_METADATA,
    ChunkRef,
    RecordDamage,
    attachment_crc,
    chunk_data,
    parse_record,
    records_of,
    schema_info,
)
from memlog.io.mcap.scan import DataScan
from memlog.io.mcap.summary import read_summary
from memlog.io.spool import ChunkSpool
from memlog.io.records import Attachment, ChannelInfo, RawMessage, ReadReport, SchemaInfo
from memlog.io.types import LogInfo

__all__ = ["McapLog", "CHUNK_CACHE_BYTES"]

_LOG = logging.getLogger("memlog.io")

#: Message bytes of the chunks a reader keeps after reading them (the last ones read), so that a
#: pass asking for a few frames at a time (the staged detector, one segment after the other) reads
#: each chunk once. A larger chunk is not kept.
CHUNK_CACHE_BYTES = 8 << 20


@dataclass
class _Learned:
    """What opening (and scanning) one MCAP file learned; shared by its readers in a process."""

    said: set[str] = field(default_factory=set)
    header: Header | None = None
    summary: Summary | None = None
    schemas: dict[int, SchemaInfo | None] = field(default_factory=dict)
    channels: dict[int, ChannelInfo] = field(default_factory=dict)
    data_channels: set[int] = field(default_factory=set)
    indexed: bool = False  # the summary's chunk index drives the reads
    chunks: list[ChunkRef] | None = None  # the scan's readable chunks and top-level messages
    counts: dict[int, int] | None = None  # the scan's messages per channel
    ranges: dict[int, list[int]] = field(default_factory=dict)  # the scan's log-time range per channel
    tables: dict[str, FrameTable] = field(default_factory=dict)
    crcs: list[bool] = field(default_factory=list)  # per chunk the scan read: was its CRC checked
    report: ReadReport | None = None  # what opening found (copied into every reader's report)
    places: dict[int, str] = field(default_factory=dict)  # damage_place() of each damage found
    unresolved: dict[int, int] = field(default_factory=dict)  # channel id -> its schema's id, not read yet
    summary_crc: str = "none"  # the footer's summary CRC: "held", "failed", "absent" (0) or "none" (no summary)
    data_crc: str = "absent"  # the DataEnd record's CRC of the data section: "held", "failed", "absent", "unchecked"
    crc_failed: set[int] = field(default_factory=set)  # offsets of the chunks that failed their CRC check
    attachment_crcs: dict[int, str] = field(default_factory=dict)  # attachment offset -> "held", "failed", "absent"
    attachments_read: bool = False  # every attachment record was read (and its CRC checked)

    @property
    def scanned(self) -> bool:
        """Whether the data was scanned to learn this (kept on disk for other processes)."""
        return self.chunks is not None

    def close(self) -> None:
        pass


class McapLog(LogReader):
    """An MCAP file opened for streaming (see :func:`memlog.io.open_log`)."""

    format = "mcap"

    def __init__(self, path: str | os.PathLike[str], validate_crcs: bool = True) -> None:
        super().__init__(path)
        self.validate_crcs = validate_crcs
        self._size = check_regular_file(self.path).st_size
        try:
            self._fh: IO[bytes] = open(self.path, "rb")
        except OSError as exc:
            raise LogReadError(f"{self.path}: cannot open: {exc.strerror}") from exc
        self._chunks_crc: list[bool] = []  # per chunk read: was its CRC checked
        # the chunks read last (offset -> messages; None: damaged), so that passes asking for a few
        # frames at a time read each chunk once as long as they move forward (bounded: CHUNK_CACHE_BYTES)
        self._recent: OrderedDict[int, tuple[list[tuple[int, Message]] | None, int]] = OrderedDict()  # with bytes
        self._recent_bytes = 0
        self._key: Any = None
        try:
            if self._fh.read(len(MAGIC)) != MAGIC:
                raise LogReadError(f"{self.path}: not an MCAP file (bad magic)")
            key = file_key("mcap", self.path, validate_crcs)
            self._holder = holder()
            self._l, new = learned(key, self._learn)
            self._key = key
        except BaseException:
            self._fh.close()
            raise
        self._said = self._l.said
        if not new and self._l.report is not None:  # what opening found, already said
            self._learned_before(self._l.report)
        self.header = self._l.header
        self.summary = self._l.summary
        self.profile = self.header.profile if self.header else ""

    # -- opening ------------------------------------------------------------------
    def _learn(self) -> _Learned:
        """Open the file for the first time in this process: header, summary, and the scan
        when the summary cannot drive the reads."""
        self._l = _Learned()
        self._said = self._l.said
        self._l.header = self._read_header()
        self._open_summary()
        for cid, sid in self._l.unresolved.items():
            self.report.index_damaged = True
            self.warn(f"{self.path}: channel {cid} ({self._l.channels[cid].topic}) names schema {sid}, which no "
                      "readable record defines: its messages are read without a schema")
        self._l.report = copy.deepcopy(self.report)
        return self._l

    def _read_header(self) -> Header | None:
        try:
            op, n = self._head(len(MAGIC))
            if op != OP_HEADER or n > self._size:
                return None
            self._fh.seek(len(MAGIC) + 9)
            return parse_record(Header, self._fh.read(n), len(MAGIC))  # type: ignore[no-any-return]
        except RecordDamage:
            return None

    def _head(self, pos: int) -> tuple[int, int]:
        self._fh.seek(pos)
        b = self._fh.read(9)
        if len(b) < 9:
            raise RecordDamage(pos, "the file ends in the middle of a record")
        return b[0], struct.unpack_from("<Q", b, 1)[0]

    def _open_summary(self) -> None:
        """Use the summary where it is whole and agrees with the data. Every summary section is
        optional (MCAP spec): a file without a summary, or whose summary repeats no channels, or
        lists channels whose schemas only the data section holds, is valid; only a summary that
        fails its CRC, does not parse or disagrees with the data is damage."""
        learned_ = self._l
        summary, summary_start, why, learned_.summary_crc = read_summary(self._fh, self._size)
        if summary is None:
            if why.startswith("no summary section"):
                _LOG.info("%s: %s: reading the data sequentially", self.path, why)
            else:
                if why.startswith("no footer"):
                    self.report.truncated = True
                elif summary_start or "outside" in why:  # a summary is there, but fails its CRC or does not parse
                    self.report.index_damaged = True
                self.warn(f"{self.path}: {why}: reading the data sequentially")
            self._scan()
            return
        learned_.summary = summary
        for sid, s in summary.schemas.items():
            learned_.schemas[sid] = schema_info(s)
        for c in summary.channels.values():
            self._add_channel(c)
        if not summary.channels or not summary.chunk_indexes:
            # channels only in the data, or an unchunked file: the data is read once, as it is
            _LOG.info("%s: %s: reading the data sequentially", self.path,
                      "the summary repeats no channels" if summary.channels == {} else "no chunk index")
            self._scan()
            return
        walked, damage, top = self._walk_chunks(summary_start)
        index = {ci.chunk_start_offset: ci for ci in summary.chunk_indexes}
        differ = [o for o, r in walked.items() if o in index and (
            index[o].chunk_length != r.index_length or index[o].message_start_time != r.start
            or index[o].message_end_time != r.end)]
        if damage is None and set(walked) == set(index) and not top and not differ:
            learned_.indexed = True
            self._resolve_schemas()
            return
        self.report.index_damaged = True
        reasons: list[str] = []
        if damage is not None:
            reasons.append(f"the data section is damaged {self._place(damage.pos)} ({damage.reason})")
        missing = sorted(set(walked) - set(index))
        bogus = sorted(set(index) - set(walked))
        if missing:
            reasons.append(f"{len(missing)} chunk(s) in the data are not in the index")
        if bogus:
            reasons.append(f"{len(bogus)} index entr{'y points' if len(bogus) == 1 else 'ies point'} to no chunk the "
                           f"data walk found (first: byte {bogus[0]})")
        if differ:
            reasons.append(f"{len(differ)} index entr{'y gives' if len(differ) == 1 else 'ies give'} another length or "
                           f"time range than the chunk record (first: byte {differ[0]})")
        if top:
            reasons.append(f"{top} message(s) lie outside chunks")
        self.warn(f"{self.path}: the chunk index and the data section disagree ({'; '.join(reasons)}): reading the data instead")
        # past damage the index may still lead to intact chunks: the scan tries them
        self._scan([ChunkRef(off, index[off].message_start_time, index[off].message_end_time,
                              index[off].chunk_length) for off in bogus], damage_known=damage is not None)

    def _walk_chunks(self, end: int) -> tuple[dict[int, ChunkRef], RecordDamage | None, int]:
        """Chunk records of the data section by their headers alone (bodies are skipped), up to
        the DataEnd record or byte ``end``; the damage that stopped the walk, if any, and how many
        messages lie outside chunks."""
        found: dict[int, ChunkRef] = {}
        top = 0
        pos = len(MAGIC)
        try:
            while pos < end:
                op, n = self._head(pos)
                if op not in KNOWN_OPS and op < 0x80:
                    raise RecordDamage(pos, f"no valid record at byte {pos} (opcode {op:#04x})")
                if pos + 9 + n > end:
                    raise RecordDamage(pos, f"record at byte {pos} claims {n} bytes, past the data section")
                if op == OP_CHUNK:
                    head = self._fh.read(min(n, CHUNK_HEAD))
                    if len(head) < CHUNK_HEAD:
                        raise RecordDamage(pos, "chunk record is too short")
                    s, e = struct.unpack_from("<QQ", head, 0)
                    found[pos] = ChunkRef(pos, s, e, 9 + n)
                elif op == OP_MESSAGE:
                    top += 1
                elif op == OP_DATA_END or op == OP_FOOTER:
                    break
                pos += 9 + n
        except RecordDamage as exc:
            return found, exc, top
        return found, None, top

    def _scan(self, past_damage: list[ChunkRef] | None = None, *, damage_known: bool = False) -> None:
        """Read the data section once, up to the damage, and learn what the reads need
        (:class:`~memlog.io.mcap.scan.DataScan`). ``past_damage``: chunks the index knows that the
        walk did not reach, tried after it."""
        DataScan(self).run(past_damage, damage_known=damage_known)

    def close(self) -> None:
        self._fh.close()
        self._recent.clear()
        self._recent_bytes = 0
        if self._key is not None:
            release(self._key, self._holder)
            self._key = None

    def _add_channel(self, c: Channel) -> None:
        """Register a summary channel; one whose schema only the data holds waits for it
        (:meth:`_resolve_schemas`)."""
        lrn = self._l
        if c.schema_id and c.schema_id not in lrn.schemas:
            lrn.unresolved[c.id] = c.schema_id
        lrn.channels[c.id] = ChannelInfo(c.id, c.topic, c.message_encoding, lrn.schemas.get(c.schema_id),
                                         dict(c.metadata))

    def _resolve_schemas(self) -> None:
        """Read chunks in file order until every summary channel whose schema the summary does not
        repeat has it (the spec lets a summary repeat channels without their schemas): usually
        the first chunk."""
        lrn = self._l
        assert lrn.summary is not None
        for ci in sorted(lrn.summary.chunk_indexes, key=lambda ci: ci.chunk_start_offset):
            if not lrn.unresolved:
                return
            self._read_chunk(ChunkRef(ci.chunk_start_offset, ci.message_start_time, ci.message_end_time,
                                      ci.chunk_length))

    # -- listing ----------------------------------------------------------------
    def channels(self) -> list[ChannelInfo]:
        return list(self._l.channels.values())

    def message_counts(self) -> dict[int, int] | None:
        lrn = self._l
        if lrn.indexed:
            if lrn.summary is not None and lrn.summary.statistics is not None:
                return dict(lrn.summary.statistics.channel_message_counts)
            return None
        return dict(lrn.counts) if lrn.counts is not None else None

    def _chunk_crcs(self) -> list[bool]:
        """Per chunk read (by this reader, or by the scan): whether its CRC was checked."""
        return self._chunks_crc + ([] if self._l.indexed else self._l.crcs)

    def checksums(self) -> str:
        lrn = self._l
        crcs = self._chunk_crcs()
        if lrn.data_crc in ("held", "failed"):  # an unchunked file's records, checked whole
            crcs = crcs + [True]
        if lrn.indexed and not crcs:
            return "unknown"
        if crcs and all(crcs):
            return "all"
        if any(crcs):
            return "some"
        return "none"

    def checksum_checks(self) -> dict[str, str]:
        lrn = self._l
        crcs = self._chunk_crcs()
        chunks = ("failed" if lrn.crc_failed else ("unread" if lrn.indexed else "none") if not crcs
                  else "held" if all(crcs) else "some" if any(crcs) else "absent")
        kinds = set(lrn.attachment_crcs.values())
        attachments = ("failed" if "failed" in kinds else "some" if len(kinds) > 1 else kinds.pop() if kinds
                       else "none" if lrn.attachments_read else "unread")
        return {"chunks": chunks, "data_section": lrn.data_crc, "summary": lrn.summary_crc, "attachments": attachments}

    def frame_table(self, topic: str) -> FrameTable:
        lrn = self._l
        table = lrn.tables.get(topic)
        if table is not None:
            return table
        if lrn.indexed:
            assert lrn.summary is not None
            if any(not ci.message_index_offsets for ci in lrn.summary.chunk_indexes):
                # message indexes are optional (MCAP spec): without them, one scan of the data numbers the frames
                _LOG.info("%s: no message indexes: numbering frames from a scan of the data", self.path)
                self._scan()
                lrn.indexed = False
            elif why := self._index_tables():
                self.report.index_damaged = True
                self.warn(f"{self.path}: the message index is {why}: numbering frames from a scan of the data")
                self._scan()
                lrn.indexed = False
                if lrn.report is not None:  # the next reader learns of it too
                    lrn.report.merge(self.report)
        return lrn.tables.setdefault(topic, FrameTable.concat([]))

    def _index_tables(self) -> str:
        """Build every camera topic's frame table from the message indexes the chunk index points
        to (no chunk is decompressed); "" when they are sound, else what is wrong with them."""
        lrn = self._l
        assert lrn.summary is not None
        cams = {c.id: c.topic for c in lrn.channels.values() if camera_kind(c.msgtype)}
        parts: dict[str, list[tuple[Any, Any, Any]]] = {t: [] for t in cams.values()}
        found: dict[int, int] = {}
        for ci in lrn.summary.chunk_indexes:
            offsets_seen: set[int] = set()
            for cid, off in ci.message_index_offsets.items():
                if cid not in cams:
                    continue
                try:
                    op, n = self._head(off)
                    body = self._fh.read(n) if op == OP_MESSAGE_INDEX and 6 <= n <= self._size else b""
                except RecordDamage:
                    return f"unreadable at byte {off}"
                got_cid, rlen = struct.unpack_from("<HI", body, 0) if len(body) >= 6 else (-1, 0)
                if got_cid != cid or rlen % 16 or 6 + rlen > len(body):
                    return f"damaged at byte {off}"
                e = np.frombuffer(body, dtype="<u8", offset=6, count=rlen // 8).reshape(-1, 2).astype(np.int64)
                times, inner = e[:, 0], e[:, 1]
                if len(e) and (times.min() < ci.message_start_time or times.max() > ci.message_end_time
                               or inner.min() < 0 or inner.max() >= ci.uncompressed_size
                               or len(set(inner.tolist()) | offsets_seen) != len(offsets_seen) + len(e)):
                    return f"inconsistent with its chunk at byte {ci.chunk_start_offset}"
                offsets_seen |= set(inner.tolist())
                found[cid] = found.get(cid, 0) + len(e)
                parts[cams[cid]].append((times, np.full(len(e), ci.chunk_start_offset, np.int64), inner))
        counts = self.message_counts()
        if counts is not None and any(found.get(cid, 0) != counts.get(cid, 0) for cid in cams):
            return "incomplete (its entries and the statistics disagree)"
        lrn.tables.update({t: FrameTable.concat(p) for t, p in parts.items()})
        return ""

    def _fill_time_range(self, info: LogInfo) -> None:
        lrn = self._l
        ranges: dict[int, list[int]] = {}
        if lrn.indexed and lrn.summary is not None:
            # per-topic ranges come from the chunk index only approximately; overall range is exact
            st = lrn.summary.statistics
            if st is not None and st.message_count:
                info.start_ns, info.end_ns = st.message_start_time, st.message_end_time
            for ci in lrn.summary.chunk_indexes:
                for cid in ci.message_index_offsets:
                    r = ranges.setdefault(cid, [ci.message_start_time, ci.message_end_time])
                    r[0] = min(r[0], ci.message_start_time)
                    r[1] = max(r[1], ci.message_end_time)
        elif not lrn.indexed:
            ranges = lrn.ranges
        self._widen_topic_ranges(info, ranges)

    # -- messages ---------------------------------------------------------------
    def _iter_messages(
        self, topics: set[str] | None, start_ns: int | None, end_ns: int | None, log_time_order: bool
    ) -> Iterator[RawMessage]:
        lrn = self._l
        ids = None if topics is None else {c.id for c in lrn.channels.values() if c.topic in topics}
        if lrn.indexed:
            assert lrn.summary is not None
            refs = [
                ChunkRef(ci.chunk_start_offset, ci.message_start_time, ci.message_end_time, ci.chunk_length)
                for ci in lrn.summary.chunk_indexes
                if ids is None or not ci.message_index_offsets or ids & set(ci.message_index_offsets)
            ]
        else:
            refs = list(lrn.chunks or [])
        yield from self._chunked_messages(refs, ids, start_ns, end_ns, log_time_order)

    def _read_chunk(self, ref: ChunkRef) -> list[tuple[int, Message]] | None:
        """Messages of the chunk (or message record) at ``ref.offset``, each with its offset in the
        chunk (schemas and channels registered); None when it is damaged (reported, once). The
        last chunks read (up to :data:`CHUNK_CACHE_BYTES` of messages) are kept and not read again."""
        if ref.offset in self._recent:
            self._recent.move_to_end(ref.offset)
            return self._recent[ref.offset][0]
        found, got = self._from_spool(ref)
        if not found:
            got = self._read_chunk_now(ref)
        size = sum(len(m.data) + 64 for _, m in got or ())
        if size <= CHUNK_CACHE_BYTES:
            self._recent[ref.offset] = (got, size)
            self._recent_bytes += size
            while self._recent_bytes > CHUNK_CACHE_BYTES:
                self._recent_bytes -= self._recent.popitem(last=False)[1][1]
        return got

    def _kept_chunks(self) -> ChunkSpool | None:
        """The job's spool (:meth:`spool`), where CRCs are checked: what it keeps was checked."""
        return self.spool() if self.validate_crcs else None

    def _records_kept(self, pos: int, body: bytes) -> tuple[list[tuple[int, Any]], bool]:
        """The records of the chunk record ``body`` at ``pos`` (:func:`chunk_data`), kept in the
        job's spool once they are read whole."""
        data, checked = chunk_data(body, pos, self.validate_crcs)
        records = records_of(data, pos)
        spool = self._kept_chunks()
        if spool is not None:
            spool.put(pos, data, checked)
        return records, checked

    def _from_spool(self, ref: ChunkRef) -> tuple[bool, list[tuple[int, Message]] | None]:
        """Whether the job's spool has the chunk at ``ref``, and the chunk as :meth:`_read_chunk_now`
        gives it (a damaged one is reported again: None)."""
        spool = self._kept_chunks() if ref.op == OP_CHUNK else None
        kept = spool.get(ref.offset) if spool is not None else None
        if isinstance(kept, str):  # found damaged by an earlier pass: said again, not read again
            self._skipped_chunk(ref, kept)
            return True, None
        if kept is None:
            return False, None
        try:
            records = records_of(kept[0], ref.offset)
        except RecordDamage:
            return False, None
        self._chunks_crc.append(kept[1])
        return True, self._absorb(records)

    def _read_chunk_now(self, ref: ChunkRef) -> list[tuple[int, Message]] | None:
        """The chunk at ``ref`` read from the log (kept in the job's spool, damage too)."""
        pos = ref.offset
        spool = self._kept_chunks() if ref.op == OP_CHUNK else None
        try:
            op, n = self._head(pos)
            if op != ref.op:
                raise RecordDamage(pos, f"no {'chunk' if ref.op == OP_CHUNK else 'message'} record at byte {pos} "
                                   f"(opcode {op:#04x})")
            if op == OP_MESSAGE:
                self._fh.seek(pos + 9)
                return [(0, parse_record(Message, self._fh.read(n), pos))]
            lengths = [n] + ([ref.index_length - 9] if ref.index_length and ref.index_length - 9 != n else [])
            err: RecordDamage | None = None
            for length in lengths:  # the record's own length first; the index's if that fails
                if length < 0 or pos + 9 + length > self._size or length > MAX_CHUNK_BYTES:
                    err = RecordDamage(pos, f"chunk at byte {pos} claims {length} bytes, past the end of the file")
                    continue
                self._fh.seek(pos + 9)
                try:
                    records, checked = self._records_kept(pos, self._fh.read(length))
                except RecordDamage as exc:
                    err = exc
                    continue
                self._chunks_crc.append(checked)
                return self._absorb(records)
            assert err is not None
            raise err
        except RecordDamage as exc:
            self._skipped_chunk(ref, exc.reason)
            if spool is not None:
                spool.put_damaged(pos, exc.reason)
            return None

    def _opcode_at(self, pos: int) -> int | None:
        """The byte at ``pos`` (a record's opcode), None past the end."""
        self._fh.seek(pos)
        b = self._fh.read(1)
        return b[0] if b else None

    def _place(self, pos: int) -> str:
        """:func:`damage_place` of ``pos``, found once per file and process (each walk of a damaged
        file meets the same damage: its zero-filled tail is not read again)."""
        places = self._l.places
        if pos not in places:
            places[pos] = damage_place(self._fh, pos, self._size)
        return places[pos]

    def _count_damaged_chunk(self, pos: int, reason: str) -> None:
        """Count the damaged chunk at ``pos`` once (and whether its CRC failed); the caller says it."""
        self.report.count("skipped_chunks", pos)
        if "CRC" in reason:
            self._l.crc_failed.add(pos)

    def _skipped_chunk(self, ref: ChunkRef, reason: str) -> None:
        self._count_damaged_chunk(ref.offset, reason)
        self.warn(f"{self.path}: chunk at byte {ref.offset} is damaged: {reason}; "
                  f"skipped its messages (log time {ref.start}..{ref.end})")

    def _absorb(self, records: list[tuple[int, Any]]) -> list[tuple[int, Message]]:
        """Register the schemas and channels among ``records``; return their messages (with their
        offsets). A channel record in the data wins over a summary that says otherwise (reported)."""
        lrn = self._l
        out = []
        for at, r in records:
            if isinstance(r, Schema):
                lrn.schemas.setdefault(r.id, schema_info(r))
            elif isinstance(r, Channel):
                if r.id not in lrn.data_channels:
                    lrn.data_channels.add(r.id)
                    old = lrn.channels.get(r.id)
                    new = ChannelInfo(r.id, r.topic, r.message_encoding, lrn.schemas.get(r.schema_id),
                                      dict(r.metadata))
                    if old is not None and (old.topic, old.message_encoding, old.schema) != (
                            new.topic, new.message_encoding, new.schema) and r.id not in lrn.unresolved:
                        self.report.index_damaged = True
                        self.warn(f"{self.path}: the summary describes channel {r.id} as {old.topic!r}, the data "
                                  f"as {r.topic!r}: using the data's")
                    if old is None or old != new:
                        lrn.channels[r.id] = new
                        lrn.unresolved.pop(r.id, None)  # a summary channel's schema, found with it in the data
            elif isinstance(r, Message):
                out.append((at, r))
        return out

    def _raw(self, m: Message, where: tuple[int, int]) -> RawMessage | None:
        ch = self._l.channels.get(m.channel_id)
        if ch is None:
            if self.report.count("bad_messages", ("unknown channel", where)):
                self.warn(f"{self.path}: message on unknown channel id {m.channel_id} at log time {m.log_time}: skipped")
            return None
        return RawMessage(ch, m.log_time, m.publish_time, m.sequence, bytes(m.data), where)

    def _chunked_messages(
        self, refs: list[ChunkRef], ids: set[int] | None, start_ns: int | None, end_ns: int | None,
        log_time_order: bool,
    ) -> Iterator[RawMessage]:
        chunks = [r for r in refs if (start_ns is None or r.end >= start_ns) and (end_ns is None or r.start < end_ns)]
        if not log_time_order:
            chunks.sort(key=lambda c: c.offset)
            for ref in chunks:
                for at, m in self._read_chunk(ref) or []:
                    if self._keep(m, ids, start_ns, end_ns):
                        r = self._raw(m, (ref.offset, at))
                        if r is not None:
                            yield r
            return
        chunks.sort(key=lambda c: (c.start, c.offset))
        heap: list[tuple[int, int, int, Message, tuple[int, int]]] = []
        order = 0
        i = 0
        while i < len(chunks) or heap:
            # load every chunk that may hold a message earlier than the heap's head
            while i < len(chunks) and (not heap or chunks[i].start <= heap[0][0]):
                ref = chunks[i]
                for at, m in self._read_chunk(ref) or []:
                    if self._keep(m, ids, start_ns, end_ns):
                        heapq.heappush(heap, (m.log_time, i, order, m, (ref.offset, at)))
                        order += 1
                i += 1
            if heap:
                _, _, _, m, where = heapq.heappop(heap)
                r = self._raw(m, where)
                if r is not None:
                    yield r

    @staticmethod
    def _keep(m: Message, ids: set[int] | None, start_ns: int | None, end_ns: int | None) -> bool:
        return (
            (ids is None or m.channel_id in ids)
            and (start_ns is None or m.log_time >= start_ns)
            and (end_ns is None or m.log_time < end_ns)
        )

    def _walk_records(self, kinds: set[int]) -> Iterator[tuple[int, int, bytes]]:
        """(offset, opcode, body) of the top-level records of the data section whose opcode is in
        ``kinds`` (other bodies are skipped by seeking), up to DataEnd/Footer; damage ends it and
        is left in ``self._walk_damage`` (None when the walk reached the end cleanly)."""
        for pos, op, body, _n in self._walk(kinds):
            yield pos, op, body

    def _walk(self, kinds: AbstractSet[int], heads: AbstractSet[int] = frozenset()
              ) -> Iterator[tuple[int, int, bytes, int]]:
        """:meth:`_walk_records` with each record's length; of the records whose opcode is in
        ``heads``, only the first :data:`CHUNK_HEAD` bytes of the body."""
        self._walk_damage: RecordDamage | None = None
        self._data_end: int | None = None  # where the DataEnd record is, once the walk reaches it
        pos = len(MAGIC)
        size = self._size
        try:
            while True:
                if pos == size:
                    raise RecordDamage(pos, "the file ends before its DataEnd record and footer")
                op, n = self._head(pos)
                if op not in KNOWN_OPS and op < 0x80:
                    raise RecordDamage(pos, f"no valid record (opcode {op:#04x})")
                if pos + 9 + n > size:
                    raise RecordDamage(pos, f"a record claims {n} bytes, past the end of the file")
                if op == OP_DATA_END or op == OP_FOOTER:
                    self._data_end = pos if op == OP_DATA_END else None
                    return
                if op in kinds or op in heads:
                    if n > MAX_CHUNK_BYTES:
                        raise RecordDamage(pos, f"a record claims {n} bytes")
                    self._fh.seek(pos + 9)
                    yield pos, op, self._fh.read(n if op in kinds else min(n, CHUNK_HEAD)), n
                pos += 9 + n
        except RecordDamage as exc:
            self._walk_damage = exc

    def _records(self, kinds: set[int]) -> Iterator[tuple[int, int, bytes]]:
        """:meth:`_walk_records`; damage is reported (a zero-filled tail from where the zeros start)."""
        yield from self._walk_records(kinds)
        exc = self._walk_damage
        if exc is not None:
            rep = self.report
            rep.truncated = True
            rep.bytes_read = exc.pos if rep.bytes_read is None else min(rep.bytes_read, exc.pos)
            self.warn(f"{self.path}: log is truncated or damaged {self._place(exc.pos)} "
                      f"({exc.reason}); read everything before it")

    # -- metadata / attachments ----------------------------------------------------
    def metadata(self) -> Iterator[tuple[str, dict[str, str]]]:
        for pos, _op, body in self._records({OP_METADATA}):
            try:
                m = parse_record(Metadata, body, pos)
            except RecordDamage as exc:
                if self.report.count("bad_messages", ("metadata", pos)):
                    self.warn(f"{self.path}: metadata record at byte {pos} is damaged ({exc.reason}); skipped")
                continue
            yield m.name, dict(m.metadata)

    def attachments(self) -> Iterator[Attachment]:
        """Every attachment record, its CRC checked where it has one (one that fails is reported
        and skipped, as a chunk is)."""
        crcs = self._l.attachment_crcs
        for pos, _op, body in self._records({OP_ATTACHMENT}):
            try:
                a = parse_record(McapAttachment, body, pos)
                crcs[pos] = "failed"  # unless attachment_crc returns
                crcs[pos] = attachment_crc(body, a, pos) if self.validate_crcs else "absent"
            except RecordDamage as exc:
                if self.report.count("bad_messages", ("attachment", pos)):
                    self.warn(f"{self.path}: attachment record at byte {pos} is damaged ({exc.reason}); skipped")
                continue
            yield Attachment(a.name, a.media_type, a.log_time, a.create_time, bytes(a.data))
        self._l.attachments_read = True

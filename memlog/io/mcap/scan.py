"""The scan of an MCAP log whose summary cannot drive the reads (a cut or unfinished recording, a
damaged index): one walk over the data section, up to the damage, learning where every readable
chunk and top-level message lies, the channels, the message counts and time ranges, and the frame
tables. A chunk followed by its message indexes (what MCAP writers put after each chunk) is learned
from them, its body not read: the passes read it, and find any damage in it then, as with an indexed
log. A chunk without them, or with a channel not known yet (its Channel record lies inside) or whose
schema is not (a summary may repeat channels without their schemas), is read."""

from __future__ import annotations

import os
import struct
import zlib
from collections.abc import Iterator
from collections.abc import Set as AbstractSet
from typing import IO, Any, Protocol

from mcap.records import Channel, Message, MessageIndex, Schema

from memlog.io._opened import counted_scan
from memlog.io.camera import camera_kind
from memlog.io.mcap.records import (
    CHUNK_HEAD,
    OP_CHANNEL,
    OP_CHUNK,
    OP_DATA_END,
    OP_MESSAGE,
    OP_MESSAGE_INDEX,
    OP_SCHEMA,
    ChunkRef,
    RecordDamage,
    frame_table_of,
    parse_record,
)
from memlog.io.records import ReadReport

__all__ = ["DataScan"]


class McapLog(Protocol):
    """What the scan uses of :class:`memlog.io.mcap.reader.McapLog` (the reader it scans for)."""

    path: str
    report: ReadReport
    _fh: IO[bytes]
    _l: Any  # the reader's learned structure, which the scan fills
    _walk_damage: RecordDamage | None
    _data_end: int | None
    _size: int
    validate_crcs: bool

    def warn(self, msg: str) -> None: ...
    def _records_kept(self, pos: int, body: bytes) -> tuple[list[tuple[int, Any]], bool]: ...
    def _absorb(self, records: list[tuple[int, Any]]) -> list[tuple[int, Message]]: ...
    def _walk(self, kinds: AbstractSet[int], heads: AbstractSet[int] = ...) -> Iterator[tuple[int, int, bytes, int]]: ...
    def _opcode_at(self, pos: int) -> int | None: ...
    def _read_chunk(self, ref: ChunkRef) -> list[tuple[int, Message]] | None: ...
    def _place(self, pos: int) -> str: ...
    def _head(self, pos: int) -> tuple[int, int]: ...
    def _count_damaged_chunk(self, pos: int, reason: str) -> None: ...


_Pending = tuple[int, int, bytes, dict[int, list[tuple[int, int]]]]  # chunk: offset, length, head, its indexes


class DataScan:
    """One scan of ``log``'s data section (see the module doc); :meth:`run` fills what the log learned."""

    def __init__(self, log: McapLog) -> None:
        self.log = log
        self.refs: list[ChunkRef] = []
        self.counts: dict[int, int] = {}
        self.entries: dict[str, list[tuple[int, int, int]]] = {}
        self.pending: _Pending | None = None
        self.chunked = False  # the walk met a chunk record

    def _note(self, ref: ChunkRef, msgs: list[tuple[int, Message]]) -> None:
        """Learn the chunk (or top-level message) at ``ref`` from its messages."""
        by_channel: dict[int, list[tuple[int, int]]] = {}
        for inner, m in msgs:
            by_channel.setdefault(m.channel_id, []).append((m.log_time, inner))
        self._note_index(ref, by_channel)

    def _note_index(self, ref: ChunkRef, index: dict[int, list[tuple[int, int]]]) -> None:
        """Learn the chunk at ``ref`` from its (log time, offset) of each message, by channel."""
        self.refs.append(ref)
        for cid, rows in index.items():
            if rows:
                self._add(cid, rows, ref)

    def _add(self, cid: int, rows: list[tuple[int, int]], ref: ChunkRef) -> None:
        lrn = self.log._l
        self.counts[cid] = self.counts.get(cid, 0) + len(rows)
        times = [t for t, _ in rows]
        r = lrn.ranges.setdefault(cid, [min(times), max(times)])
        r[0], r[1] = min(r[0], *times), max(r[1], *times)
        ch = lrn.channels.get(cid)
        if ch is not None and camera_kind(ch.msgtype):
            self.entries.setdefault(ch.topic, []).extend((t, ref.offset, inner) for t, inner in rows)

    def _read_chunk(self, pos: int, n: int) -> None:
        log = self.log
        try:
            log._fh.seek(pos + 9)
            body = log._fh.read(n)
            recs, checked = log._records_kept(pos, body)
            log._l.crcs.append(checked)
            msgs = log._absorb(recs)
            start, end = struct.unpack_from("<QQ", body, 0)
            self._note(ChunkRef(pos, start, end, 9 + n), msgs)
        except RecordDamage as exc:
            log._count_damaged_chunk(pos, exc.reason)
            log.warn(f"{log.path}: chunk at byte {pos} is damaged: {exc.reason}; skipped")

    def _settle(self, indexed: bool) -> None:
        """Learn the chunk waiting for its indexes: from them (``indexed``: they are whole), or read it."""
        if self.pending is None:
            return
        pos, n, head, index = self.pending
        self.pending = None
        lrn = self.log._l
        if indexed and index and all(cid in lrn.channels and cid not in lrn.unresolved for cid in index):
            start, end = struct.unpack_from("<QQ", head, 0)
            self._note_index(ChunkRef(pos, start, end, 9 + n), index)
        else:
            self._read_chunk(pos, n)

    def _walk(self) -> None:
        log = self.log
        for pos, op, body, n in log._walk({OP_SCHEMA, OP_CHANNEL, OP_MESSAGE, OP_MESSAGE_INDEX}, heads={OP_CHUNK}):
            if op == OP_MESSAGE_INDEX and self.pending is not None:
                try:
                    mi = parse_record(MessageIndex, body, pos)
                    if mi.records:
                        self.pending[3].setdefault(mi.channel_id, []).extend(mi.records)
                except RecordDamage:
                    self.pending = (self.pending[0], self.pending[1], self.pending[2], {})  # (read the chunk instead)
                continue
            self._settle(True)
            try:
                if op == OP_SCHEMA:
                    log._absorb([(0, parse_record(Schema, body, pos))])
                elif op == OP_CHANNEL:
                    log._absorb([(0, parse_record(Channel, body, pos))])
                elif op == OP_MESSAGE:
                    m = parse_record(Message, body, pos)
                    self._note(ChunkRef(pos, m.log_time, m.log_time, 9 + len(body), OP_MESSAGE), [(0, m)])
                elif op == OP_CHUNK:
                    if len(body) < CHUNK_HEAD:
                        raise RecordDamage(pos, "chunk record is too short")
                    self.pending = (pos, n, body, {})
                    self.chunked = True
            except RecordDamage as exc:
                log.report.count("skipped_chunks", pos)
                log.warn(f"{log.path}: record at byte {pos} is damaged: {exc.reason}; skipped")
        # damage right after a chunk's indexes: trusted unless the damaged record is one more index
        damage = log._walk_damage
        self._settle(damage is None or log._opcode_at(damage.pos) not in (OP_MESSAGE_INDEX, None))

    def _check_data_crc(self) -> None:
        """An unchunked file's data-section CRC (its DataEnd record's), over every byte before
        DataEnd; a chunked file's messages are covered by its chunk CRCs (not read again for this)."""
        log = self.log
        lrn = log._l
        end = log._data_end
        if end is None or log._walk_damage is not None:
            lrn.data_crc = "absent"
            return
        op, n = log._head(end)
        body = log._fh.read(min(n, 4))
        crc = struct.unpack_from("<I", body)[0] if op == OP_DATA_END and len(body) == 4 else 0
        if crc == 0:
            lrn.data_crc = "absent"
            return
        if self.chunked or not log.validate_crcs:
            lrn.data_crc = "unchecked"
            return
        got, at = 0, 0
        log._fh.seek(0)
        while at < end:
            block = log._fh.read(min(1 << 20, end - at))
            if not block:
                break
            got, at = zlib.crc32(block, got), at + len(block)
        if got == crc:
            lrn.data_crc = "held"
            return
        lrn.data_crc = "failed"
        log.report.data_crc_failed = True
        log.warn(f"{log.path}: the data section fails its CRC check (DataEnd record at byte {end}: expected "
                 f"{crc:#010x}, got {got:#010x}): its records were kept, but any of them may be damaged")

    def run(self, past_damage: list[ChunkRef] | None = None, *, damage_known: bool = False) -> None:
        """Scan, then try ``past_damage`` (chunks the index knows that the walk did not reach)."""
        log = self.log
        counted_scan(os.path.realpath(log.path))
        self._walk()
        damage: RecordDamage | None = log._walk_damage
        self._check_data_crc()
        later = [r for r in past_damage or [] if damage is None or r.offset > damage.pos]
        found_later = 0
        for ref in later:
            got = log._read_chunk(ref)
            if got is not None:
                found_later += 1
                self._note(ref, got)
        if damage is not None:
            rep = log.report
            rep.bytes_read = damage.pos
            where = log._place(damage.pos)
            if found_later:
                rep.index_damaged = True
                log.warn(f"{log.path}: the data section is damaged {where} ({damage.reason}); read everything "
                         f"before it and {found_later} chunk(s) the index knows after it")
            else:
                rep.truncated = True
                if not damage_known or not later:
                    log.warn(f"{log.path}: log is truncated or damaged {where} ({damage.reason}); read everything "
                             "before it")
        lrn = log._l
        lrn.chunks = sorted(self.refs, key=lambda r: r.offset)
        lrn.counts = self.counts
        for ch in lrn.channels.values():  # camera topics without a readable message have empty tables
            if camera_kind(ch.msgtype):
                self.entries.setdefault(ch.topic, [])
        lrn.tables = {t: frame_table_of(e) for t, e in self.entries.items()}

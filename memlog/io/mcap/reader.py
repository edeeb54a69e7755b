"""MCAP reader: any profile, streamed chunk by chunk, robust to damage.

The data is the truth; the summary (index) is a shortcut taken only when it proves itself:

* the summary section is read with its CRC (footer ``summary_crc``); one that fails it or does
  not parse is ignored;
* its chunk index must list exactly the chunks a walk over the data section's record headers
  finds (offsets only; the walk reads each record's 9-byte header and skips the body);
* every chunk is read at its offset with the length its own record header gives, decompressed
  to no more than the size it declares, and checked against its CRC.

When the index passes, chunks are read through it (filtered by channel and time) and merged in
log-time order. When it does not, the chunks the data walk found (plus any intact chunk the
index knows past damage) are read instead and the reader reports the index as damaged. Without a
summary the file is read sequentially up to the damage. A chunk whose CRC does not match is
reported and skipped; the rest is read. A zero-filled tail is named where the zeros start.
"""

from __future__ import annotations

import heapq
import io
import os
import struct
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from typing import IO, Any

from mcap.data_stream import ReadDataStream
from mcap.records import Attachment as McapAttachment
from mcap.records import Channel, ChunkIndex, Header, Message, Metadata, Schema, Statistics
from mcap.summary import Summary

from memlog.errors import LogReadError
from memlog.io._damage import MAX_CHUNK_BYTES, check_regular_file, damage_place, decompress, merge_groups
from memlog.io.base import LogReader
from memlog.io.records import Attachment, ChannelInfo, RawMessage, SchemaInfo
from memlog.io.types import LogInfo

__all__ = ["McapLog"]

MAGIC = b"\x89MCAP0\r\n"
_FOOTER_LEN = 1 + 8 + 8 + 8 + 4  # opcode, length, summary_start, summary_offset_start, summary_crc
# opcodes
_HEADER, _FOOTER, _SCHEMA, _CHANNEL, _MESSAGE, _CHUNK = 0x01, 0x02, 0x03, 0x04, 0x05, 0x06
_MESSAGE_INDEX, _CHUNK_INDEX, _ATTACHMENT, _METADATA, _DATA_END = 0x07, 0x08, 0x09, 0x0C, 0x0F
_STATISTICS = 0x0B
_KNOWN = set(range(0x01, 0x10))
_CHUNK_HEAD = 8 + 8 + 8 + 4 + 4  # start, end, uncompressed size, crc, compression length


class _Damage(Exception):
    """A record that cannot be what it claims (reported by the reader with its byte offset)."""

    def __init__(self, pos: int, reason: str) -> None:
        super().__init__(reason)
        self.pos, self.reason = pos, reason


@dataclass(frozen=True)
class _ChunkRef:
    """A chunk record found in the data (or an index entry to try): offset and log-time range."""

    offset: int
    start: int
    end: int
    index_length: int = 0  # the length the chunk index gives (used only if the record's own fails)


def _schema_info(s: Schema | None) -> SchemaInfo | None:
    if s is None or s.id == 0:
        return None
    return SchemaInfo(s.name, s.encoding, bytes(s.data))


def _parse(cls: Any, body: bytes, pos: int) -> Any:
    try:
        stream = ReadDataStream(io.BytesIO(body))
        rec = cls.read(stream, len(body)) if cls is Message else cls.read(stream)
    except Exception as exc:  # noqa: BLE001 - garbage bytes fail in many ways; all mean damage here
        raise _Damage(pos, f"{cls.__name__} record does not parse ({type(exc).__name__}: {exc})") from None
    if stream.count > len(body):
        raise _Damage(pos, f"{cls.__name__} record is longer than its length field")
    return rec


def _chunk_records(body: bytes, pos: int, validate_crc: bool) -> tuple[list[Any], bool]:
    """Schema, Channel and Message records of the chunk record ``body`` (at byte ``pos``) and
    whether its CRC was checked. Raises :class:`_Damage`."""
    if len(body) < _CHUNK_HEAD + 8:
        raise _Damage(pos, "chunk record is too short")
    start, end, size, crc, clen = struct.unpack_from("<QQQII", body, 0)
    at = _CHUNK_HEAD
    try:
        compression = body[at : at + clen].decode()
    except UnicodeDecodeError:
        raise _Damage(pos, "chunk compression name is not text") from None
    at += clen
    if at + 8 > len(body):
        raise _Damage(pos, "chunk record is too short")
    (dlen,) = struct.unpack_from("<Q", body, at)
    at += 8
    if at + dlen > len(body):
        raise _Damage(pos, f"chunk data length {dlen} is longer than the record")
    try:
        data = decompress(compression, body[at : at + dlen], size)
    except Exception as exc:  # noqa: BLE001 - zstd/lz4 errors have no common base
        raise _Damage(pos, f"chunk does not decompress ({type(exc).__name__}: {exc})") from None
    checked = validate_crc and crc != 0
    if checked and zlib.crc32(data) != crc:
        raise _Damage(pos, f"chunk fails its CRC check (expected {crc:#010x}, got {zlib.crc32(data):#010x})")
    out: list[Any] = []
    at = 0
    while at < len(data):
        if at + 9 > len(data):
            raise _Damage(pos, "chunk ends inside a record header")
        op, n = data[at], struct.unpack_from("<Q", data, at + 1)[0]
        if at + 9 + n > len(data):
            raise _Damage(pos, "a record in the chunk is longer than the chunk")
        body_i = data[at + 9 : at + 9 + n]
        if op == _MESSAGE:
            out.append(_parse(Message, body_i, pos))
        elif op == _CHANNEL:
            out.append(_parse(Channel, body_i, pos))
        elif op == _SCHEMA:
            out.append(_parse(Schema, body_i, pos))
        at += 9 + n
    return out, checked


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
        if self._fh.read(len(MAGIC)) != MAGIC:
            self._fh.close()
            raise LogReadError(f"{self.path}: not an MCAP file (bad magic)")
        self.header: Header | None = None
        self.summary: Summary | None = None
        self._schemas: dict[int, SchemaInfo | None] = {}
        self._channels: dict[int, ChannelInfo] = {}
        self._data_channels: set[int] = set()  # channel ids confirmed by a record in the data
        self._chunks_crc: list[bool] = []  # per chunk read: was its CRC checked
        self._top_messages = 0
        self._damage_told = False  # the sequential read's damage warning is given once
        self._indexed = False  # the summary's chunk index drives the reads
        self._chunks: list[_ChunkRef] | None = None  # chunks to read when the index is not trusted
        try:
            self.header = self._read_header()
            self._open_summary()
        except BaseException:
            self._fh.close()
            raise
        self.profile = self.header.profile if self.header else ""

    # -- opening ------------------------------------------------------------------
    def _read_header(self) -> Header | None:
        try:
            op, n = self._head(len(MAGIC))
            if op != _HEADER or n > self._size:
                return None
            self._fh.seek(len(MAGIC) + 9)
            return _parse(Header, self._fh.read(n), len(MAGIC))  # type: ignore[no-any-return]
        except _Damage:
            return None

    def _head(self, pos: int) -> tuple[int, int]:
        self._fh.seek(pos)
        b = self._fh.read(9)
        if len(b) < 9:
            raise _Damage(pos, "the file ends in the middle of a record")
        return b[0], struct.unpack_from("<Q", b, 1)[0]

    def _read_summary(self) -> tuple[Summary | None, int, str]:
        """(summary, summary_start, why it is not used)."""
        size = self._size
        if size < len(MAGIC) * 2 + _FOOTER_LEN:
            return None, 0, "the file is too short to hold a footer"
        self._fh.seek(size - len(MAGIC) - _FOOTER_LEN)
        tail = self._fh.read(_FOOTER_LEN + len(MAGIC))
        if tail[-len(MAGIC):] != MAGIC or tail[0] != _FOOTER:
            return None, 0, "no footer at the end (truncated or unfinished recording)"
        start, offset_start, crc = struct.unpack_from("<QQI", tail, 9)
        if start == 0:
            return None, 0, "no summary section (unindexed MCAP)"
        footer_pos = size - len(MAGIC) - _FOOTER_LEN
        if not len(MAGIC) < start <= footer_pos:
            return None, 0, f"the footer points to a summary at byte {start}, outside the file"
        self._fh.seek(start)
        blob = self._fh.read(footer_pos - start)
        if crc != 0:
            got = zlib.crc32(tail[: _FOOTER_LEN - 4], zlib.crc32(blob))
            if got != crc:
                return None, start, f"the summary section fails its CRC check (expected {crc:#010x}, got {got:#010x})"
        summary = Summary()
        at = 0
        try:
            while at < len(blob):
                if at + 9 > len(blob):
                    raise _Damage(start + at, "summary ends inside a record header")
                op, n = blob[at], struct.unpack_from("<Q", blob, at + 1)[0]
                if op not in _KNOWN and op < 0x80 or at + 9 + n > len(blob):
                    raise _Damage(start + at, f"summary record (opcode {op:#04x}, length {n}) is not valid")
                body = blob[at + 9 : at + 9 + n]
                if op == _SCHEMA:
                    s = _parse(Schema, body, start + at)
                    summary.schemas[s.id] = s
                elif op == _CHANNEL:
                    c = _parse(Channel, body, start + at)
                    summary.channels[c.id] = c
                elif op == _CHUNK_INDEX:
                    summary.chunk_indexes.append(_parse(ChunkIndex, body, start + at))
                elif op == _STATISTICS:
                    summary.statistics = _parse(Statistics, body, start + at)
                at += 9 + n
        except _Damage as exc:
            return None, start, f"the summary section does not parse ({exc.reason})"
        return summary, start, ""

    def _open_summary(self) -> None:
        summary, summary_start, why = self._read_summary()
        if summary is not None and summary.channels:
            self.summary = summary
            for sid, s in summary.schemas.items():
                self._schemas[sid] = _schema_info(s)
            for c in summary.channels.values():
                self._add_channel(c)
        if summary is None or not summary.channels:
            if (summary is not None and summary.chunk_indexes) or "CRC" in why or "parse" in why or "outside" in why:
                self.report.index_damaged = True
            if why.startswith("no footer"):
                self.report.truncated = True
            self.summary = None
            self.warn(f"{self.path}: {why or 'the summary lists no channels'}: reading the data sequentially")
            self._scan_channels()
            return
        if not summary.chunk_indexes:
            return  # unchunked file (or no messages): read sequentially, channels from the summary
        walked, damage = self._walk_chunks(summary_start)
        index = {ci.chunk_start_offset: ci for ci in summary.chunk_indexes}
        differ = [o for o, r in walked.items() if o in index and (
            index[o].chunk_length != r.index_length or index[o].message_start_time != r.start
            or index[o].message_end_time != r.end)]
        if damage is None and set(walked) == set(index) and not self._top_messages and not differ:
            self._indexed = True
            return
        self.report.index_damaged = True
        reasons: list[str] = []
        if damage is not None:
            reasons.append(f"the data section is damaged {damage_place(self._fh, damage.pos, self._size)} ({damage.reason})")
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
        if self._top_messages:
            reasons.append(f"{self._top_messages} message(s) lie outside chunks")
        self.warn(f"{self.path}: the chunk index and the data section disagree ({'; '.join(reasons)}): reading the data instead")
        if self._top_messages:
            self.summary = None  # messages outside chunks: only a sequential read finds them all
            return
        refs = {o: _ChunkRef(r.offset, r.start, r.end) for o, r in walked.items()}
        for off in bogus:  # past damage the index may still lead to intact chunks: try them
            ci = index[off]
            refs[off] = _ChunkRef(off, ci.message_start_time, ci.message_end_time, ci.chunk_length)
        self._chunks = sorted(refs.values(), key=lambda r: r.offset)

    def _walk_chunks(self, end: int) -> tuple[dict[int, _ChunkRef], _Damage | None]:
        """Chunk records of the data section by their headers alone (bodies are skipped), up to
        the DataEnd record or byte ``end``; the damage that stopped the walk, if any."""
        found: dict[int, _ChunkRef] = {}
        pos = len(MAGIC)
        try:
            while pos < end:
                op, n = self._head(pos)
                if op not in _KNOWN and op < 0x80:
                    raise _Damage(pos, f"no valid record at byte {pos} (opcode {op:#04x})")
                if pos + 9 + n > end:
                    raise _Damage(pos, f"record at byte {pos} claims {n} bytes, past the data section")
                if op == _CHUNK:
                    head = self._fh.read(min(n, _CHUNK_HEAD))
                    if len(head) < _CHUNK_HEAD:
                        raise _Damage(pos, "chunk record is too short")
                    s, e = struct.unpack_from("<QQ", head, 0)
                    found[pos] = _ChunkRef(pos, s, e, 9 + n)
                elif op == _MESSAGE:
                    self._top_messages += 1
                elif op == _DATA_END or op == _FOOTER:
                    break
                pos += 9 + n
        except _Damage as exc:
            return found, exc
        return found, None

    def close(self) -> None:
        self._fh.close()

    def _add_channel(self, c: Channel) -> ChannelInfo:
        info = ChannelInfo(c.id, c.topic, c.message_encoding, self._schemas.get(c.schema_id), dict(c.metadata))
        self._channels[c.id] = info
        return info

    def _scan_channels(self) -> None:
        for _ in self._sequential(None, None, None, want_messages=False):
            pass

    # -- listing ----------------------------------------------------------------
    def channels(self) -> list[ChannelInfo]:
        return list(self._channels.values())

    def message_counts(self) -> dict[int, int] | None:
        if self.summary is not None and self.summary.statistics is not None and self._indexed:
            return dict(self.summary.statistics.channel_message_counts)
        return None

    def checksums(self) -> str:
        if self.summary is not None and self._indexed and self.summary.chunk_indexes and not self._chunks_crc:
            return "unknown"
        if self._chunks_crc and all(self._chunks_crc):
            return "all"
        if any(self._chunks_crc):
            return "some"
        return "none"

    def topic_times(self, topic: str) -> Any:
        """Log times of ``topic`` from the MessageIndex records the chunk index points to (no
        chunk is decompressed); None when the index is not trusted or has no message indexes."""
        import numpy as np

        if not self._indexed or self.summary is None:
            return None
        ids = {c.id for c in self._channels.values() if c.topic == topic}
        parts: list[Any] = []
        counts = self.message_counts() or {}
        for ci in self.summary.chunk_indexes:
            for cid, off in ci.message_index_offsets.items():
                if cid not in ids:
                    continue
                try:
                    op, n = self._head(off)
                    body = self._fh.read(n) if op == _MESSAGE_INDEX and 6 <= n <= self._size else b""
                    got_cid, rlen = struct.unpack_from("<HI", body, 0) if len(body) >= 6 else (-1, 0)
                except _Damage:
                    return None
                if got_cid != cid or rlen % 16 or 6 + rlen > len(body):
                    return None
                parts.append(np.frombuffer(body, dtype="<u8", offset=6, count=rlen // 8)[0::2])
        times = np.sort(np.concatenate(parts)).astype(np.int64) if parts else np.zeros(0, np.int64)
        if counts and len(times) != sum(counts.get(i, 0) for i in ids):
            return None  # the message indexes and the statistics disagree: no exact times
        return times

    def _fill_time_range(self, info: LogInfo) -> None:
        if self.summary is None or not self._indexed:
            return
        # per-topic ranges come from the chunk index only approximately; overall range is exact
        st = self.summary.statistics
        if st is not None and st.message_count:
            info.start_ns, info.end_ns = st.message_start_time, st.message_end_time
        ranges: dict[int, list[int]] = {}
        for ci in self.summary.chunk_indexes:
            for cid in ci.message_index_offsets:
                r = ranges.setdefault(cid, [ci.message_start_time, ci.message_end_time])
                r[0] = min(r[0], ci.message_start_time)
                r[1] = max(r[1], ci.message_end_time)
        for t in info.topics:
            for c in self._channels.values():
                if c.topic == t.topic and c.id in ranges:
                    lo, hi = ranges[c.id]
                    t.start_ns = lo if t.start_ns is None else min(t.start_ns, lo)
                    t.end_ns = hi if t.end_ns is None else max(t.end_ns, hi)

    # -- messages ---------------------------------------------------------------
    def _iter_messages(
        self, topics: set[str] | None, start_ns: int | None, end_ns: int | None, log_time_order: bool
    ) -> Iterator[RawMessage]:
        ids = None if topics is None else {c.id for c in self._channels.values() if c.topic in topics}
        if self._indexed:
            assert self.summary is not None
            refs = [
                _ChunkRef(ci.chunk_start_offset, ci.message_start_time, ci.message_end_time, ci.chunk_length)
                for ci in self.summary.chunk_indexes
                if ids is None or not ci.message_index_offsets or ids & set(ci.message_index_offsets)
            ]
            yield from self._chunked_messages(refs, ids, start_ns, end_ns, log_time_order)
        elif self._chunks is not None:
            yield from self._chunked_messages(self._chunks, ids, start_ns, end_ns, log_time_order)
        else:
            yield from self._sequential(ids, start_ns, end_ns, want_messages=True)

    def _read_chunk(self, ref: _ChunkRef) -> list[Message] | None:
        """Messages of the chunk at ``ref.offset`` (schemas and channels registered); None when it
        is damaged (reported)."""
        pos = ref.offset
        try:
            op, n = self._head(pos)
            if op != _CHUNK:
                raise _Damage(pos, f"no chunk record at byte {pos} (opcode {op:#04x})")
            lengths = [n] + ([ref.index_length - 9] if ref.index_length and ref.index_length - 9 != n else [])
            err: _Damage | None = None
            for length in lengths:  # the record's own length first; the index's if that fails
                if length < 0 or pos + 9 + length > self._size or length > MAX_CHUNK_BYTES:
                    err = _Damage(pos, f"chunk at byte {pos} claims {length} bytes, past the end of the file")
                    continue
                self._fh.seek(pos + 9)
                try:
                    records, checked = _chunk_records(self._fh.read(length), pos, self.validate_crcs)
                except _Damage as exc:
                    err = exc
                    continue
                self._chunks_crc.append(checked)
                return self._absorb(records)
            assert err is not None
            raise err
        except _Damage as exc:
            self.report.skipped_chunks += 1
            self.warn(f"{self.path}: chunk at byte {pos} is damaged: {exc.reason}; "
                      f"skipped its messages (log time {ref.start}..{ref.end})")
            return None

    def _absorb(self, records: list[Any]) -> list[Message]:
        """Register the schemas and channels among ``records``; return their messages. A channel
        record in the data wins over a summary that says otherwise (reported)."""
        out = []
        for r in records:
            if isinstance(r, Schema):
                self._schemas.setdefault(r.id, _schema_info(r))
            elif isinstance(r, Channel):
                if r.id not in self._data_channels:
                    self._data_channels.add(r.id)
                    old = self._channels.get(r.id)
                    new = ChannelInfo(r.id, r.topic, r.message_encoding, self._schemas.get(r.schema_id),
                                      dict(r.metadata))
                    if old is not None and (old.topic, old.message_encoding, old.schema) != (
                            new.topic, new.message_encoding, new.schema):
                        self.report.index_damaged = True
                        self.warn(f"{self.path}: the summary describes channel {r.id} as {old.topic!r}, the data "
                                  f"as {r.topic!r}: using the data's")
                    if old is None or old != new:
                        self._channels[r.id] = new
            elif isinstance(r, Message):
                out.append(r)
        return out

    def _raw(self, m: Message) -> RawMessage | None:
        ch = self._channels.get(m.channel_id)
        if ch is None:
            self.report.bad_messages += 1
            self.warn(f"{self.path}: message on unknown channel id {m.channel_id} at log time {m.log_time}: skipped")
            return None
        return RawMessage(ch, m.log_time, m.publish_time, m.sequence, bytes(m.data))

    def _chunked_messages(
        self, refs: list[_ChunkRef], ids: set[int] | None, start_ns: int | None, end_ns: int | None,
        log_time_order: bool,
    ) -> Iterator[RawMessage]:
        chunks = [r for r in refs if (start_ns is None or r.end >= start_ns) and (end_ns is None or r.start < end_ns)]
        if not log_time_order:
            chunks.sort(key=lambda c: c.offset)
            for ref in chunks:
                for m in self._read_chunk(ref) or []:
                    if self._keep(m, ids, start_ns, end_ns):
                        r = self._raw(m)
                        if r is not None:
                            yield r
            return
        chunks.sort(key=lambda c: (c.start, c.offset))
        heap: list[tuple[int, int, int, Message]] = []
        order = 0
        i = 0
        while i < len(chunks) or heap:
            # load every chunk that may hold a message earlier than the heap's head
            while i < len(chunks) and (not heap or chunks[i].start <= heap[0][0]):
                for m in self._read_chunk(chunks[i]) or []:
                    if self._keep(m, ids, start_ns, end_ns):
                        heapq.heappush(heap, (m.log_time, i, order, m))
                        order += 1
                i += 1
            if heap:
                m = heapq.heappop(heap)[3]
                r = self._raw(m)
                if r is not None:
                    yield r

    @staticmethod
    def _keep(m: Message, ids: set[int] | None, start_ns: int | None, end_ns: int | None) -> bool:
        return (
            (ids is None or m.channel_id in ids)
            and (start_ns is None or m.log_time >= start_ns)
            and (end_ns is None or m.log_time < end_ns)
        )

    def _records(self, kinds: set[int]) -> Iterator[tuple[int, int, bytes]]:
        """(offset, opcode, body) of the top-level records of the data section whose opcode is in
        ``kinds`` (other bodies are skipped by seeking), up to DataEnd/Footer; damage ends it with a
        warning that says where (a zero-filled tail from where the zeros start)."""
        pos = len(MAGIC)
        size = self._size
        try:
            while True:
                if pos == size:
                    raise _Damage(pos, "the file ends before its DataEnd record and footer")
                op, n = self._head(pos)
                if op not in _KNOWN and op < 0x80:
                    raise _Damage(pos, f"no valid record (opcode {op:#04x})")
                if pos + 9 + n > size:
                    raise _Damage(pos, f"a record claims {n} bytes, past the end of the file")
                if op == _DATA_END or op == _FOOTER:
                    return
                if op in kinds:
                    if n > MAX_CHUNK_BYTES:
                        raise _Damage(pos, f"a record claims {n} bytes")
                    self._fh.seek(pos + 9)
                    yield pos, op, self._fh.read(n)
                pos += 9 + n
        except _Damage as exc:
            rep = self.report
            rep.truncated = True
            if not self._damage_told:
                self._damage_told = True
                rep.bytes_read = exc.pos
                self.warn(f"{self.path}: log is truncated or damaged {damage_place(self._fh, exc.pos, size)} "
                          f"({exc.reason}); read everything before it")

    def _sequential(
        self, ids: set[int] | None, start_ns: int | None, end_ns: int | None, want_messages: bool
    ) -> Iterator[RawMessage]:
        """File-order scan up to the damage; chunks' messages merged into log-time order."""

        def groups() -> Iterator[list[tuple[int, RawMessage]]]:
            for pos, op, body in self._records({_SCHEMA, _CHANNEL, _MESSAGE, _CHUNK}):
                try:
                    if op == _SCHEMA:
                        self._absorb([_parse(Schema, body, pos)])
                    elif op == _CHANNEL:
                        self._absorb([_parse(Channel, body, pos)])
                    elif op == _MESSAGE:
                        if want_messages:
                            yield self._group([_parse(Message, body, pos)], ids, start_ns, end_ns)
                    else:
                        recs, checked = _chunk_records(body, pos, self.validate_crcs)
                        self._chunks_crc.append(checked)
                        msgs = self._absorb(recs)
                        if want_messages:
                            yield self._group(msgs, ids, start_ns, end_ns)
                except _Damage as exc:
                    self.report.skipped_chunks += 1
                    self.warn(f"{self.path}: {'chunk' if op == _CHUNK else 'record'} at byte {pos} is damaged: "
                              f"{exc.reason}; skipped")

        yield from merge_groups(groups())

    def _group(self, msgs: list[Message], ids: set[int] | None, start_ns: int | None,
               end_ns: int | None) -> list[tuple[int, RawMessage]]:
        out = []
        for m in msgs:
            if self._keep(m, ids, start_ns, end_ns):
                r = self._raw(m)
                if r is not None:
                    out.append((m.log_time, r))
        return out

    # -- metadata / attachments ----------------------------------------------------
    def metadata(self) -> Iterator[tuple[str, dict[str, str]]]:
        for pos, _op, body in self._records({_METADATA}):
            try:
                m = _parse(Metadata, body, pos)
            except _Damage as exc:
                self.report.bad_messages += 1
                self.warn(f"{self.path}: metadata record at byte {pos} is damaged ({exc.reason}); skipped")
                continue
            yield m.name, dict(m.metadata)

    def attachments(self) -> Iterator[Attachment]:
        for pos, _op, body in self._records({_ATTACHMENT}):
            try:
                a = _parse(McapAttachment, body, pos)
            except _Damage as exc:
                self.report.bad_messages += 1
                self.warn(f"{self.path}: attachment record at byte {pos} is damaged ({exc.reason}); skipped")
                continue
            yield Attachment(a.name, a.media_type, a.log_time, a.create_time, bytes(a.data))


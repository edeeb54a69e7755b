"""MCAP reader: any profile, streamed chunk by chunk, robust to damage.

With a summary section, chunks are read through the chunk index and merged in log-time
order (only chunks that overlap in time are held at once, so memory stays bounded).
Without one (a truncated or unindexed file) the file is read sequentially up to the
damage. A chunk whose CRC does not match is reported and skipped; the rest is read.
"""

from __future__ import annotations

import heapq
import io
import os
from collections.abc import Iterator
from typing import IO, Any

from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.reader import make_reader
from mcap.records import Attachment as McapAttachment
from mcap.records import Channel, Chunk, ChunkIndex, Footer, Header, Message, Metadata, Schema
from mcap.stream_reader import CRCValidationError, StreamReader, breakup_chunk
from mcap.summary import Summary

from memlog.errors import LogReadError
from memlog.io.base import LogReader
from memlog.io.records import Attachment, ChannelInfo, RawMessage, SchemaInfo
from memlog.io.types import LogInfo

__all__ = ["McapLog"]

MAGIC = b"\x89MCAP0\r\n"
_RECORD_LIMIT = 1 << 31


def _schema_info(s: Schema | None) -> SchemaInfo | None:
    if s is None or s.id == 0:
        return None
    return SchemaInfo(s.name, s.encoding, bytes(s.data))


def _why(exc: BaseException) -> str:
    from mcap.exceptions import EndOfFile

    if isinstance(exc, EndOfFile):
        return "the file ends in the middle of a record"
    return f"{type(exc).__name__}: {exc}"


class McapLog(LogReader):
    """An MCAP file opened for streaming (see :func:`memlog.io.open_log`)."""

    format = "mcap"

    def __init__(self, path: str | os.PathLike[str], validate_crcs: bool = True) -> None:
        super().__init__(path)
        self.validate_crcs = validate_crcs
        try:
            self._fh: IO[bytes] = open(self.path, "rb")
        except OSError as exc:
            raise LogReadError(f"{self.path}: cannot open: {exc.strerror}") from exc
        if self._fh.read(len(MAGIC)) != MAGIC:
            self._fh.close()
            raise LogReadError(f"{self.path}: not an MCAP file (bad magic)")
        self._fh.seek(0)
        self.header: Header | None = None
        self.summary: Summary | None = None
        try:
            reader = make_reader(self._fh, validate_crcs=False)
            self.header = reader.get_header()
            self.summary = reader.get_summary()
        except Exception:  # missing or damaged footer/summary: fall back to a sequential scan
            self.summary = None
        if self.summary is not None and self.summary.statistics is None and not self.summary.chunk_indexes:
            # A summary without chunk indexes (unchunked file) cannot drive indexed reads.
            self._indexed = False
        else:
            self._indexed = self.summary is not None and bool(self.summary.chunk_indexes)
        if self.header is None:
            self.header = self._read_header()
        self.profile = self.header.profile if self.header else ""
        self._schemas: dict[int, SchemaInfo | None] = {}
        self._channels: dict[int, ChannelInfo] = {}
        self._scanned = False
        if self.summary is not None and self.summary.channels:
            for sid, s in self.summary.schemas.items():
                self._schemas[sid] = _schema_info(s)
            for cid, c in self.summary.channels.items():
                self._add_channel(c)
        else:
            self.warn(f"{self.path}: no summary section (truncated or unindexed MCAP): reading sequentially")
            self._scan_channels()

    def _read_header(self) -> Header | None:
        self._fh.seek(0)
        try:
            for rec in StreamReader(self._fh, emit_chunks=True).records:
                if isinstance(rec, Header):
                    return rec
                break
        except Exception:
            return None
        return None

    def close(self) -> None:
        self._fh.close()

    def _add_channel(self, c: Channel) -> ChannelInfo:
        info = ChannelInfo(c.id, c.topic, c.message_encoding, self._schemas.get(c.schema_id), dict(c.metadata))
        self._channels[c.id] = info
        return info

    def _scan_channels(self) -> None:
        for _ in self._sequential(None, None, None, want_messages=False):
            pass
        self._scanned = True

    # -- listing ----------------------------------------------------------------
    def channels(self) -> list[ChannelInfo]:
        return list(self._channels.values())

    def message_counts(self) -> dict[int, int] | None:
        if self.summary is not None and self.summary.statistics is not None and self._indexed:
            return dict(self.summary.statistics.channel_message_counts)
        return None

    def _fill_time_range(self, info: LogInfo) -> None:
        if self.summary is None or not self.summary.chunk_indexes:
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
            yield from self._indexed_messages(ids, start_ns, end_ns, log_time_order)
        else:
            yield from self._sequential(ids, start_ns, end_ns, want_messages=True)

    def _read_chunk(self, ci: ChunkIndex) -> list[Message] | None:
        try:
            self._fh.seek(ci.chunk_start_offset)
            buf = self._fh.read(ci.chunk_length)
            if len(buf) < ci.chunk_length:
                raise EOFError("chunk extends past the end of the file")
            if buf[0] != Opcode.CHUNK:
                raise ValueError(f"no chunk record at byte {ci.chunk_start_offset}")
            chunk = Chunk.read(ReadDataStream(io.BytesIO(buf[9:])))
            records = breakup_chunk(chunk, validate_crc=self.validate_crcs)
        except CRCValidationError as exc:
            self.report.skipped_chunks += 1
            self.warn(
                f"{self.path}: chunk at byte {ci.chunk_start_offset} fails its CRC check ({exc}); "
                f"skipped its messages (log time {ci.message_start_time}..{ci.message_end_time})"
            )
            return None
        except Exception as exc:
            self.report.skipped_chunks += 1
            self.warn(
                f"{self.path}: chunk at byte {ci.chunk_start_offset} is damaged ({type(exc).__name__}: {exc}); "
                f"skipped its messages (log time {ci.message_start_time}..{ci.message_end_time})"
            )
            return None
        return self._absorb(records)

    def _absorb(self, records: list[Any]) -> list[Message]:
        """Register the schemas and channels among ``records``; return their messages."""
        out = []
        for r in records:
            if isinstance(r, Schema):
                self._schemas.setdefault(r.id, _schema_info(r))
            elif isinstance(r, Channel):
                if r.id not in self._channels:
                    self._add_channel(r)
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

    def _indexed_messages(
        self, ids: set[int] | None, start_ns: int | None, end_ns: int | None, log_time_order: bool
    ) -> Iterator[RawMessage]:
        assert self.summary is not None
        chunks = [
            ci
            for ci in self.summary.chunk_indexes
            if (ids is None or not ci.message_index_offsets or ids & set(ci.message_index_offsets))
            and (start_ns is None or ci.message_end_time >= start_ns)
            and (end_ns is None or ci.message_start_time < end_ns)
        ]
        if not log_time_order:
            chunks.sort(key=lambda c: c.chunk_start_offset)
            for ci in chunks:
                for m in self._read_chunk(ci) or []:
                    if self._keep(m, ids, start_ns, end_ns):
                        r = self._raw(m)
                        if r is not None:
                            yield r
            return
        chunks.sort(key=lambda c: (c.message_start_time, c.chunk_start_offset))
        heap: list[tuple[int, int, int, Message]] = []
        order = 0
        i = 0
        while i < len(chunks) or heap:
            # load every chunk that may hold a message earlier than the heap's head
            while i < len(chunks) and (not heap or chunks[i].message_start_time <= heap[0][0]):
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

    def _sequential(
        self, ids: set[int] | None, start_ns: int | None, end_ns: int | None, want_messages: bool
    ) -> Iterator[RawMessage]:
        """File-order scan; stops with a warning at the first damaged record."""
        self._fh.seek(0)
        reader = StreamReader(self._fh, emit_chunks=True, record_size_limit=_RECORD_LIMIT)
        try:
            for rec in reader.records:
                if isinstance(rec, (Schema, Channel)):
                    self._absorb([rec])
                elif isinstance(rec, Chunk):
                    try:
                        inner = breakup_chunk(rec, validate_crc=self.validate_crcs)
                    except Exception as exc:
                        self.report.skipped_chunks += 1
                        self.warn(f"{self.path}: chunk before byte {self._fh.tell()} is damaged ({exc}); skipped")
                        continue
                    msgs = self._absorb(inner)
                    if want_messages:
                        msgs.sort(key=lambda m: m.log_time)
                        for m in msgs:
                            if self._keep(m, ids, start_ns, end_ns):
                                raw = self._raw(m)
                                if raw is not None:
                                    yield raw
                elif isinstance(rec, Message):
                    if want_messages and self._keep(rec, ids, start_ns, end_ns):
                        raw = self._raw(rec)
                        if raw is not None:
                            yield raw
                elif isinstance(rec, Footer):
                    break
        except (McapError, EOFError, ValueError, OSError, MemoryError, Exception) as exc:
            pos = self._fh.tell()
            if not self.report.truncated:
                self.report.truncated = True
                self.report.bytes_read = pos
                self.warn(
                    f"{self.path}: log is truncated or damaged near byte {pos} of {self.size_bytes} "
                    f"({_why(exc)}); read everything before it"
                )

    # -- metadata / attachments ----------------------------------------------------
    def _sequential_records(self, kind: type) -> Iterator[Any]:
        self._fh.seek(0)
        try:
            for rec in StreamReader(self._fh, emit_chunks=True, record_size_limit=_RECORD_LIMIT).records:
                if isinstance(rec, kind):
                    yield rec
        except Exception:
            return

    def metadata(self) -> Iterator[tuple[str, dict[str, str]]]:
        if self.summary is not None and self.summary.metadata_indexes:
            try:
                self._fh.seek(0)
                reader = make_reader(self._fh)
                for m in reader.iter_metadata():
                    yield m.name, dict(m.metadata)
                return
            except Exception as exc:
                self.warn(f"{self.path}: metadata index unreadable ({exc}); scanning the file")
        for m in self._sequential_records(Metadata):
            yield m.name, dict(m.metadata)

    def attachments(self) -> Iterator[Attachment]:
        if self.summary is not None and self.summary.attachment_indexes:
            try:
                self._fh.seek(0)
                reader = make_reader(self._fh)
                for a in reader.iter_attachments():
                    yield Attachment(a.name, a.media_type, a.log_time, a.create_time, bytes(a.data))
                return
            except Exception as exc:
                self.warn(f"{self.path}: attachment index unreadable ({exc}); scanning the file")
        for a in self._sequential_records(McapAttachment):
            yield Attachment(a.name, a.media_type, a.log_time, a.create_time, bytes(a.data))

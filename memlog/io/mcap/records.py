"""MCAP records from bytes, checked: the opcodes, the damage a record can show, chunk references
and the records inside a chunk (the building blocks of :mod:`memlog.io.mcap.reader`)."""

from __future__ import annotations

import io
import struct
import zlib
from dataclasses import dataclass
from typing import Any

import numpy as np
from mcap.data_stream import ReadDataStream
from mcap.records import Channel, Message, Schema

from memlog.io._damage import decompress
from memlog.io.frame_table import FrameTable
from memlog.io.records import SchemaInfo

__all__ = ["MAGIC", "FOOTER_LEN", "KNOWN_OPS", "CHUNK_HEAD", "OP_HEADER", "OP_FOOTER", "OP_SCHEMA", "OP_CHANNEL",
           "OP_MESSAGE", "OP_CHUNK", "OP_MESSAGE_INDEX", "OP_CHUNK_INDEX", "OP_ATTACHMENT", "OP_METADATA",
           "OP_DATA_END", "OP_STATISTICS", "RecordDamage", "ChunkRef", "schema_info", "parse_record",
           "chunk_records", "chunk_data", "records_of", "frame_table_of", "attachment_crc"]

MAGIC = b"\x89MCAP0\r\n"
FOOTER_LEN = 1 + 8 + 8 + 8 + 4  # opcode, length, summary_start, summary_offset_start, summary_crc
# opcodes
OP_HEADER, OP_FOOTER, OP_SCHEMA, OP_CHANNEL, OP_MESSAGE, OP_CHUNK = 0x01, 0x02, 0x03, 0x04, 0x05, 0x06
OP_MESSAGE_INDEX, OP_CHUNK_INDEX, OP_ATTACHMENT, OP_METADATA, OP_DATA_END = 0x07, 0x08, 0x09, 0x0C, 0x0F
OP_STATISTICS = 0x0B
KNOWN_OPS = set(range(0x01, 0x10))
CHUNK_HEAD = 8 + 8 + 8 + 4 + 4  # start, end, uncompressed size, crc, compression length


class RecordDamage(Exception):
    """A record that cannot be what it claims (reported by the reader with its byte offset)."""

    def __init__(self, pos: int, reason: str) -> None:
        super().__init__(reason)
        self.pos, self.reason = pos, reason


@dataclass(frozen=True)
class ChunkRef:
    """A chunk record found in the data (or an index entry to try), or a message record outside
    chunks (``op`` 0x05): offset and log-time range."""

    offset: int
    start: int
    end: int
    index_length: int = 0  # the length the chunk index gives (used only if the record's own fails)
    op: int = OP_CHUNK


def schema_info(s: Schema | None) -> SchemaInfo | None:
    if s is None or s.id == 0:
        return None
    return SchemaInfo(s.name, s.encoding, bytes(s.data), s.id)


def parse_record(cls: Any, body: bytes, pos: int) -> Any:
    try:
        stream = ReadDataStream(io.BytesIO(body))
        rec = cls.read(stream, len(body)) if cls is Message else cls.read(stream)
    except Exception as exc:  # noqa: BLE001 - garbage bytes fail in many ways; all mean damage here
        raise RecordDamage(pos, f"{cls.__name__} record does not parse ({type(exc).__name__}: {exc})") from None
    if stream.count > len(body):
        raise RecordDamage(pos, f"{cls.__name__} record is longer than its length field")
    return rec


def attachment_crc(body: bytes, a: Any, pos: int) -> str:
    """The CRC that ends attachment ``a`` (parsed from its record ``body`` at ``pos``; it covers
    every field before it): "held", or "absent" when it is 0. Raises :class:`RecordDamage` when it
    fails (the ``mcap`` library does not check it)."""
    end = 8 + 8 + 4 + len(a.name.encode()) + 4 + len(a.media_type.encode()) + 8 + len(a.data)
    (crc,) = struct.unpack_from("<I", body, end)
    if crc == 0:
        return "absent"
    got = zlib.crc32(body[:end])
    if got != crc:
        raise RecordDamage(pos, f"attachment {a.name!r} fails its CRC check (expected {crc:#010x}, got {got:#010x})")
    return "held"


def chunk_records(body: bytes, pos: int, validate_crc: bool) -> tuple[list[tuple[int, Any]], bool]:
    """Schema, Channel and Message records of the chunk record ``body`` (at byte ``pos``), each
    with its offset in the chunk's uncompressed records, and whether the CRC was checked. Raises
    :class:`RecordDamage`."""
    data, checked = chunk_data(body, pos, validate_crc)
    return records_of(data, pos), checked


def chunk_data(body: bytes, pos: int, validate_crc: bool) -> tuple[bytes, bool]:
    """The uncompressed records of the chunk record ``body`` (at byte ``pos``), and whether the CRC
    was checked. Raises :class:`RecordDamage`."""
    if len(body) < CHUNK_HEAD + 8:
        raise RecordDamage(pos, "chunk record is too short")
    start, end, size, crc, clen = struct.unpack_from("<QQQII", body, 0)
    at = CHUNK_HEAD
    try:
        compression = body[at : at + clen].decode()
    except UnicodeDecodeError:
        raise RecordDamage(pos, "chunk compression name is not text") from None
    at += clen
    if at + 8 > len(body):
        raise RecordDamage(pos, "chunk record is too short")
    (dlen,) = struct.unpack_from("<Q", body, at)
    at += 8
    if at + dlen > len(body):
        raise RecordDamage(pos, f"chunk data length {dlen} is longer than the record")
    try:
        data = decompress(compression, body[at : at + dlen], size)
    except Exception as exc:  # noqa: BLE001 - zstd/lz4 errors have no common base
        raise RecordDamage(pos, f"chunk does not decompress ({type(exc).__name__}: {exc})") from None
    checked = validate_crc and crc != 0
    if checked and zlib.crc32(data) != crc:
        raise RecordDamage(pos, f"chunk fails its CRC check (expected {crc:#010x}, got {zlib.crc32(data):#010x})")
    return bytes(data), checked


def records_of(data: bytes, pos: int) -> list[tuple[int, Any]]:
    """Schema, Channel and Message records of a chunk's uncompressed records ``data`` (the chunk at
    byte ``pos``), each with its offset in ``data``. Raises :class:`RecordDamage`."""
    out: list[tuple[int, Any]] = []
    at = 0
    while at < len(data):
        if at + 9 > len(data):
            raise RecordDamage(pos, "chunk ends inside a record header")
        op, n = data[at], struct.unpack_from("<Q", data, at + 1)[0]
        if at + 9 + n > len(data):
            raise RecordDamage(pos, "a record in the chunk is longer than the chunk")
        body_i = data[at + 9 : at + 9 + n]
        if op == OP_MESSAGE:
            out.append((at, parse_record(Message, body_i, pos)))
        elif op == OP_CHANNEL:
            out.append((at, parse_record(Channel, body_i, pos)))
        elif op == OP_SCHEMA:
            out.append((at, parse_record(Schema, body_i, pos)))
        at += 9 + n
    return out




def frame_table_of(entries: list[tuple[int, int, int]]) -> FrameTable:
    a = np.asarray(entries, dtype=np.int64).reshape(-1, 3)
    return FrameTable(a[:, 0], a[:, 1], a[:, 2])

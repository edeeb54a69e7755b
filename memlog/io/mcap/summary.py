"""The MCAP summary section: found through the footer, checked against its CRC and parsed record
by record; one that fails any of it is not used (:mod:`memlog.io.mcap.reader` then reads the data)."""

from __future__ import annotations

import struct
import zlib
from typing import IO

from mcap.records import Channel, ChunkIndex, Schema, Statistics
from mcap.summary import Summary

from memlog.io.mcap.records import (
    FOOTER_LEN,
    KNOWN_OPS,
    MAGIC,
    OP_CHANNEL,
    OP_CHUNK_INDEX,
    OP_FOOTER,
    OP_SCHEMA,
    OP_STATISTICS,
    RecordDamage,
    parse_record,
)

__all__ = ["read_summary"]


def read_summary(fh: IO[bytes], size: int) -> tuple[Summary | None, int, str]:
    """The summary section of the MCAP file open as ``fh`` (``size`` bytes), read through the
    footer and checked (its CRC, every record parses): (summary, summary_start, why it is not
    used); the summary is None when it cannot be used."""
    if size < len(MAGIC) * 2 + FOOTER_LEN:
        return None, 0, "the file is too short to hold a footer"
    fh.seek(size - len(MAGIC) - FOOTER_LEN)
    tail = fh.read(FOOTER_LEN + len(MAGIC))
    if tail[-len(MAGIC):] != MAGIC or tail[0] != OP_FOOTER:
        return None, 0, "no footer at the end (truncated or unfinished recording)"
    start, offset_start, crc = struct.unpack_from("<QQI", tail, 9)
    if start == 0:
        return None, 0, "no summary section (unindexed MCAP)"
    footer_pos = size - len(MAGIC) - FOOTER_LEN
    if not len(MAGIC) < start <= footer_pos:
        return None, 0, f"the footer points to a summary at byte {start}, outside the file"
    fh.seek(start)
    blob = fh.read(footer_pos - start)
    if crc != 0:
        got = zlib.crc32(tail[: FOOTER_LEN - 4], zlib.crc32(blob))
        if got != crc:
            return None, start, f"the summary section fails its CRC check (expected {crc:#010x}, got {got:#010x})"
    summary = Summary()
    at = 0
    try:
        while at < len(blob):
            if at + 9 > len(blob):
                raise RecordDamage(start + at, "summary ends inside a record header")
            op, n = blob[at], struct.unpack_from("<Q", blob, at + 1)[0]
            if op not in KNOWN_OPS and op < 0x80 or at + 9 + n > len(blob):
                raise RecordDamage(start + at, f"summary record (opcode {op:#04x}, length {n}) is not valid")
            body = blob[at + 9 : at + 9 + n]
            if op == OP_SCHEMA:
                s = parse_record(Schema, body, start + at)
                summary.schemas[s.id] = s
            elif op == OP_CHANNEL:
                c = parse_record(Channel, body, start + at)
                summary.channels[c.id] = c
            elif op == OP_CHUNK_INDEX:
                summary.chunk_indexes.append(parse_record(ChunkIndex, body, start + at))
            elif op == OP_STATISTICS:
                summary.statistics = parse_record(Statistics, body, start + at)
            at += 9 + n
    except RecordDamage as exc:
        return None, start, f"the summary section does not parse ({exc.reason})"
    return summary, start, ""

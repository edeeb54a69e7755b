"""The MCAP summary section: found through the footer, checked against the footer's summary CRC
and parsed by the ``mcap`` library's record reader; one that fails either is not used
(:mod:`memlog.io.mcap.reader` then reads the data). Every part of a summary is optional: one that
repeats no channels or schemas, or has no chunk index, is valid."""

from __future__ import annotations

import io
import struct
import zlib
from typing import IO, NamedTuple

from mcap.records import AttachmentIndex, Channel, ChunkIndex, Footer, MetadataIndex, Schema, Statistics
from mcap.stream_reader import StreamReader
from mcap.summary import Summary

from memlog.io.mcap.records import FOOTER_LEN, MAGIC, OP_FOOTER

__all__ = ["read_summary", "SummaryRead"]


class SummaryRead(NamedTuple):
    """What :func:`read_summary` found: the ``summary`` (None when it cannot be used), where it
    starts, ``why`` it is not used ("" when it is), and its ``crc``: "held", "failed", "absent"
    (the footer gives none) or "none" (there is no summary)."""

    summary: Summary | None
    start: int
    why: str
    crc: str


def read_summary(fh: IO[bytes], size: int) -> SummaryRead:
    """The summary section of the MCAP file open as ``fh`` (``size`` bytes), read through the
    footer and checked (its CRC, every record parses)."""
    if size < len(MAGIC) * 2 + FOOTER_LEN:
        return SummaryRead(None, 0, "the file is too short to hold a footer", "none")
    fh.seek(size - len(MAGIC) - FOOTER_LEN)
    tail = fh.read(FOOTER_LEN + len(MAGIC))
    if tail[-len(MAGIC):] != MAGIC or tail[0] != OP_FOOTER:
        return SummaryRead(None, 0, "no footer at the end (truncated or unfinished recording)", "none")
    start, _offset_start, crc = struct.unpack_from("<QQI", tail, 9)
    if start == 0:
        return SummaryRead(None, 0, "no summary section (unindexed MCAP)", "none")
    footer_pos = size - len(MAGIC) - FOOTER_LEN
    if not len(MAGIC) < start <= footer_pos:
        return SummaryRead(None, 0, f"the footer points to a summary at byte {start}, outside the file", "none")
    fh.seek(start)
    blob = fh.read(footer_pos - start)
    if crc != 0:
        got = zlib.crc32(tail[: FOOTER_LEN - 4], zlib.crc32(blob))
        if got != crc:
            return SummaryRead(None, start, f"the summary section fails its CRC check (expected {crc:#010x}, got "
                               f"{got:#010x})", "failed")
    summary = Summary()
    try:
        for rec in StreamReader(io.BytesIO(blob + tail), skip_magic=True, record_size_limit=len(blob) + 1).records:
            if isinstance(rec, Schema):
                summary.schemas[rec.id] = rec
            elif isinstance(rec, Channel):
                summary.channels[rec.id] = rec
            elif isinstance(rec, ChunkIndex):
                summary.chunk_indexes.append(rec)
            elif isinstance(rec, AttachmentIndex):
                summary.attachment_indexes.append(rec)
            elif isinstance(rec, MetadataIndex):
                summary.metadata_indexes.append(rec)
            elif isinstance(rec, Statistics):
                summary.statistics = rec
            elif isinstance(rec, Footer):
                break
    except Exception as exc:  # noqa: BLE001 - garbage bytes fail in many ways; all mean damage here
        return SummaryRead(None, start, f"the summary section does not parse ({type(exc).__name__}: {exc})",
                           "held" if crc else "absent")
    return SummaryRead(summary, start, "", "held" if crc else "absent")

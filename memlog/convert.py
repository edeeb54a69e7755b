"""Pipeline step: any log -> indexed, compressed MCAP holding every input record.

MCAP input keeps its profile, schemas, channels, messages (bytes, log time, publish time,
sequence), metadata and attachments. A ROS 1 bag becomes a ``ros1`` profile MCAP
(``ros1msg`` schemas, ``ros1`` messages, md5sum/callerid/latching in channel metadata); a
ROS 2 bag becomes a ``ros2`` profile MCAP (``ros2msg``/``ros2idl`` schemas, ``cdr``
messages). Payloads are never re-serialised.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from memlog.io import McapLogWriter, copy_log, open_log
from memlog.io.records import ReadReport
from memlog.progress import progress

__all__ = ["convert", "ConvertResult"]


@dataclass
class ConvertResult:
    output: Path
    messages: int
    bytes_in: int
    bytes_out: int
    metadata: int
    attachments: int
    report: ReadReport


def convert(
    log: str | os.PathLike[str],
    output: str | os.PathLike[str],
    *,
    compression: str = "zstd",
    chunk_size: int = 4 * 1024 * 1024,
) -> ConvertResult:
    """Write ``log`` as an indexed MCAP at ``output`` (atomically)."""
    with open_log(log) as reader:
        if Path(output).resolve() == Path(reader.path).resolve():
            from memlog.errors import LogWriteError

            raise LogWriteError(f"{output}: output would overwrite the input log")
        counts = reader.message_counts()
        total = sum(counts.values()) if counts else None
        with McapLogWriter(output, profile=reader.profile, compression=compression, chunk_size=chunk_size) as w:
            stats = copy_log(reader, w, wrap=lambda it: progress(it, total=total, desc="convert"))
        return ConvertResult(
            Path(output), stats.messages, reader.size_bytes, os.path.getsize(output), stats.metadata,
            stats.attachments, reader.report,
        )

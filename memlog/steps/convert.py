"""Pipeline step ``convert``: any log -> indexed, compressed MCAP holding every input record.

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
from typing import Literal

from memlog.configfile import check_ints
from memlog.errors import ConfigError
from memlog.io.atomic import check_output
from memlog.io.mcap import McapLogWriter, copy_log
from memlog.io.open import open_log
from memlog.io.records import ReadReport
from memlog.progress import progress

__all__ = ["convert", "ConvertConfig", "ConvertResult"]


@dataclass(frozen=True)
class ConvertConfig:
    """``compression`` of the MCAP chunks and their ``chunk_size`` in bytes."""

    compression: Literal["zstd", "lz4", "none"] = "zstd"
    chunk_size: int = 4 * 1024 * 1024

    def __post_init__(self) -> None:
        if self.compression not in ("zstd", "lz4", "none"):
            raise ConfigError(f"compression must be zstd, lz4 or none, got {self.compression!r}")
        check_ints(self, {"chunk_size": 1024})


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
    config: ConvertConfig | None = None,
) -> ConvertResult:
    """Write ``log`` as an indexed MCAP at ``output`` (atomically)."""
    cfg = config or ConvertConfig()
    check_output(output, [log])
    with open_log(log) as reader:
        counts = reader.message_counts()
        total = sum(counts.values()) if counts else None
        with McapLogWriter(output, profile=reader.profile, compression=cfg.compression, chunk_size=cfg.chunk_size) as w:
            stats = copy_log(reader, w, wrap=lambda it: progress(it, total=total, desc="convert"))
        return ConvertResult(
            Path(output), stats.messages, reader.size_bytes, os.path.getsize(output), stats.metadata,
            stats.attachments, reader.report,
        )

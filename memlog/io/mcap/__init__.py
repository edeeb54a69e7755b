"""MCAP reading (any profile, chunk-indexed, robust to damage) and writing (atomic, indexed)."""

from memlog.errors import LogReadError, LogWriteError
from memlog.io.mcap.reader import McapLog
from memlog.io.mcap.writer import CopyStats, McapLogWriter, copy_log

__all__ = ["McapLog", "McapLogWriter", "copy_log", "CopyStats", "LogReadError", "LogWriteError"]

"""Open any log by its content, not its extension."""

from __future__ import annotations

import os
from pathlib import Path

from memlog.errors import LogReadError
from memlog.io._damage import check_regular_file
from memlog.io.base import LogReader
from memlog.io.paths import resolve_path

__all__ = ["open_log", "sniff_format"]

_MCAP = b"\x89MCAP0\r\n"
_ROS1 = b"#ROSBAG V2.0"
_SQLITE = b"SQLite format 3\x00"


def sniff_format(path: str | os.PathLike[str]) -> str:
    """``"mcap"``, ``"ros1bag"`` or ``"ros2bag"``; :class:`LogReadError` otherwise
    (:class:`~memlog.errors.SymlinkLoopError` when ``path`` is a symlink loop)."""
    p = Path(path)
    resolve_path(p)  # a symlink loop is a usage error, not a missing file
    if not p.exists():
        raise LogReadError(f"{p}: no such file or directory")
    if p.is_dir():
        if (p / "metadata.yaml").is_file() or any(p.glob("*.db3")) or any(p.glob("*.mcap")):
            return "ros2bag"
        raise LogReadError(f"{p}: directory is not a ROS 2 bag (no metadata.yaml)")
    check_regular_file(str(p))  # before open(): a named pipe would block forever
    try:
        with open(p, "rb") as fh:
            head = fh.read(16)
    except OSError as exc:
        raise LogReadError(f"{p}: cannot read: {exc.strerror}") from exc
    if head.startswith(_MCAP):
        return "mcap"
    if head.startswith(_ROS1):
        return "ros1bag"
    if head.startswith(_SQLITE):
        if (p.parent / "metadata.yaml").is_file() or p.suffix == ".db3":
            return "ros2bag-file"
    if not head:
        raise LogReadError(f"{p}: file is empty, not a log")
    raise LogReadError(f"{p}: not a log memlog can read (expected MCAP, a ROS 1 bag or a ROS 2 bag directory)")


def open_log(path: str | os.PathLike[str], validate_crcs: bool = True) -> LogReader:
    """Open an MCAP file, a ROS 1 ``.bag`` or a ROS 2 bag directory (or its ``.db3``)."""
    kind = sniff_format(path)
    if kind == "mcap":
        from memlog.io.mcap import McapLog

        return McapLog(path, validate_crcs=validate_crcs)
    if kind == "ros1bag":
        from memlog.io.rosbag1 import Ros1BagLog

        return Ros1BagLog(path)
    from memlog.io.rosbag2 import Ros2BagLog

    target = Path(path).parent if kind == "ros2bag-file" else Path(path)
    return Ros2BagLog(target)

"""The identity of an input log, so caches and resumable outputs are keyed on what they were made from.

:func:`log_identity` is the resolved path, the size in bytes and the modification time (ns) of a
log file, or of every file of a ROS 2 bag directory. Two identities are equal only when the
same files have the same sizes and times: a different log, or the same path rewritten, refuses
the cache.
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from memlog.errors import ConfigError
from memlog.io.paths import resolve_path

__all__ = ["log_identity", "same_identity", "log_name", "log_names", "sha256_file"]


def sha256_file(path: str | os.PathLike[str], chunk: int = 1 << 20) -> str:
    """Hex sha256 of a file's bytes, read in chunks (maps and model files are hundreds of MB)."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while block := fh.read(chunk):
            h.update(block)
    return h.hexdigest()


def log_identity(path: str | os.PathLike[str]) -> dict[str, Any]:
    """``{"path", "size", "mtime_ns"}`` of a log file or bag directory (JSON-ready)."""
    p = resolve_path(path)
    if p.is_dir():
        files = sorted(f for f in p.rglob("*") if f.is_file())
        stats = [f.stat() for f in files]
        return {"path": str(p), "size": sum(s.st_size for s in stats),
                "mtime_ns": max((s.st_mtime_ns for s in stats), default=0), "files": len(files)}
    st = p.stat()
    return {"path": str(p), "size": st.st_size, "mtime_ns": st.st_mtime_ns}


def same_identity(recorded: Any, path: str | os.PathLike[str]) -> bool:
    """Whether ``recorded`` (a :func:`log_identity` read back) still describes ``path``."""
    try:
        return isinstance(recorded, dict) and recorded == log_identity(path)
    except OSError:
        return False


def log_name(path: str | os.PathLike[str]) -> str:
    """A log's name for the outputs made from it: the file or bag directory name without
    ``.mcap``/``.bag``/``.db3``."""
    name = Path(str(path).rstrip("/")).name
    for suffix in (".mcap", ".bag", ".db3"):
        name = name.removesuffix(suffix)
    return name


def log_names(logs: Sequence[str | os.PathLike[str]], output: str | os.PathLike[str], advice: str) -> list[str]:
    """:func:`log_name` of each log; ConfigError (naming the ``-o`` directory, with ``advice``)
    when two logs share a name, so their outputs would collide."""
    names = [log_name(log) for log in logs]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ConfigError(f"-o {output}: several logs are named {', '.join(dup)}; their outputs would collide "
                          f"({advice})")
    return names

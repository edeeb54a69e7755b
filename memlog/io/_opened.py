"""What opening a log learned, kept once per process: a log is read to find its structure once.

Opening a log can be expensive: an unindexed or damaged MCAP or ROS 1 bag is scanned from its
first byte to its last (to find its chunks, channels and frame tables), a cut ``.db3`` is copied
with its header fixed, a ``.db3.zstd`` is decompressed. Steps open the same log many times (one
pass per stage, one reader per job), so every reader keeps what it learned in a per-process
cache keyed by the file's identity (resolved path, device, inode, size, modification time): the
next reader of the same unchanged file starts from there instead of reading the log again, and
the warnings a log gave are said once per process (every reader's report still records them, so
damage is still reported by every step).

The cache is this process's alone: memlog's worker processes are spawned, not forked
(:mod:`memlog.steps.parallel`; Ray actors likewise), so each worker learns a log itself the first
time one of its jobs opens it, and keeps it for its next jobs (a log that must be scanned is
scanned once per worker, not once per job; a job carries only the log's path). A process that
other code forks from one that has opened a log inherits its entries; a ROS 2 bag's sqlite
connections are opened again in it, never shared. Entries are dropped least recently used first
(never while a reader uses them), and all at exit; :func:`clear_cache` drops them now (tests; a
notebook that wants a log read afresh).

The cache and its scan counts are the :class:`~memlog.runtime.OpenedLogs` of the runtime context
in force (:func:`memlog.runtime.current`); the functions here use that one. A Runtime made by
replacing a setting shares it; a reader releases its entry where it learned it as long as the
Runtime in force keeps the same cache while it reads.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Hashable
from typing import Any, Protocol, TypeVar

from memlog.runtime import DEFAULT_OPENED_LOGS, current

__all__ = ["Learned", "learned", "release", "clear_cache", "file_key", "scans", "MAX_ENTRIES"]

#: Logs whose structure is kept when no reader uses them.
MAX_ENTRIES = DEFAULT_OPENED_LOGS


class Learned(Protocol):
    """What a reader learned about one log (format-specific); ``said``: warnings already shown."""

    said: set[str]

    def close(self) -> None: ...


S = TypeVar("S", bound=Learned)


def file_key(kind: str, path: str, *extra: Hashable) -> Hashable:
    """The cache key of ``path`` (a file, or a directory and every file in it) as it is now."""
    real = os.path.realpath(path)
    if os.path.isdir(real):
        parts = []
        for name in sorted(os.listdir(real)):
            try:
                st = os.stat(os.path.join(real, name))
            except OSError:
                continue
            parts.append((name, st.st_ino, st.st_size, st.st_mtime_ns))
        return (kind, real, tuple(parts), extra)
    st = os.stat(real)
    return (kind, real, st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns, extra)


def learned(key: Hashable, make: Callable[[], S]) -> tuple[S, bool]:
    """The entry of ``key`` (made by ``make()`` when there is none) and whether it was made now.
    The caller uses it until :func:`release`."""
    return current().opened.learned(key, make)


def release(key: Hashable) -> None:
    """A reader is done with the entry of ``key``."""
    current().opened.release(key)


def clear_cache() -> None:
    """Drop every entry no reader uses (closing its temporary files)."""
    current().opened.clear()


def counted_scan(path: str) -> None:
    """Count one full scan of ``path``'s data (see :func:`scans`)."""
    current().opened.count_scan(path)


def scans(path: str | None = None) -> Any:
    """How many times this process scanned a log's data in full to learn its structure (all
    logs when ``path`` is None)."""
    counts = current().opened.scans()
    if path is None:
        return counts
    return counts.get(os.path.realpath(path), 0)

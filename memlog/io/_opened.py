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

**Across processes.** What a *scan* learned (an entry whose ``scanned`` is true: an unindexed or
damaged MCAP read from its first byte) is also kept on disk, in the runtime context's cache
directory (``<cache>/scans/``, keyed by the file's identity as above), so that memlog's worker
processes and Ray actors on the same machine (or sharing the cache directory), and later runs,
start from the driver's scan instead of reading the log again: one job reads a damaged log's
bytes once to learn it. An entry read back says its warnings again in the new process (its
``said`` starts empty). A record that does not load, was written by another memlog version or
belongs to another file is ignored (and the log scanned); the records are loaded with an
unpickler that admits memlog's, mcap's and numpy's plain types only; at most :data:`MAX_SCANS`
records are kept (the oldest dropped). A cache directory that cannot be written only costs the
scans.
"""

from __future__ import annotations

import hashlib
import io
import logging
import os
import pickle
from collections.abc import Callable, Hashable
from pathlib import Path
from typing import Any, Protocol, TypeVar

from memlog._version import __version__
from memlog.runtime import DEFAULT_OPENED_LOGS, OpenedLogs, current

__all__ = ["Learned", "learned", "release", "holder", "clear_cache", "file_key", "scans", "MAX_ENTRIES", "MAX_SCANS",
           "scan_record_path", "key_digest"]

#: Logs whose structure is kept when no reader uses them.
MAX_ENTRIES = DEFAULT_OPENED_LOGS
#: Scan records kept on disk (the least recently written dropped first).
MAX_SCANS = 256
#: Bumped when what a scan record holds changes (with memlog's version, it must match to be used).
_SCAN_FORMAT = 3
_log = logging.getLogger(__name__)


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
    """The entry of ``key`` (read back from its scan record, else made by ``make()``, when this
    process has none) and whether it was made now (False when it was read back: the caller says
    what it found as it does for an entry it did not make). The caller uses it until :func:`release`."""
    recalled: list[bool] = []

    def recall_or_make() -> S:
        got = _recall(key)
        if got is not None:
            recalled.append(True)
            return got  # type: ignore[no-any-return]
        made = make()
        if getattr(made, "scanned", False):
            _remember(key, made)
        return made

    entry, new = current().opened.learned(key, recall_or_make)
    return entry, new and not recalled


def key_digest(key: Hashable) -> str:
    """A file name for ``key`` (a :func:`file_key`): what memlog keeps of that file on disk is named by it."""
    return hashlib.sha256(repr(key).encode()).hexdigest()[:32]


def scan_record_path(key: Hashable) -> Path:
    """Where the scan record of ``key`` (a :func:`file_key`) is kept."""
    return current().cache_path() / "scans" / f"{key_digest(key)}.pickle"


class _PlainUnpickler(pickle.Unpickler):
    """Loads only the plain types a scan record holds: builtin containers and numbers, numpy arrays,
    and memlog's and mcap's record classes (classes only: no function of theirs is called)."""

    _BUILTINS = frozenset({"set", "frozenset", "dict", "list", "tuple", "bytes", "bytearray", "int", "float",
                           "complex", "str", "bool", "slice", "range"})
    _NUMPY = frozenset({"_reconstruct", "ndarray", "dtype", "_frombuffer", "scalar"})

    def find_class(self, module: str, name: str) -> Any:
        top = module.split(".")[0]
        allowed = ((module == "builtins" and name in self._BUILTINS)
                   or (module == "collections" and name in ("OrderedDict", "defaultdict"))
                   or (module == "copyreg" and name == "_reconstructor")
                   or (top == "numpy" and name in self._NUMPY)
                   or top in ("memlog", "mcap"))
        if not allowed:
            raise pickle.UnpicklingError(f"{module}.{name} is not allowed in a scan record")
        found = super().find_class(module, name)
        if top in ("memlog", "mcap") and not isinstance(found, type):
            raise pickle.UnpicklingError(f"{module}.{name} is not a class: not allowed in a scan record")
        return found


def _recall(key: Hashable) -> Any:
    path = scan_record_path(key)
    try:
        data = path.read_bytes()
    except OSError:
        return None
    try:
        fmt, version, got_key, entry = _PlainUnpickler(io.BytesIO(data)).load()
    except Exception as exc:  # noqa: BLE001 - a damaged or foreign record: scan again
        _log.debug("scan record %s does not load (%s): scanning again", path, exc)
        return None
    if (fmt, version, got_key) != (_SCAN_FORMAT, __version__, key):
        return None
    entry.said = set()
    return entry


def _remember(key: Hashable, entry: Any) -> None:
    path = scan_record_path(key)
    said = entry.said
    try:
        entry.said = set()
        data = pickle.dumps((_SCAN_FORMAT, __version__, key, entry), protocol=pickle.HIGHEST_PROTOCOL)
    except Exception as exc:  # noqa: BLE001 - an entry that does not pickle is kept in this process only
        _log.debug("scan of %s not kept on disk: %s", key, exc)
        return
    finally:
        entry.said = said
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
        try:
            tmp.write_bytes(data)
            os.replace(tmp, path)
        finally:
            tmp.unlink(missing_ok=True)
        old = sorted(path.parent.glob("*.pickle"), key=lambda p: p.stat().st_mtime)
        for p in old[: max(0, len(old) - MAX_SCANS)]:
            p.unlink(missing_ok=True)
    except OSError as exc:
        _log.debug("scan record %s not written: %s", path, exc)


def release(key: Hashable, cache: OpenedLogs | None = None) -> None:
    """A reader is done with the entry of ``key``; ``cache``: the one it learned it from
    (:func:`holder`, taken when it opened), else the runtime context's in force now."""
    (cache if cache is not None else current().opened).release(key)


def holder() -> OpenedLogs:
    """The cache :func:`learned` uses now (a reader keeps it, to release its entry there even when
    another runtime context is in force when it closes)."""
    return current().opened


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

"""A job's local copy of the log chunks it has read, so that each chunk is read from the log once.

``memlog map`` reads the frames of a log in three passes (entropy and views of every frame; the
detector on each segment's candidates; the writer on the kept frames), ``batch`` adds the score
step's pass, and a log without a summary is scanned first. Each pass reads nearly every chunk,
because a segment of a few frames has a candidate in almost every chunk. A step therefore runs
as a **job** (:func:`job`): while it runs, every chunk of that log that any process reads —
the driver's scan, worker processes, local Ray actors — is kept, decompressed and checked, in
``<cache>/spool/<log>/``; a later pass (in any process) reads it there instead of the log. The
job removes the folder when it ends (an outer job of the same log in the same process, such as
``batch`` around ``score`` and ``map``, keeps it until the outer job ends).

* What was read whole and intact is kept; of a damaged chunk, why it is damaged (a later pass
  reports it again without reading it).
* Bounded: a process keeps at most ``Runtime.spool_bytes`` (``MEMLOG_SPOOL_BYTES``, default
  8 GiB; 0 turns the spool off), and never fills the disk below :data:`MIN_FREE_BYTES`. Past the
  bound, later passes read the rest from the log as before.
* A process that does not see the folder (a Ray actor on another node with its own cache, a
  command outside a job such as ``inspect``) reads the log, as before.
* Which file a folder belongs to is its identity (path, device, inode, size, modification time):
  a log that changes gets another folder. A folder older than :data:`STALE_S` is left from a job
  that died; the next job removes it.
"""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path

from memlog.io._opened import file_key, key_digest
from memlog.runtime import DEFAULT_SPOOL_BYTES, current

__all__ = ["ChunkSpool", "job", "spool_of", "MIN_FREE_BYTES", "DEFAULT_SPOOL_BYTES"]

log = logging.getLogger(__name__)

#: The spool never writes a chunk that would leave less than this free on its disk.
MIN_FREE_BYTES = 2 << 30
_LOCK = threading.Lock()  # (guards the runtime context's count of jobs per log)
#: A spool folder untouched this long is left from a job that died (removed by the next job).
STALE_S = 24 * 3600.0


def _identity(path: str | os.PathLike[str]) -> str | None:
    """The folder name of ``path``'s spool: its :func:`~memlog.io._opened.file_key` (None when it is
    not a regular file)."""
    if not os.path.isfile(path):
        return None
    try:
        return key_digest(file_key("spool", os.fspath(path)))
    except OSError:
        return None


def _root() -> Path:
    return current().cache_path() / "spool"


class ChunkSpool:
    """The spool folder of one log in this process: chunks by their offset in the file."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self.written = 0  # bytes this process put here

    def _file(self, offset: int) -> Path:
        return self.folder / f"{offset}.chunk"

    def get(self, offset: int) -> tuple[bytes, bool] | str | None:
        """The chunk at ``offset``: its uncompressed records and whether its CRC was checked when it
        was read; or, for a chunk found damaged, why (text); None when it is not kept (or the job
        has ended)."""
        try:
            with open(self._file(offset), "rb") as fh:
                blob = fh.read()
        except OSError:
            return None
        kind = blob[:1]
        if kind not in (b"c", b"u", b"d"):
            return None
        if kind == b"d":
            return blob[1:].decode("utf-8", "replace")
        return blob[1:], kind == b"c"

    def put(self, offset: int, data: bytes, checked: bool) -> None:
        """Keep the chunk at ``offset`` (``data``: its uncompressed records), within the bounds; an
        error here only means the chunk is not kept."""
        self._keep(offset, (b"c" if checked else b"u") + data)

    def put_damaged(self, offset: int, reason: str) -> None:
        """Keep that the chunk at ``offset`` is damaged, and why: a later pass reports it without
        reading it again."""
        self._keep(offset, b"d" + reason.encode())

    def _keep(self, offset: int, blob: bytes) -> None:
        cap = current().spool_bytes
        if self.written + len(blob) > cap or not self.folder.is_dir():
            return
        try:
            if shutil.disk_usage(self.folder).free - len(blob) < MIN_FREE_BYTES:
                return
            fd, tmp = tempfile.mkstemp(dir=self.folder, prefix=".", suffix=".tmp")
            try:
                with os.fdopen(fd, "wb") as fh:
                    fh.write(blob)
                os.replace(tmp, self._file(offset))
            except BaseException:
                with contextlib.suppress(OSError):
                    os.unlink(tmp)
                raise
        except OSError as exc:
            log.debug("spool: chunk at %d not kept (%s)", offset, exc)
            return
        self.written += len(blob)


def spool_of(path: str | os.PathLike[str]) -> ChunkSpool | None:
    """The spool of ``path`` when a job of it is running (its folder exists) and the spool is on."""
    if current().spool_bytes <= 0:
        return None
    name = _identity(path)
    if name is None:
        return None
    folder = _root() / name
    return ChunkSpool(folder) if folder.is_dir() else None


@contextlib.contextmanager
def job(path: str | os.PathLike[str]) -> Iterator[None]:
    """Run a step on ``path`` as one job: its chunks are kept while the block runs (see the module
    doc), and removed after it unless an outer job of the same log in this process still runs."""
    if current().spool_bytes <= 0:
        yield
        return
    name = _identity(path)
    if name is None:
        yield
        return
    jobs = current().spools
    folder = _root() / name
    with _LOCK:  # (batch runs logs on threads)
        ready = jobs.get(name, 0) > 0
        if not ready:
            _remove_stale(folder)
            try:
                folder.mkdir(parents=True, exist_ok=True)
                ready = True
            except OSError as exc:
                log.debug("spool: %s not made (%s); the log is read at every pass", folder, exc)
        if ready:
            jobs[name] = jobs.get(name, 0) + 1
    if not ready:
        yield
        return
    try:
        yield
    finally:
        with _LOCK:
            jobs[name] -= 1
            last = jobs[name] <= 0
            if last:
                del jobs[name]
        if last:
            shutil.rmtree(folder, ignore_errors=True)


def _remove_stale(keep: Path) -> None:
    """Remove spool folders left by jobs that died (untouched for :data:`STALE_S`)."""
    root = keep.parent
    if not root.is_dir():
        return
    now = time.time()
    for entry in root.iterdir():
        try:
            if entry != keep and entry.is_dir() and now - entry.stat().st_mtime > STALE_S:
                shutil.rmtree(entry, ignore_errors=True)
        except OSError:
            continue

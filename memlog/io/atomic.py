"""Atomic output files and the output-path rules every memlog command follows.

Every file memlog writes goes through :class:`AtomicFile`: the data goes to a temporary file
beside the target (``.<name>.<random>.tmp``), which is fsynced, given the normal file mode and
renamed over the target only when complete. An interrupted run never leaves a half-written
file under the final name, and an existing file there stays untouched until the new one is
complete. Files that only make sense together (a map and its descriptors) are put in place by
:func:`commit_together`, so that a new file never stands beside an old companion.

Output paths (:func:`check_output`): memlog creates the output itself (a file, or the output
directory of ``evaluate``/``batch``) but never a missing parent directory, and an output may
never be one of the command's inputs (compared by resolved path and by ``os.path.samefile``,
so hard links, symlinks and ``./x`` vs ``x`` are caught). Paths are followed by
:func:`memlog.io.paths.resolve_path`: an output or input that is a symlink loop is a usage error.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Callable, Iterable, Iterator, Sequence
from pathlib import Path
from types import TracebackType
from typing import BinaryIO

from memlog.errors import LogWriteError, OutputPathError, SymlinkLoopError
from memlog.io.paths import resolve_path

__all__ = ["AtomicFile", "atomic_output", "write_bytes_atomic", "file_mode", "check_output", "same_path",
           "commit_together"]

PathLike = str | os.PathLike[str]


def file_mode() -> int:
    """Permission bits a plain ``open(path, "w")`` would give under the current umask."""
    mask = os.umask(0)
    os.umask(mask)
    return 0o666 & ~mask


def same_path(a: PathLike, b: PathLike) -> bool:
    """Whether ``a`` and ``b`` name the same file or directory (resolved path, or samefile)."""
    pa, pb = Path(a), Path(b)
    try:
        if resolve_path(pa) == resolve_path(pb):
            return True
    except (OSError, SymlinkLoopError):
        pass
    try:
        return pa.exists() and pb.exists() and os.path.samefile(pa, pb)
    except OSError:
        return False


def _inside(path: Path, directory: Path) -> bool:
    try:
        resolve_path(path).relative_to(resolve_path(directory))
        return True
    except (ValueError, OSError, SymlinkLoopError):
        return False


def check_output(
    output: PathLike, inputs: Iterable[PathLike] = (), *, flag: str = "-o", directory: bool = False
) -> Path:
    """Validate an output path before any work: raise :class:`OutputPathError` naming ``flag``.

    The parent directory must exist (memlog never creates it); a file output must not be an
    existing directory (``directory=True``: an output directory must not be an existing file);
    the output must not be any of ``inputs`` nor lie inside an input directory (a ROS 2 bag).
    An output or input that is (or passes through) a symlink loop raises
    :class:`~memlog.errors.SymlinkLoopError` (a usage error too).
    """
    out = Path(output)
    if str(output) == "":
        raise OutputPathError(f"{flag}: empty output path")
    resolve_path(out, flag)
    for inp in inputs:
        resolve_path(inp)
    parent = out.parent if str(out.parent) else Path(".")
    if not parent.is_dir():
        raise OutputPathError(f"{flag} {out}: directory {parent} does not exist (memlog does not create it)")
    if not directory and out.is_dir():
        raise OutputPathError(f"{flag} {out}: is a directory, expected a file name")
    if directory and out.exists() and not out.is_dir():
        raise OutputPathError(f"{flag} {out}: exists and is not a directory")
    for inp in inputs:
        ip = Path(inp)
        if same_path(out, ip):
            raise OutputPathError(f"{flag} {out}: would overwrite the input {ip}")
        if ip.is_dir() and _inside(out, ip):
            raise OutputPathError(f"{flag} {out}: lies inside the input bag directory {ip}")
    return out


class AtomicFile:
    """A file written under a temporary name and renamed to ``path`` by :meth:`commit`.

    ``fh`` is the open binary handle; :meth:`abort` (or an exception inside ``with``) removes
    the temporary file and leaves ``path`` as it was.
    """

    def __init__(self, path: PathLike) -> None:
        self.path = Path(path)
        parent = self.path.parent if str(self.path.parent) else Path(".")
        if not parent.is_dir():
            raise LogWriteError(f"{self.path}: directory {parent} does not exist")
        if self.path.is_dir():
            raise LogWriteError(f"{self.path}: is a directory")
        fd, tmp = tempfile.mkstemp(prefix=f".{self.path.name}.", suffix=".tmp", dir=parent)
        self.tmp = Path(tmp)
        self.fh: BinaryIO = os.fdopen(fd, "wb")
        self._done = False

    def commit(self) -> Path:
        """Flush, fsync, set the normal file mode and rename over ``path``."""
        if self._done:
            return self.path
        try:
            self.fh.flush()
            os.fsync(self.fh.fileno())
            self.fh.close()
            os.chmod(self.tmp, file_mode())  # mkstemp creates 0600
            os.replace(self.tmp, self.path)
        except BaseException:
            self.abort()
            raise
        self._done = True
        return self.path

    def abort(self) -> None:
        """Drop the temporary file; the target is left as it was."""
        if self._done:
            return
        self._done = True
        try:
            self.fh.close()
        finally:
            self.tmp.unlink(missing_ok=True)

    def __enter__(self) -> "AtomicFile":
        return self

    def __exit__(self, et: type[BaseException] | None, ev: BaseException | None, tb: TracebackType | None) -> None:
        if et is None:
            self.commit()
        else:
            self.abort()


@contextlib.contextmanager
def atomic_output(path: PathLike) -> Iterator[Path]:
    """Yield a temporary path next to ``path`` for a library that writes by file name; rename it
    to ``path`` if the block succeeds, remove it on any exception."""
    af = AtomicFile(path)
    af.fh.close()
    try:
        yield af.tmp
        af.fh = open(af.tmp, "ab")
        af.commit()
    except BaseException:
        af.abort()
        raise


def write_bytes_atomic(path: PathLike, data: bytes, check: Callable[[Path], None] | None = None) -> Path:
    """Write ``data`` to ``path`` atomically; ``check`` may inspect the temporary file first."""
    with AtomicFile(path) as af:
        af.fh.write(data)
        if check is not None:
            af.fh.flush()
            check(af.tmp)
    return Path(path)


def commit_together(files: Sequence[AtomicFile], stale: Iterable[PathLike] = ()) -> None:
    """Put complete files that belong together (a map and its descriptors) in place so that a new
    file never stands beside an old companion.

    The old files at the targets of ``files[1:]`` (and the ``stale`` paths: old companions that
    get no new version) are first moved aside (renamed to ``.NAME.*.old`` in their directory),
    then ``files`` are committed in order, then the moved-aside files are removed. When a step
    fails, the others are undone as far as they can be and the exception propagates: before the
    first commit, the moved-aside files are moved back (the old set is as it was); after it, the
    new files committed so far are removed as well (the old first file was already replaced, so
    none of the set is left). Only a crash inside this function (power loss, SIGKILL) can leave
    an incomplete set: a first file (old or new) without its companions, and the moved-aside
    files beside it — never a new file beside an old companion.
    """
    aside: list[tuple[Path, Path]] = []  # (target, where its old file went)
    committed: list[AtomicFile] = []
    try:
        for target in [f.path for f in files[1:]] + [Path(p) for p in stale]:
            if os.path.lexists(target):
                fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".old", dir=target.parent)
                os.close(fd)
                try:
                    os.replace(target, tmp)
                except BaseException:
                    os.unlink(tmp)
                    raise
                aside.append((target, Path(tmp)))
        for f in files:
            f.commit()
            committed.append(f)
    except BaseException:
        for f in files:
            f.abort()  # (a no-op for those committed)
        for f in committed:
            with contextlib.suppress(OSError):
                f.path.unlink()
        for target, old in reversed(aside):
            with contextlib.suppress(OSError):
                if committed:
                    old.unlink()
                else:
                    os.replace(old, target)
        raise
    for _target, old in aside:
        with contextlib.suppress(OSError):
            old.unlink()

"""The one place memlog follows a path it was given: :func:`resolve_path`.

A path that is (or passes through) a symbolic link loop names no file: following it fails with
``ELOOP``, which ``Path.resolve()`` turns into a ``RuntimeError`` before Python 3.13 and ignores
after, and which ``Path.exists()`` hides as "missing". Every path check of memlog's inputs and
outputs (:func:`memlog.io.atomic.check_output`, :func:`memlog.io.open.sniff_format`) goes through
:func:`resolve_path`, so a loop is a usage error (exit 2) that names the path, on every Python.
"""

from __future__ import annotations

import errno
import os
from pathlib import Path

from memlog.errors import SymlinkLoopError

__all__ = ["resolve_path", "symlink_loop"]

PathLike = str | os.PathLike[str]


def _loops(path: Path) -> bool:
    try:
        os.stat(path)
    except OSError as exc:
        return exc.errno == errno.ELOOP
    except ValueError:  # an embedded NUL: not a loop (the caller's own checks say what it is)
        return False
    return False


def symlink_loop(path: PathLike) -> Path | None:
    """The first part of ``path`` (itself or one of its parent directories) that is a symbolic
    link loop, or None when following ``path`` meets no loop."""
    p = Path(path)
    if not _loops(p):
        return None
    for part in [*reversed(p.parents), p]:
        if str(part) not in ("", ".") and _loops(part):
            return part
    return p


def resolve_path(path: PathLike, flag: str = "") -> Path:
    """``path`` made absolute with every symbolic link followed (a missing part is kept as
    written, like ``Path.resolve()``). A path that is or passes through a symlink loop raises
    :class:`~memlog.errors.SymlinkLoopError` (a usage error) naming ``flag`` and the path."""
    p = Path(path)
    loop = symlink_loop(p)
    if loop is None:
        try:
            return p.resolve()
        except RuntimeError:  # Python < 3.13: a loop made since the check above
            loop = p
    where = f"{flag} {p}" if flag else str(p)
    what = "is a symlink loop" if loop == p else f"passes through the symlink loop {loop}"
    raise SymlinkLoopError(f"{where}: {what} (its symbolic links lead back to each other, so it names no file)")

"""Progress bars that switch themselves off when output is not a terminal or --quiet."""

from __future__ import annotations

import sys
from collections.abc import Iterable, Iterator
from typing import Any, TypeVar

__all__ = ["progress", "set_quiet", "is_quiet", "info"]

T = TypeVar("T")
_QUIET = False


def set_quiet(quiet: bool) -> None:
    global _QUIET
    _QUIET = quiet


def is_quiet() -> bool:
    return _QUIET


def info(text: str) -> None:
    """A status line on stderr (suppressed by --quiet)."""
    if not _QUIET:
        print(text, file=sys.stderr)


def progress(it: Iterable[T], *, total: int | None = None, desc: str = "", unit: str = "msg", **kw: Any) -> Iterator[T]:
    """Wrap an iterable in a tqdm bar on a terminal; pass it through otherwise."""
    if _QUIET or not sys.stderr.isatty():
        yield from it
        return
    from tqdm import tqdm

    yield from tqdm(it, total=total, desc=desc, unit=unit, dynamic_ncols=True, leave=False, **kw)

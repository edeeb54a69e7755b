"""Progress bars that switch themselves off when output is not a terminal or --quiet."""

from __future__ import annotations

import sys
import time
from collections.abc import Iterable, Iterator
from typing import Any, TypeVar

__all__ = ["progress", "set_quiet", "info"]

T = TypeVar("T")
_QUIET = False


def set_quiet(quiet: bool) -> None:
    global _QUIET
    _QUIET = quiet


def info(text: str) -> None:
    """A status line on stderr (suppressed by --quiet)."""
    if not _QUIET:
        print(text, file=sys.stderr)


def _log_lines(it: Iterable[T], total: int | None, desc: str, unit: str, every_s: float) -> Iterator[T]:
    """Off a terminal (CI, nohup): a plain status line every ``every_s`` seconds."""
    t0 = last = time.monotonic()
    n = 0
    for x in it:
        yield x
        n += 1
        now = time.monotonic()
        if now - last >= every_s:
            last = now
            rate = n / (now - t0)
            of = f"/{total}" if total else ""
            eta = f", about {(total - n) / rate:.0f} s left" if total and rate > 0 else ""
            print(f"memlog: {desc}: {n}{of} {unit}s ({rate:.2f}/s{eta})", file=sys.stderr, flush=True)


def progress(it: Iterable[T], *, total: int | None = None, desc: str = "", unit: str = "msg",
             every_s: float = 30.0, **kw: Any) -> Iterator[T]:
    """Wrap an iterable in a tqdm bar on a terminal, or status lines every ``every_s`` seconds
    otherwise; nothing with --quiet."""
    if _QUIET:
        yield from it
        return
    if not sys.stderr.isatty():
        yield from _log_lines(it, total, desc, unit, every_s)
        return
    from tqdm import tqdm

    yield from tqdm(it, total=total, desc=desc, unit=unit, dynamic_ncols=True, leave=False, **kw)

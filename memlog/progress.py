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


def _status(desc: str, n: int, total: int | None, unit: str, elapsed: float, done: bool) -> str:
    rate = n / elapsed if elapsed > 0 else 0.0
    of = f"/{total}" if total is not None else ""
    pct = f" ({100 * n / total:.0f} %)" if total else ""
    if done:
        return f"memlog: {desc}: {n}{of} {unit}s{pct} in {elapsed:.1f} s ({rate:.2f}/s)"
    if total is not None and rate > 0:
        left = f", about {max(0.0, (total - n) / rate):.0f} s left"
    else:
        left = ", total unknown" if total is None else ""
    return f"memlog: {desc}: {n}{of} {unit}s{pct} ({rate:.2f}/s{left})"


def _log_lines(it: Iterable[T], total: int | None, desc: str, unit: str, every_s: float) -> Iterator[T]:
    """Off a terminal (CI, nohup): a status line with the total and the time left every
    ``every_s`` seconds, and one when the loop ends."""
    t0 = last = time.monotonic()
    n = 0
    for x in it:
        yield x
        n += 1
        now = time.monotonic()
        if now - last >= every_s:
            last = now
            print(_status(desc, n, total, unit, now - t0, False), file=sys.stderr, flush=True)
    print(_status(desc, n, total, unit, time.monotonic() - t0, True), file=sys.stderr, flush=True)


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

    # miniters=1: the count on screen follows every item (a fast copy showed "0msg" until it ended)
    yield from tqdm(it, total=total, desc=desc, unit=unit, dynamic_ncols=True, leave=False, miniters=1,
                    mininterval=0.2, **kw)

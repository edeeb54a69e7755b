"""Status messages and progress: library code logs, the caller decides what is shown.

Messages go to the ``memlog`` logger (:func:`info`, :func:`warning`; readers warn on
``memlog.io``): the command line shows INFO and above on stderr as ``memlog: ...`` lines (``-q``:
warnings only); a notebook or another program sees what its own logging configuration shows
(Python's default: warnings). Progress is a tqdm bar when stderr is a terminal, else a status
line every 30 s through the ``memlog.progress`` logger (INFO). Whether bars are drawn
(:func:`set_quiet`) and where progress is counted instead (:func:`redirect`) are context
variables, so threads that run steps side by side (``memlog batch --logs-at-once``) each have
their own.

The time left is estimated from the items after the first one: what comes before the first item
(models loading on first use, a worker starting) is not item time, so it does not inflate the
estimate (the elapsed time and the final rate still count it).
"""

from __future__ import annotations

import contextlib
import contextvars
import logging
import sys
import time
from collections.abc import Callable, Iterable, Iterator
from typing import Any, TypeVar

__all__ = ["progress", "set_quiet", "is_quiet", "info", "warning", "Bar", "redirect", "LOGGER"]

T = TypeVar("T")
#: The logger of every memlog message (children: ``memlog.io``, ``memlog.progress``).
LOGGER = logging.getLogger("memlog")
_PROGRESS = logging.getLogger("memlog.progress")
_QUIET: contextvars.ContextVar[bool] = contextvars.ContextVar("memlog_quiet", default=False)
#: While set (:func:`redirect`), :func:`progress` draws nothing and calls it with (desc, unit) per item.
_SINK: contextvars.ContextVar[Callable[[str, str], None] | None] = contextvars.ContextVar("memlog_sink", default=None)


def set_quiet(quiet: bool) -> None:
    """No progress bars or status lines in this context (and the threads started from it with
    its context)."""
    _QUIET.set(quiet)


def is_quiet() -> bool:
    return _QUIET.get()


def info(text: str) -> None:
    """A status message (``memlog`` logger, INFO)."""
    LOGGER.info(text)


def warning(text: str) -> None:
    """A warning (``memlog`` logger, WARNING)."""
    LOGGER.warning(text)


def _status(desc: str, n: int, total: int | None, unit: str, elapsed: float, done: bool,
            rate: float | None = None) -> str:
    """A status line; ``rate``: items per second for the time left (default ``n / elapsed``)."""
    avg = n / elapsed if elapsed > 0 else 0.0
    of = f"/{total}" if total is not None else ""
    pct = f" ({100 * n / total:.0f} %)" if total else ""
    if done:
        return f"{desc}: {n}{of} {unit}s{pct} in {elapsed:.1f} s ({avg:.2f}/s)"
    r = avg if rate is None else rate
    if total is not None and r > 0:
        left = f", about {max(0.0, (total - n) / r):.0f} s left"
    elif total is not None and n < total:
        left = ", estimating the time left"
    else:
        left = ", total unknown" if total is None else ""
    return f"{desc}: {n}{of} {unit}s{pct} ({r:.2f}/s{left})"


class _Rate:
    """Items per second from the first item on: the wait for the first item (model loading) is
    left out of the estimate of the time left."""

    def __init__(self) -> None:
        self.first: float | None = None
        self.n_first = 0

    def seen(self, n: int, now: float) -> None:
        if self.first is None and n > 0:
            self.first, self.n_first = now, n
        elif self.first is not None and now - self.first < 0.01:
            self.n_first = n  # came with the first (a worker's first chunk): not timed either

    def rate(self, n: int, now: float) -> float:
        if self.first is None or n <= self.n_first or now <= self.first:
            return 0.0
        return (n - self.n_first) / (now - self.first)


def _log_lines(it: Iterable[T], total: int | None, desc: str, unit: str, every_s: float) -> Iterator[T]:
    """Off a terminal (CI, nohup): a status line with the total and the time left every
    ``every_s`` seconds, and one when the loop ends."""
    t0 = last = time.monotonic()
    n = 0
    rate = _Rate()
    for x in it:
        n += 1
        now = time.monotonic()
        rate.seen(n, now)
        yield x
        now = time.monotonic()
        if now - last >= every_s:
            last = now
            _PROGRESS.info(_status(desc, n, total, unit, now - t0, False, rate.rate(n, now)))
    _PROGRESS.info(_status(desc, n, total, unit, time.monotonic() - t0, True))


def _tqdm_from_first(it: Iterable[T], bar: Any) -> Iterator[T]:
    """Items of ``it`` counted on the tqdm ``bar``; its clock restarts at the first item, so the
    rate and the time left it shows leave the wait for the first item out."""
    first = True
    try:
        for x in it:
            if first:
                first = False
                bar.reset(total=bar.total)  # the clock (and the rate's history) from here
            bar.update(1)
            yield x
    finally:
        bar.close()


def progress(it: Iterable[T], *, total: int | None = None, desc: str = "", unit: str = "msg",
             every_s: float = 30.0, **kw: Any) -> Iterator[T]:
    """Wrap an iterable in a tqdm bar on a terminal, or status lines every ``every_s`` seconds
    otherwise; nothing with --quiet."""
    sink = _SINK.get()
    if sink is not None:
        for x in it:
            yield x
            sink(desc, unit)
        return
    if _QUIET.get():
        yield from it
        return
    if not sys.stderr.isatty():
        yield from _log_lines(it, total, desc, unit, every_s)
        return
    from tqdm import tqdm

    # miniters=1: the count on screen follows every item (a fast copy showed "0msg" until it ended)
    yield from _tqdm_from_first(it, tqdm(total=total, desc=desc, unit=unit, dynamic_ncols=True, leave=False,
                                         miniters=1, mininterval=0.2, **kw))


@contextlib.contextmanager
def redirect(sink: Callable[[str, str], None]) -> Iterator[None]:
    """Inside the block, :func:`progress` loops draw nothing and call ``sink(desc, unit)`` once
    per item instead (a caller that runs several steps shows one bar over all of them)."""
    token = _SINK.set(sink)
    try:
        yield
    finally:
        _SINK.reset(token)


class Bar:
    """A progress bar advanced by hand (:meth:`update`): tqdm on a terminal, a status line every
    ``every_s`` seconds otherwise (with the time left), nothing when quiet."""

    def __init__(self, total: int | None, desc: str, unit: str, every_s: float = 30.0) -> None:
        self.total, self.desc, self.unit, self.every_s = total, desc, unit, every_s
        self.n = 0
        self.note = ""
        self._t0 = self._last = time.monotonic()
        self._rate = _Rate()
        self._bar: Any = None
        self._closed = False
        if not _QUIET.get() and sys.stderr.isatty():
            from tqdm import tqdm

            self._bar = tqdm(total=total, desc=desc, unit=unit, dynamic_ncols=True, leave=False, mininterval=0.2)

    def set_note(self, text: str) -> None:
        """A short text shown with the count (e.g. which log is running)."""
        self.note = text
        if self._bar is not None:
            self._bar.set_postfix_str(text, refresh=False)

    def write(self, text: str) -> None:
        """A status line (as :func:`info`) that does not break the bar."""
        if self._bar is not None:
            from tqdm import tqdm

            tqdm.write(text, file=sys.stderr)
        else:
            info(text)

    def update(self, n: int = 1) -> None:
        first = self.n == 0 and n > 0
        self.n += n
        now = time.monotonic()
        self._rate.seen(self.n, now)
        if self._bar is not None:
            if first:  # the bar's clock from the first item: its time left leaves the wait before out
                self._bar.reset(total=self.total)
            self._bar.update(n)
            return
        if not _QUIET.get() and now - self._last >= self.every_s:
            self._last = now
            _PROGRESS.info(self._line(now, False))

    def _line(self, now: float, done: bool) -> str:
        line = _status(self.desc, self.n, self.total, self.unit, now - self._t0, done, self._rate.rate(self.n, now))
        return f"{line}; {self.note}" if self.note else line

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        if self._bar is not None:
            self._bar.close()
            self._bar = None
        elif not _QUIET.get():
            _PROGRESS.info(self._line(time.monotonic(), True))

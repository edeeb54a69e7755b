"""Running a step's jobs on several worker processes, results back in job order.

A step cuts its work into jobs (picklable: a module-level function and its arguments, e.g.
"score these frames of this log") and hands them to an :class:`Executor`, which yields the
results **in job order** whatever order they finish in, so a single writer can merge them into
outputs that are byte-identical to a one-process run. :class:`InProcess` runs them here;
:class:`Processes` on a pool of worker processes, each with its own models (loaded once per
process, see :func:`cached`) and ONNX Runtime thread count, so workers do not oversubscribe the
cores. The Ray executor of ``memlog batch`` (:mod:`memlog.steps.ray_pool`) implements the same
interface; an executor may also say how many threads its jobs should use (``threads``, see
:func:`job_threads`) and that its workers are other machines (``remote``).
"""

from __future__ import annotations

import os
from collections import deque
from collections.abc import Callable, Hashable, Iterable, Iterator
from concurrent.futures import Future, ProcessPoolExecutor
from typing import Any, Protocol, TypeVar

from memlog.errors import ConfigError

__all__ = ["Executor", "InProcess", "Processes", "make_executor", "cached", "cpu_count", "threads_per_worker",
           "job_threads"]

R = TypeVar("R")
Job = tuple[Any, ...]


class Executor(Protocol):
    """Runs ``fn(*job)`` for every job and yields the results in job order."""

    workers: int

    def map_ordered(self, fn: Callable[..., R], jobs: Iterable[Job]) -> Iterator[R]: ...

    def close(self) -> None: ...


def cpu_count() -> int:
    """Cores this process may use (the affinity mask, not the machine's total)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def threads_per_worker(workers: int, threads: int = 0) -> int:
    """ONNX Runtime threads per worker: ``threads`` when given, else the cores split evenly."""
    if threads:
        return threads
    return max(1, cpu_count() // max(1, workers))


def job_threads(executor: Executor, threads: int = 0) -> int:
    """ONNX Runtime threads for the jobs of ``executor``: ``threads`` when given, else the
    executor's own count when it declares one (a Ray actor's CPUs, on whatever node it runs),
    else this machine's cores split between its workers."""
    if threads:
        return threads
    own = getattr(executor, "threads", 0)
    return int(own) if own else threads_per_worker(executor.workers)


class InProcess:
    """Runs every job in this process, one after the other."""

    workers = 1

    def map_ordered(self, fn: Callable[..., R], jobs: Iterable[Job]) -> Iterator[R]:
        for job in jobs:
            yield fn(*job)

    def close(self) -> None:
        pass


def _init_worker(quiet: bool) -> None:
    from memlog.progress import set_quiet

    set_quiet(quiet)


class Processes:
    """A pool of ``workers`` processes; at most ``ahead`` jobs are submitted beyond the one whose
    result is awaited next (bounded memory for results waiting to be merged)."""

    def __init__(self, workers: int, *, quiet: bool = True, ahead: int | None = None) -> None:
        if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
            raise ConfigError(f"workers must be an integer >= 1, got {workers!r}")
        self.workers = workers
        self.ahead = ahead if ahead is not None else 2 * workers
        self._pool = ProcessPoolExecutor(workers, initializer=_init_worker, initargs=(quiet,))

    def map_ordered(self, fn: Callable[..., R], jobs: Iterable[Job]) -> Iterator[R]:
        pending: deque[Future[R]] = deque()
        it = iter(jobs)
        exhausted = False
        while True:
            while not exhausted and len(pending) < self.ahead:
                try:
                    job = next(it)
                except StopIteration:
                    exhausted = True
                    break
                pending.append(self._pool.submit(fn, *job))
            if not pending:
                return
            try:
                yield pending.popleft().result()
            except BaseException:
                for f in pending:
                    f.cancel()
                raise

    @property
    def broken(self) -> bool:
        """A worker process died: every job submitted from now on fails with ``BrokenProcessPool``."""
        return bool(getattr(self._pool, "_broken", False))

    def close(self) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)


def make_executor(workers: int) -> Executor:
    """:class:`InProcess` for one worker, else :class:`Processes`."""
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ConfigError(f"workers must be an integer >= 1, got {workers!r}")
    return InProcess() if workers == 1 else Processes(workers)


_CACHE: dict[Hashable, Any] = {}


def cached(key: Hashable, make: Callable[[], R]) -> R:
    """A per-process cache of expensive objects (models): ``make()`` once per ``key`` and process."""
    if key not in _CACHE:
        _CACHE[key] = make()
    value: R = _CACHE[key]
    return value

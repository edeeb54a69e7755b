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

**How workers start.** Local workers are started with the ``spawn`` method
(:data:`START_METHOD`) on every platform, never forked from the driver: a worker is a new
interpreter that imports what its jobs need, as a Ray actor is. A fork would copy the driver's
state as it is at that moment: its threads' locks (``memlog batch`` runs logs side by side on
threads, ONNX Runtime and Ray run their own), open sqlite connections and files, caches, models
already loaded. The workers are long-lived (one pool per step, or per ``memlog batch`` run) and load
their models once each, so a new interpreter per worker costs little; ``forkserver`` would save
only the imports, and only with a preload list that is global to the program, and it does not exist
on Windows (where, as on macOS, ``spawn`` is the default anyway). So everything a job needs
travels with it or is given to each worker when it starts:

* the job's function and arguments (pickled; the function is found by its module and name);
* whether progress is quiet, and the levels of the ``memlog`` loggers (:func:`worker_setup`, run
  by each worker when it starts);
* the runtime context (:class:`memlog.runtime.Runtime`: the pixel cap of ``--max-pixels``, the
  entropy kernel choice, the model cache's bound and directory), given to each worker when it starts
  and installed there; its caches are not: each worker has its own, empty when it starts;
* what opening a log learned is learned again by each worker, once (:mod:`memlog.io._opened`).

What a job logs on the ``memlog`` loggers goes back with its result (or its exception) and is
handled by the driver's ``memlog`` loggers, as if it had been logged there; but not what its
readers warn (``memlog.io``): that is in the job's report, which the driver's reader absorbs and
says once (:meth:`~memlog.io.base.LogReader.absorb`). A script that runs a
step on workers must keep its own work under ``if __name__ == "__main__":`` (each worker imports
the script's main module, as on macOS and Windows).
"""

from __future__ import annotations

import copy
import logging
import multiprocessing
import os
from collections import deque
from collections.abc import Callable, Hashable, Iterable, Iterator
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from multiprocessing.context import BaseContext
from typing import Any, Protocol, TypeVar, cast

import numpy as np

from memlog.errors import ConfigError
from memlog.runtime import Runtime, current, install

__all__ = ["Executor", "InProcess", "Processes", "make_executor", "cached", "cpu_count", "threads_per_worker",
           "job_threads", "START_METHOD", "mp_context", "log_levels", "worker_setup", "run_job", "replay"]

R = TypeVar("R")
Job = tuple[Any, ...]

#: How memlog starts its local worker processes (see the module's doc).
START_METHOD = "spawn"


def mp_context() -> BaseContext:
    """The multiprocessing context of memlog's local worker processes (:data:`START_METHOD`)."""
    return multiprocessing.get_context(START_METHOD)


class _TrackedContext:
    """A multiprocessing context that remembers the processes it starts (a pool's workers), so that a
    pool that lost a worker can stop the others itself: CPython 3.11's ``shutdown`` of a broken pool
    may wait for ever on a worker that survived."""

    def __init__(self, base: BaseContext) -> None:
        self._base: Any = base
        self.started: list[Any] = []

    def __getattr__(self, name: str) -> Any:
        return getattr(self._base, name)

    def Process(self, *args: Any, **kwargs: Any) -> Any:  # noqa: N802 (the context's own name)
        proc = self._base.Process(*args, **kwargs)
        self.started.append(proc)
        return proc


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


# -- what a worker is given, and what it gives back -------------------------------------------------
_LOGS = "memlog_worker_logs"  # the attribute of a failed job's exception that takes its records back
#: The loggers a worker's records come back from (:mod:`memlog.progress`).
_LOGGERS = ("memlog", "memlog.progress")


def log_levels() -> dict[str, int]:
    """The levels of this process's ``memlog`` loggers, for :func:`worker_setup`."""
    return {name: logging.getLogger(name).getEffectiveLevel() for name in _LOGGERS}


class _Keep(logging.Handler):
    """A worker's handler of the ``memlog`` loggers: keeps the running job's records for the driver."""

    def __init__(self) -> None:
        super().__init__()
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        r = copy.copy(record)  # one that pickles: the message as text, a traceback as text
        if record.exc_info and not r.exc_text:
            r.exc_text = logging.Formatter().formatException(record.exc_info)
        r.msg, r.args, r.exc_info = record.getMessage(), None, None
        self.records.append(r)


def _keeper() -> _Keep | None:
    """The handler :func:`worker_setup` gave this worker's ``memlog`` logger (None: not a worker)."""
    return next((h for h in logging.getLogger("memlog").handlers if isinstance(h, _Keep)), None)


def worker_setup(quiet: bool, levels: dict[str, int], runtime: Runtime | None = None) -> None:
    """Prepare a worker process: the driver's runtime context when given (installed here), progress
    quiet or not, the driver's ``memlog`` logger levels (:func:`log_levels`), and what the ``memlog``
    loggers get kept for the driver (:func:`run_job`; not the readers' warnings, which the job's
    report takes back)."""
    from memlog.progress import set_quiet

    if runtime is not None:
        install(runtime)
    set_quiet(quiet)
    top = logging.getLogger("memlog")
    for h in list(top.handlers):
        top.removeHandler(h)
    top.addHandler(_Keep())
    top.propagate = False  # the driver's handlers say it, not this process's root
    for name, level in levels.items():
        logging.getLogger(name).setLevel(level)
    # A reader's warnings are in its job's ReadReport, which the driver's reader absorbs and says
    # once (LogReader.absorb); said here too, they would be said twice.
    io = logging.getLogger("memlog.io")
    io.addHandler(logging.NullHandler())
    io.propagate = False


def run_job(fn: Callable[..., R], job: Job) -> tuple[R, list[logging.LogRecord]]:
    """``fn(*job)`` on a worker, with the records it logged (for :func:`replay`); when it raises,
    the records go with its exception."""
    keep = _keeper()
    if keep is None:  # not a worker made by worker_setup: its loggers say it themselves
        return fn(*job), []
    keep.records = []
    try:
        result = fn(*job)
    except BaseException as exc:
        setattr(exc, _LOGS, keep.records)
        keep.records = []
        raise
    records, keep.records = keep.records, []
    return result, records


def replay(records: Iterable[logging.LogRecord] | BaseException) -> None:
    """Hand a worker's records (or those its failed job's exception carries) to this process's
    loggers, as if they had been logged here."""
    got = records.__dict__.pop(_LOGS, ()) if isinstance(records, BaseException) else records
    for r in got:
        lg = logging.getLogger(r.name)
        if lg.isEnabledFor(r.levelno):
            lg.handle(r)


def _start_worker(runtime: Runtime, setup: Callable[[bool, dict[str, int]], None], quiet: bool,
                  levels: dict[str, int]) -> None:
    """A local worker's initializer: the driver's runtime context, then ``setup(quiet, levels)``
    (:func:`worker_setup`, or what replaces it)."""
    install(runtime)
    _one_blas_thread()
    setup(quiet, levels)


def _one_blas_thread() -> None:
    """Run numpy's OpenBLAS on one thread in a worker: the workers share the cores already, and
    OpenBLAS's own threads, idling in a worker beside ONNX Runtime's and the frame pipeline's, were
    seen to stall a job for minutes. Nothing happens where numpy has another BLAS."""
    import ctypes
    import glob

    libs = os.path.join(os.path.dirname(os.path.dirname(np.__file__)), "numpy.libs")
    for path in glob.glob(os.path.join(libs, "libscipy_openblas*.so")) + glob.glob(os.path.join(libs, "libopenblas*.so")):
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for name in ("scipy_openblas_set_num_threads64_", "scipy_openblas_set_num_threads", "openblas_set_num_threads"):
            fn = getattr(lib, name, None)
            if fn is not None:
                fn(1)
                return


def _nothing() -> None:
    """An empty job (:attr:`Processes.broken` offers one to a pool to see whether it takes jobs)."""


class Processes:
    """A pool of ``workers`` processes, started by :data:`START_METHOD`; at most ``ahead`` jobs are
    submitted beyond the one whose result is awaited next (bounded memory for results waiting to be
    merged). Each worker is given the runtime context in force here when the pool is made
    (``runtime``: another one)."""

    def __init__(self, workers: int, *, quiet: bool = True, ahead: int | None = None,
                 runtime: Runtime | None = None) -> None:
        if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
            raise ConfigError(f"workers must be an integer >= 1, got {workers!r}")
        self.workers = workers
        self.ahead = ahead if ahead is not None else 2 * workers
        self._broken = False
        self._closed = False
        given = runtime if runtime is not None else current()
        self._context = _TrackedContext(mp_context())
        self._pool = ProcessPoolExecutor(workers, mp_context=cast(BaseContext, self._context),
                                         initializer=_start_worker, initargs=(given, worker_setup, quiet, log_levels()))

    def _watch(self, f: Future[Any]) -> None:
        """A job's future is done: a pool that lost a worker fails its jobs with ``BrokenProcessPool``
        (the one that ran there, and every one waiting), whether or not anyone awaits them."""
        if not f.cancelled() and isinstance(f.exception(), BrokenProcessPool):
            self._broken = True

    def _submit(self, fn: Callable[..., Any], *args: Any) -> Future[Any]:
        try:
            f = self._pool.submit(fn, *args)
        except BrokenProcessPool:
            self._broken = True
            raise
        f.add_done_callback(self._watch)
        return f

    def map_ordered(self, fn: Callable[..., R], jobs: Iterable[Job]) -> Iterator[R]:
        pending: deque[Future[tuple[R, list[logging.LogRecord]]]] = deque()
        it = iter(jobs)
        exhausted = False
        while True:
            while not exhausted and len(pending) < self.ahead:
                try:
                    job = next(it)
                except StopIteration:
                    exhausted = True
                    break
                pending.append(self._submit(run_job, fn, job))
            if not pending:
                return
            try:
                result, records = pending.popleft().result()
                replay(records)
                yield result
            except BaseException as exc:
                replay(exc)
                for f in pending:
                    f.cancel()
                raise

    @property
    def broken(self) -> bool:
        """A worker process died: every job submitted from now on fails with ``BrokenProcessPool``.
        Seen in the jobs' futures; a worker that died between jobs is seen by offering the pool an
        empty job (a broken pool refuses it)."""
        if not self._broken and not self._closed:
            try:
                self._submit(_nothing)
            except BrokenProcessPool:
                pass  # (_submit noted it)
            except RuntimeError:  # the interpreter is shutting down: no job is started any more
                pass
        return self._broken

    def close(self) -> None:
        """Wait for the workers to finish and stop them; a pool that lost a worker stops the others
        first (its jobs have failed already, and waiting for them could hang)."""
        self._closed = True
        if self._broken:
            for proc in self._context.started:
                if proc.is_alive():
                    proc.kill()
        self._pool.shutdown(wait=True, cancel_futures=True)


def make_executor(workers: int) -> Executor:
    """:class:`InProcess` for one worker, else :class:`Processes` (given the runtime context in
    force, :func:`memlog.runtime.current`)."""
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ConfigError(f"workers must be an integer >= 1, got {workers!r}")
    return InProcess() if workers == 1 else Processes(workers)


def cached(key: Hashable, make: Callable[[], R]) -> R:
    """A per-process cache of expensive objects (models): ``make()`` once per ``key`` and process,
    kept in the runtime context's bounded model cache (:attr:`memlog.runtime.Runtime.models`; the
    least recently used is dropped beyond ``model_cache_size``)."""
    return current().models.get(key, make)

"""A step's jobs on a Ray cluster: actors that keep the models, results back in job order.

:class:`RayActors` is an :class:`~memlog.steps.parallel.Executor` like the local process pool:
the jobs are the steps' own (a module-level function and its picklable arguments, e.g.
``score_chunk(log, config, window, chunk)``), so a step runs on Ray without knowing it. Each
actor is one long-lived worker process holding the models (loaded once per process through
:func:`~memlog.steps.parallel.cached`, not once per job) and reserving the CPUs its ONNX Runtime
threads use, plus a share of a GPU when the cluster has GPUs (:func:`plan_placement`), so actors
never oversubscribe a node.

Fault tolerance: a job is a pure function of its arguments (it reads the log, writes nothing),
so when an actor's process dies (killed, out of memory, node lost) Ray restarts the actor and
runs the job again (``max_task_retries``); the driver, the only writer, sees the result once. A
job that still fails after its retries fails that log (:class:`WorkerLostError`).

Ray is an optional extra (``pip install 'memlog[ray]'``); this module imports it only inside
functions, and :func:`require_ray` says how to install it.
"""

from __future__ import annotations

import importlib.util
import logging
import os
import platform
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from dataclasses import asdict, dataclass
from typing import Any, TypeVar

from memlog._version import __version__
from memlog.errors import ConfigError, MemlogError
from memlog.steps.parallel import Job, cpu_count

__all__ = ["RAY_INSTALL", "KILL_HOOK", "ray_available", "require_ray", "connect", "cluster_resources", "Placement",
           "plan_placement", "RayActors", "WorkerLostError"]

R = TypeVar("R")

RAY_INSTALL = "pip install 'memlog[ray]'"
#: Test hook: when this environment variable names a file that exists in a worker's environment,
#: the first worker to finish a job removes the file and exits before returning the result (a
#: worker killed mid-task, exactly once); the job must then be retried.
KILL_HOOK = "MEMLOG_TEST_KILL_WORKER"


#: Default cap on actors sharing one GPU (each holds a ResMem session, ~1-1.5 GB of GPU memory).
MAX_ACTORS_PER_GPU = 16


class WorkerLostError(MemlogError):
    """A job's worker process died on every attempt (out of memory, a crash, a lost node)."""


def _ray() -> Any:
    """The ray module, untyped (its annotations do not cover actors made from plain classes)."""
    return importlib.import_module("ray")


def ray_available() -> bool:
    """Whether Ray can be imported (``memlog[ray]``)."""
    return importlib.util.find_spec("ray") is not None


def require_ray(flag: str = "--ray") -> None:
    """A usage error naming the install command when Ray is not installed."""
    if not ray_available():
        raise ConfigError(f"{flag}: Ray is not installed; install it with {RAY_INSTALL} "
                          "(ray:// addresses need pip install 'ray[client]')")


def connect(address: str | None = None, *, quiet: bool = True) -> bool:
    """Connect this process to Ray: the cluster at ``address`` (``auto``, ``ray://HOST:10001``,
    ``HOST:6379``), or else ``$RAY_ADDRESS``, or else a new local instance with this machine's
    cores. A process already connected (a notebook, a test) is used as it is. Returns whether this
    call connected, i.e. whether the caller should ``ray.shutdown()`` when done."""
    require_ray()
    ray = _ray()

    if ray.is_initialized():
        return False
    kw: dict[str, Any] = {"logging_level": logging.WARNING if quiet else logging.INFO, "log_to_driver": not quiet}
    try:
        if address is None and not os.environ.get("RAY_ADDRESS"):
            ray.init(num_cpus=cpu_count(), include_dashboard=False, **kw)
        else:
            ray.init(address=address, **kw)
    except Exception as exc:  # Ray raises ConnectionError, RuntimeError, ValueError...
        where = address or os.environ.get("RAY_ADDRESS") or "a local instance"
        raise ConfigError(f"--ray {address or ''}".rstrip() + f": could not connect to Ray ({where}): {exc}") from None
    return True


def cluster_resources() -> tuple[float, float]:
    """(CPUs, GPUs) of the connected Ray cluster."""
    ray = _ray()

    res = ray.cluster_resources()
    return float(res.get("CPU", 0.0)), float(res.get("GPU", 0.0))


@dataclass(frozen=True)
class Placement:
    """How jobs are placed: ``actors`` worker processes, each reserving ``threads`` CPUs (its ONNX
    Runtime and OpenCV threads) and ``gpus`` of a GPU (0: CPU actors)."""

    actors: int
    threads: int
    gpus: float

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def plan_placement(cpus: float, gpus: float, *, workers: int | None = None, threads: int = 0,
                   device: str = "auto", actors_per_gpu: int | None = None) -> Placement:
    """The actors for a cluster of ``cpus`` CPUs and ``gpus`` GPUs.

    CPU only (no GPU, or ``device`` cpu): ``threads`` CPUs per actor (default 1) and as many
    actors as the CPUs hold, or ``workers``. With GPUs (``device`` auto or cuda):
    ``actors_per_gpu`` actors share each GPU (default: the CPUs per GPU over ``threads``, at most
    :data:`MAX_ACTORS_PER_GPU`): decoding, the detector and entropy stay on the CPU (~0.2
    core-seconds per frame) while ResMem needs ~5 ms of an H100 per frame, so a GPU needs the
    frames of many CPU workers; the cap bounds the GPU memory of their ONNX Runtime sessions.
    Raises :class:`ConfigError` when the cluster cannot hold what was asked."""
    t = threads or 1
    if device == "cuda" and gpus <= 0:
        raise ConfigError("--device cuda: the Ray cluster has no GPU (drop --device, or use --device cpu)")
    if cpus < t:
        raise ConfigError(f"--threads {t}: the Ray cluster has only {cpus:g} CPU(s)")
    if device != "cpu" and gpus > 0:
        per_gpu = actors_per_gpu or max(1, min(MAX_ACTORS_PER_GPU, int(cpus / gpus) // t))
        share = 1.0 / per_gpu
        n = workers or max(1, min(int(gpus * per_gpu), int(cpus // t)))
        if n * share > gpus + 1e-9 or n * t > cpus:
            raise ConfigError(f"--workers {n}: {n} actors with {t} CPU(s) and {share:g} GPU each do not fit the Ray "
                              f"cluster ({cpus:g} CPUs, {gpus:g} GPUs)")
        return Placement(n, t, share)
    n = workers or max(1, int(cpus // t))
    if n * t > cpus:
        raise ConfigError(f"--workers {n} with --threads {t} needs {n * t} CPUs; the Ray cluster has {cpus:g} "
                          "(fewer --workers or --threads)")
    return Placement(n, t, 0.0)


class _Worker:
    """One Ray actor: a worker process that runs jobs; models stay in its process cache."""

    def __init__(self, threads: int) -> None:
        from memlog.progress import set_quiet

        set_quiet(True)
        try:
            import cv2

            cv2.setNumThreads(threads)  # OpenCV's pool (resize, detector) within the actor's CPUs
        except ImportError:
            pass

    def info(self, device: str) -> dict[str, Any]:
        """Who this worker is; raises the model layer's error when ``device`` cannot be used here."""
        from memlog.models.runtime import choose_providers

        return {"pid": os.getpid(), "host": platform.node(), "memlog": __version__,
                "providers": choose_providers(device), "gpus": os.environ.get("CUDA_VISIBLE_DEVICES")}

    def run(self, fn: Callable[..., Any], job: Job) -> tuple[int, Any]:
        result = fn(*job)
        _kill_hook()
        return os.getpid(), result


def _kill_hook() -> None:
    path = os.environ.get(KILL_HOOK)
    if not path:
        return
    try:
        os.unlink(path)  # exactly one worker wins
    except OSError:
        return
    os._exit(1)


class RayActors:
    """An executor of ``placement.actors`` Ray actors. Each actor has at most ``depth`` jobs queued
    (the next one is ready when it finishes) and at most ``ahead`` jobs are in flight beyond the
    one whose result is awaited next (bounded memory for results waiting to be merged). A dead
    actor is restarted by Ray and its job run again up to ``max_retries`` times; :attr:`restarts`
    counts the worker processes lost so far."""

    def __init__(self, placement: Placement, *, device: str = "auto", max_retries: int = 3, depth: int = 2,
                 ahead: int | None = None, start_timeout_s: float = 600.0) -> None:
        ray = _ray()

        if max_retries < 0:
            raise ConfigError(f"max_retries must be >= 0, got {max_retries}")
        self.placement = placement
        self.workers = placement.actors
        self.remote = True  # jobs run on other machines: the driver's device is not theirs
        self.threads = placement.threads
        self.max_retries = max_retries
        self.depth = depth
        self.ahead = ahead if ahead is not None else depth * placement.actors
        self.restarts = 0
        cls = ray.remote(_Worker).options(num_cpus=placement.threads, num_gpus=placement.gpus,
                                          max_restarts=-1, max_task_retries=max_retries)
        self._actors = [cls.remote(placement.threads) for _ in range(placement.actors)]
        try:
            self.info = ray.get([a.info.remote(device) for a in self._actors], timeout=start_timeout_s)
        except ray.exceptions.GetTimeoutError:
            self.close()
            raise MemlogError(f"Ray could not start {placement.actors} actor(s) of {placement.threads} CPU(s) and "
                              f"{placement.gpus:g} GPU within {start_timeout_s:.0f} s (is the cluster busy?)") from None
        except ray.exceptions.RayTaskError as err:
            self.close()
            raise _cause(err) from None
        except ray.exceptions.RayError as err:  # an actor died while starting (memlog missing on a node?)
            self.close()
            raise MemlogError(f"Ray actors could not start: {type(err).__name__}: {err}") from None
        except BaseException:
            self.close()
            raise
        self._pids = [int(i["pid"]) for i in self.info]
        other = sorted({f"{i['host']}: memlog {i['memlog']}" for i in self.info if i["memlog"] != __version__})
        if other:
            self.close()
            raise MemlogError(f"Ray workers run another memlog than this driver ({__version__}): {', '.join(other)}; "
                              "install the same version on every node")

    def map_ordered(self, fn: Callable[..., R], jobs: Iterable[Job]) -> Iterator[R]:
        ray = _ray()

        order: deque[tuple[Any, int]] = deque()  # (ref, actor) in job order
        running: dict[Any, int] = {}  # refs not yet seen finished -> actor
        load = [0] * len(self._actors)
        it = iter(jobs)
        exhausted = False
        try:
            while True:
                while not exhausted and len(order) < self.ahead:
                    k = min(range(len(load)), key=load.__getitem__)
                    if load[k] >= self.depth:
                        break
                    try:
                        job = next(it)
                    except StopIteration:
                        exhausted = True
                        break
                    ref = self._actors[k].run.remote(fn, job)
                    order.append((ref, k))
                    running[ref] = k
                    load[k] += 1
                if not order:
                    return
                head, k = order[0]
                if head in running:
                    ready, _ = ray.wait(list(running), num_returns=1)
                    for r in ready:
                        load[running.pop(r)] -= 1
                    continue
                order.popleft()
                yield self._result(head, k)
        finally:
            for ref, _ in order:
                try:
                    ray.cancel(ref)
                except Exception:  # already finished, or not cancellable: its result is dropped
                    pass

    def _result(self, ref: Any, k: int) -> Any:
        ray = _ray()

        try:
            pid, result = ray.get(ref)
        except ray.exceptions.RayTaskError as err:
            raise _cause(err) from None
        except ray.exceptions.RayError as err:
            raise WorkerLostError(f"a Ray worker died on each of {self.max_retries + 1} attempts at one job (out of "
                                  f"memory? a crash? see the Ray logs): {type(err).__name__}: {err}") from None
        if pid != self._pids[k]:  # Ray restarted this actor since we last heard from it
            self.restarts += 1
            self._pids[k] = pid
        return result

    def close(self) -> None:
        ray = _ray()

        for a in self._actors:
            try:
                ray.kill(a)
            except Exception:  # already gone
                pass
        self._actors = []


def _cause(err: Any) -> BaseException:
    """The exception a job raised on its worker (Ray wraps it)."""
    cause = getattr(err, "cause", None)
    return cause if isinstance(cause, BaseException) else err

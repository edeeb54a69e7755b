"""A step's jobs on a Ray cluster: actors that keep the models, results back in job order.

:class:`RayActors` is an :class:`~memlog.steps.parallel.Executor` like the local process pool:
the jobs are the steps' own (a module-level function and its picklable arguments, e.g.
``score_chunk(log, config, window, chunk)``), so a step runs on Ray without knowing it. Each
actor is one long-lived worker process holding the models (loaded once per process through
:func:`~memlog.steps.parallel.cached`, not once per job) and reserving the CPUs its ONNX Runtime
threads use, plus a share of a GPU on a node with GPUs. The actors are planned per node
(:func:`plan_placement` over :func:`cluster_nodes`: every actor fits the node it is planned on,
so actors never oversubscribe a node and never wait for a node that does not exist) and pinned
there (a soft node affinity: an actor whose node is lost is restarted elsewhere).

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
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import asdict, dataclass
from typing import Any, NamedTuple, TypeVar

from memlog._version import __version__
from memlog.errors import ConfigError, MemlogError
from memlog.runtime import Runtime, current, install
from memlog.steps.parallel import Job, cpu_count, log_levels, replay, run_job, worker_setup

__all__ = ["RAY_INSTALL", "ray_available", "require_ray", "connect", "Node", "cluster_nodes", "NodePlacement",
           "Placement", "plan_placement", "RayActors", "WorkerLostError"]

R = TypeVar("R")

RAY_INSTALL = "pip install 'memlog[ray]'"


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
    ``HOST:6379``), or else the runtime context's ``ray_address`` (:func:`memlog.runtime.current`;
    ``$RAY_ADDRESS`` for the command line and the API), or else a new local instance with this
    machine's cores. A process already connected (a notebook, a test) is used as it is. Returns
    whether this call connected, i.e. whether the caller should ``ray.shutdown()`` when done."""
    require_ray()
    ray = _ray()

    if ray.is_initialized():
        return False
    kw: dict[str, Any] = {"logging_level": logging.WARNING if quiet else logging.INFO, "log_to_driver": not quiet}
    target = address if address is not None else current().ray_address
    try:
        if not target:
            ray.init(num_cpus=cpu_count(), include_dashboard=False, **kw)
        else:
            ray.init(address=target, **kw)
    except Exception as exc:  # Ray raises ConnectionError, RuntimeError, ValueError...
        where = target or "a local instance"
        raise ConfigError(f"--ray {address or ''}".rstrip() + f": could not connect to Ray ({where}): {exc}") from None
    return True


class Node(NamedTuple):
    """One alive node of a Ray cluster: its CPUs and GPUs (totals, as the node declares them)
    and its Ray node id ("" for a node described without Ray, as in a plan made by hand)."""

    cpus: float
    gpus: float
    id: str = ""


def cluster_nodes() -> list[Node]:
    """The alive nodes of the connected Ray cluster (``ray.nodes()``), with their CPUs and GPUs."""
    ray = _ray()

    nodes = []
    for n in ray.nodes():
        if n.get("Alive"):
            res = n.get("Resources") or {}
            nodes.append(Node(float(res.get("CPU", 0.0)), float(res.get("GPU", 0.0)), str(n.get("NodeID", ""))))
    return nodes


@dataclass(frozen=True)
class NodePlacement:
    """``actors`` actors on the node ``node`` (a Ray node id; "" for a node without one), each
    reserving ``gpus`` of a GPU there (0: CPU actors)."""

    node: str
    actors: int
    gpus: float


@dataclass(frozen=True)
class Placement:
    """How jobs are placed: ``actors`` worker processes, each reserving ``threads`` CPUs (its ONNX
    Runtime and OpenCV threads); ``gpus``: the GPU share of a GPU actor (0: CPU actors only; the
    largest share when GPU nodes differ); ``nodes``: how many actors, with which GPU share, on
    each node (empty: anywhere Ray puts them, each with ``gpus``)."""

    actors: int
    threads: int
    gpus: float
    nodes: tuple[NodePlacement, ...] = ()

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["nodes"] = list(d["nodes"])  # as JSON reads it back
        return d


def _node_capacity(node: Node, threads: int, device: str, actors_per_gpu: int | None) -> tuple[int, float]:
    """(actors, GPU share of each) that one node holds by :func:`plan_placement`'s rule."""
    if node.cpus < threads:
        return 0, 0.0
    if device != "cpu" and node.gpus > 0:
        per_gpu = actors_per_gpu or max(1, min(MAX_ACTORS_PER_GPU, int(node.cpus / node.gpus) // threads))
        return min(int(node.gpus * per_gpu + 1e-9), int(node.cpus // threads)), 1.0 / per_gpu
    if device == "cuda":  # the models must run on a GPU: a CPU-only node holds no actor
        return 0, 0.0
    return int(node.cpus // threads), 0.0


def _spread(caps: list[int], n: int) -> list[int]:
    """``n`` actors over nodes that hold at most ``caps[i]`` each, one node after the other in turn."""
    got = [0] * len(caps)
    n = min(n, sum(caps))
    while n > 0:
        for i, cap in enumerate(caps):
            if n > 0 and got[i] < cap:
                got[i] += 1
                n -= 1
    return got


def _nodes_text(nodes: Sequence[Node]) -> str:
    return "; ".join(f"{n.cpus:g} CPU(s)" + (f" + {n.gpus:g} GPU(s)" if n.gpus else "") for n in nodes)


def plan_placement(nodes: Sequence[Node], *, workers: int | None = None, threads: int = 0, device: str = "auto",
                   actors_per_gpu: int | None = None) -> Placement:
    """The actors for a cluster of ``nodes`` (each with its CPUs and GPUs), planned node by node:
    every actor is planned on a node that holds its CPUs and its GPU share.

    On one node: without GPUs (or with ``device`` cpu), ``threads`` CPUs per actor (default 1)
    and as many actors as the node's CPUs hold. With GPUs (``device`` auto or cuda), every actor
    on the node shares a GPU: ``actors_per_gpu`` actors per GPU (default: the node's CPUs per GPU
    over ``threads``, at most :data:`MAX_ACTORS_PER_GPU`), as many as its GPUs and CPUs hold:
    decoding, the detector and entropy stay on the CPU (~0.2 core-seconds per frame) while ResMem
    needs ~5 ms of an H100 per frame, so a GPU needs the frames of many CPU workers; the cap
    bounds the GPU memory of their ONNX Runtime sessions. With ``device`` auto a CPU-only node
    holds CPU actors; with ``device`` cuda it holds none.

    The placement is the sum over the nodes; ``workers`` asks for that many actors instead, taken
    from the GPU nodes first, then the CPU nodes, spread over the nodes in turn. Raises
    :class:`ConfigError` naming what is missing when no node holds one actor, or the nodes cannot
    hold ``workers`` actors."""
    t = threads or 1
    if device == "cuda" and not any(n.gpus > 0 for n in nodes):
        raise ConfigError("--device cuda: the Ray cluster has no GPU (drop --device, or use --device cpu)")
    if not nodes:
        raise ConfigError("the Ray cluster has no alive node")
    caps = [_node_capacity(n, t, device, actors_per_gpu) for n in nodes]
    total = sum(c for c, _ in caps)
    if total == 0:
        usable = [n for n in nodes if n.gpus > 0] if device == "cuda" else list(nodes)
        kind = "GPU node" if device == "cuda" else "node"
        most = max((n.cpus for n in usable), default=0.0)
        if most < t:
            raise ConfigError(f"--threads {t}: an actor needs {t} CPU(s) on one node; the largest {kind} of the Ray "
                              f"cluster has {most:g} (nodes: {_nodes_text(nodes)})")
        raise ConfigError(f"no Ray node holds one actor of {t} CPU(s) and its GPU share: a node's GPUs times its "
                          f"actors per GPU is below 1 (nodes: {_nodes_text(nodes)}); raise --actors-per-gpu")
    if workers is not None and workers > total:
        gpu_part = " and a GPU share" if any(share for _, share in caps) else ""
        raise ConfigError(f"--workers {workers}: the Ray cluster's nodes hold at most {total} actor(s) of {t} CPU(s)"
                          f"{gpu_part} each (nodes: {_nodes_text(nodes)}); use fewer --workers or --threads")
    counts = [c for c, _ in caps]
    if workers is not None:
        gpu = [k for k, (_, share) in enumerate(caps) if share > 0]
        cpu = [k for k, (_, share) in enumerate(caps) if share == 0]
        counts = [0] * len(caps)
        left = workers
        for group in (gpu, cpu):
            got = _spread([caps[k][0] for k in group], min(left, sum(caps[k][0] for k in group)))
            for k, g in zip(group, got):
                counts[k] = g
            left -= sum(got)
    placed = tuple(NodePlacement(n.id, c, share) for n, c, (_, share) in zip(nodes, counts, caps) if c > 0)
    return Placement(sum(p.actors for p in placed), t, max((p.gpus for p in placed), default=0.0), placed)


class _Worker:
    """One Ray actor: a worker process that runs jobs; models stay in its process cache. Ray
    starts it afresh (on any node), so it is given what the driver's settings say: its runtime
    context (the pixel cap, the entropy kernel choice, the model cache's bound; the model cache
    directory stays the node's own) and the levels of the ``memlog`` loggers (what its jobs log goes
    back with their results)."""

    def __init__(self, threads: int, runtime: Runtime, levels: dict[str, int]) -> None:
        install(runtime.replace(cache_dir=current().cache_dir))  # models are where this node keeps them
        worker_setup(True, levels)
        try:
            import cv2

            cv2.setNumThreads(threads)  # OpenCV's pool (resize, detector) within the actor's CPUs
        except ImportError:
            pass

    def info(self, device: str) -> dict[str, Any]:
        """Who this worker is; raises the model layer's error when ``device`` cannot be used here."""
        from memlog.models.runtime import choose_providers

        context = _ray().get_runtime_context()
        return {"pid": os.getpid(), "host": platform.node(), "node": context.get_node_id(),
                "memlog": __version__, "providers": choose_providers(device),
                "gpus": ",".join(str(g) for g in context.get_accelerator_ids().get("GPU", [])) or None}

    def run(self, fn: Callable[..., Any], job: Job) -> tuple[int, Any, list[logging.LogRecord]]:
        result, records = run_job(fn, job)
        return os.getpid(), result, records


class RayActors:
    """An executor of ``placement.actors`` Ray actors, each on the node ``placement.nodes`` plans
    it on (a soft node affinity: it waits for room there, and goes elsewhere only when that node
    is gone). Each actor has at most ``depth`` jobs queued (the next one is ready when it
    finishes) and at most ``ahead`` jobs are in flight beyond the one whose result is awaited
    next (bounded memory for results waiting to be merged). A dead actor is restarted by Ray and
    its job run again up to ``max_retries`` times; :attr:`restarts` counts the worker processes
    lost so far."""

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
        affinity = importlib.import_module("ray.util.scheduling_strategies").NodeAffinitySchedulingStrategy
        cls = ray.remote(_Worker)
        runtime, levels = current(), log_levels()  # the driver's settings, which a Ray worker does not inherit
        self._actors = []
        for group in placement.nodes or (NodePlacement("", placement.actors, placement.gpus),):
            pin = {"scheduling_strategy": affinity(group.node, soft=True)} if group.node else {}
            one = cls.options(num_cpus=placement.threads, num_gpus=group.gpus, max_restarts=-1,
                              max_task_retries=max_retries, **pin)
            self._actors += [one.remote(placement.threads, runtime, levels) for _ in range(group.actors)]
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
            pid, result, records = ray.get(ref)
        except ray.exceptions.RayTaskError as err:
            cause = _cause(err)
            replay(cause)
            raise cause from None
        except ray.exceptions.RayError as err:
            raise WorkerLostError(f"a Ray worker died on each of {self.max_retries + 1} attempts at one job (out of "
                                  f"memory? a crash? see the Ray logs): {type(err).__name__}: {err}") from None
        if pid != self._pids[k]:  # Ray restarted this actor since we last heard from it
            self.restarts += 1
            self._pids[k] = pid
        replay(records)
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

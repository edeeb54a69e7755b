"""Pipeline step ``batch``: score and map many logs, on local worker processes or a Ray cluster.

For every log, :func:`batch` runs :func:`~memlog.steps.score.score` and then
:func:`~memlog.steps.map.make_map` (which scores again as ``memlog map`` does, not reusing the
first scores), writing ``OUTDIR/NAME.scored.mcap``, ``NAME.map.mcap`` and ``NAME.map.parquet``:
the same files, timing fields aside, as ``memlog score`` and ``memlog map`` run on one process.
Each step cuts a log into chunks of frames (time windows) that run as jobs on an executor
(:mod:`memlog.steps.parallel`: local processes; :mod:`memlog.steps.ray_pool`: Ray actors) and
are merged in log-time order by the one writer, this process (the driver).

* Outputs are written atomically by the driver, into a directory it can write; with Ray, the
  workers only read the logs, so the logs must be at the same path on every node (a shared
  filesystem) while OUTDIR need only be reachable by the driver.
* Resume: the summary file (default ``OUTDIR/batch.json``, rewritten after every log) records
  each finished log's input identity (:func:`~memlog.io.identity.log_identity`), the key of
  what its outputs depend on (every output setting, the memlog version and the sha256 of every
  model the run uses) and each output's size and modification time; a rerun skips a log whose
  record still matches and says so. A worker process that dies (out of memory) fails its log;
  the pool is replaced for the logs after it.
* A damaged log is finished as far as it can be read and reported (exit 3); a log that cannot be
  read at all, or whose map would be empty, fails (exit 1) after the others have run.
"""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
import glob
import hashlib
import json
import os
import threading
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from memlog._version import __version__
from memlog.configfile import check_ints
from memlog.errors import ConfigError, MemlogError
from memlog.io.atomic import check_output
from memlog.io.base import FrameWindow
from memlog.io.identity import log_identity, log_names
from memlog.io.open import open_log
from memlog.io import spool
from memlog.io.records import ReadReport
from memlog.models.runtime import choose_providers
from memlog.outputs.results import write_results
from memlog.progress import Bar, info, redirect, warning
from memlog.runtime import current
from memlog.settings import Flag, nonneg_int, positive_int, setting
from memlog.settings import ray_address as ray_address_check
from memlog.steps.map import MapConfig, make_map
from memlog.steps.parallel import Executor, InProcess, cpu_count, make_executor
from memlog.steps.score import score

__all__ = ["batch", "BatchConfig", "BatchResult", "LogResult", "read_manifest", "SUMMARY_NAME", "OUTPUT_SUFFIXES"]

SUMMARY_NAME = "batch.json"
#: Output kind -> file name suffix after the log's name.
OUTPUT_SUFFIXES = {"scored": ".scored.mcap", "map": ".map.mcap", "descriptors": ".map.parquet"}

Status = Literal["ok", "damaged", "failed", "skipped"]


@dataclass(frozen=True)
class BatchConfig:
    """Settings of ``memlog batch`` (the ``[batch]`` table; scoring, selection and the map step
    keep their own in ``map``).

    ``map``: the score and map settings (``map.topics`` and ``map.stride`` choose the frames of
    both steps; ``map.workers`` and ``map.descriptors_path`` are not used); ``workers``: local
    worker processes (default: the cores), or with ``ray`` the number of Ray actors (default: as
    many as the cluster's CPUs, or GPUs, hold); ``ray``: run the jobs on Ray, at ``ray_address``
    (``auto``, ``ray://HOST:10001``; None: ``$RAY_ADDRESS`` or a new local instance);
    ``actors_per_gpu``: actors sharing one GPU (default: CPUs per GPU over threads, at most 16);
    ``max_retries``: attempts at a job after its worker died; ``resume``: skip logs whose
    outputs are up to date; ``chunk_frames``: frames per scoring job; ``logs_at_once``: logs
    the driver works on at the same time (their jobs share the workers, so one log's serial
    parts, such as copying records and writing, overlap another's scoring).
    """

    map: MapConfig = field(default_factory=MapConfig)
    workers: int | None = setting(None, Flag(
        ("--workers",), "local worker processes (default: the cores); with --ray, Ray actors (default: as many as "
        "the cluster's nodes hold, each by its own CPUs and GPUs)", "performance", positive_int, metavar="N"))
    ray: bool = False
    ray_address: str | None = setting(None, Flag(
        ("--ray",), "run the jobs on Ray (needs memlog[ray]): the cluster at ADDRESS (auto, ray://HOST:10001, "
        "HOST:6379), else $RAY_ADDRESS or a new local Ray instance", check=ray_address_check, nargs="?",
        const="local", metavar="ADDRESS", value=lambda v: None if v == "local" else v, also={"ray": True}))
    actors_per_gpu: int | None = setting(None, Flag(
        ("--actors-per-gpu",), "with --ray on GPUs: actors sharing one GPU (default: the node's CPUs per GPU / "
        "--threads, at most 16)", "performance", positive_int, metavar="N"))
    max_retries: int = setting(3, Flag(("--max-retries",), "attempts at a job after its worker died (default 3)",
                                       "performance", nonneg_int, metavar="N"))
    resume: bool = setting(True, Flag(("--no-resume",), "score and map every log, even those up to date", "outputs",
                                      action="store_true", value=lambda v: False))
    chunk_frames: int = 16
    logs_at_once: int = setting(1, Flag(
        ("--logs-at-once",), "logs worked on at the same time, sharing the workers (default 1)", "performance",
        positive_int, metavar="N"))

    def __post_init__(self) -> None:
        check_ints(self, {"workers": 1, "actors_per_gpu": 1, "max_retries": 0, "chunk_frames": 1, "logs_at_once": 1},
                   optional=True)
        if self.ray_address is not None and not self.ray:
            raise ConfigError("ray_address is given but ray is off (use --ray ADDRESS)")
        if self.map.descriptors_path is not None:
            object.__setattr__(self, "map", dataclasses.replace(self.map, descriptors_path=None))

    def window(self) -> FrameWindow:
        """The frames the score step reads (the map step's topics and stride)."""
        return FrameWindow(self.map.topics, stride=self.map.stride)

    def output_settings(self) -> dict[str, Any]:
        """What the outputs depend on (resume compares it): every setting but the performance
        ones (workers, threads, Ray)."""
        m = dataclasses.replace(self.map, workers=1, score=self.map.score.replace(threads=0))
        settings: dict[str, Any] = json.loads(json.dumps(dataclasses.asdict(m), sort_keys=True))
        return settings

    def models(self) -> list[str]:
        """The models whose files the outputs depend on."""
        names = ["resmem", "ssd-mobilenet-v2-coco"]
        if self.map.score.mode == "fast":
            names.append("resmem-int8")
        if self.map.descriptor is not None and ("dinov2" in self.map.descriptor or self.map.descriptor == "auto"):
            names.append("dinov2-vits14")
        return names

    def settings_key(self, models: dict[str, str | None] | None = None) -> str:
        """sha256 of what the outputs depend on (recorded per log): :meth:`output_settings`, the
        memlog version and ``models`` (name -> sha256 of the model file, None when not prepared;
        default: read now, :func:`model_versions`)."""
        key = {"settings": self.output_settings(), "memlog_version": __version__,
               "models": model_versions(self.models()) if models is None else models}
        return hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()


def model_versions(names: Sequence[str]) -> dict[str, str | None]:
    """sha256 of each named model as prepared on this machine (None when it is not prepared: a
    run that needs it fails and says so; one that does not, such as ``auto`` choosing the
    thumbnail, is not affected)."""
    from memlog.models.registry import list_models

    ready = {m.name: m.sha256 if m.ready else None for m in list_models()}
    return {n: ready.get(n) for n in names}


@dataclass
class LogResult:
    """What happened to one log: ``status`` ok, damaged (finished, input damaged), failed (see
    ``error``) or skipped (outputs up to date); ``frames`` scored and ``kept`` in the map;
    ``worker_failures``: worker processes lost (and their jobs retried) while it ran; ``notes``:
    what the map's topics say of themselves (a map smaller than the keep fraction asks, and why)."""

    log: str
    name: str
    status: Status
    outputs: dict[str, str]
    frames: int | None = None
    kept: int | None = None
    seconds: float = 0.0
    worker_failures: int = 0
    damage: list[str] = field(default_factory=list)
    error: str | None = None
    identity: dict[str, Any] | None = None
    settings: str | None = None
    report: ReadReport | None = None
    files: dict[str, dict[str, int]] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        return {
            "log": self.log, "name": self.name, "status": self.status, "frames": self.frames, "kept": self.kept,
            "seconds": round(self.seconds, 3), "worker_failures": self.worker_failures, "damage": self.damage,
            "error": self.error, "identity": self.identity, "settings_sha256": self.settings, "outputs": self.outputs,
            "files": self.files, "notes": self.notes,
        }


@dataclass
class BatchResult:
    """What :func:`batch` did: one :class:`LogResult` per log, in the order given."""

    outdir: Path
    summary: Path
    logs: list[LogResult]
    seconds: float
    executor: dict[str, Any]
    settings: dict[str, Any]

    @property
    def exit_code(self) -> int:
        """1 when a log failed, else 3 when one was damaged, else 0."""
        if any(r.status == "failed" for r in self.logs):
            return 1
        return 3 if any(r.damage for r in self.logs) else 0

    def to_dict(self) -> dict[str, Any]:
        counts = {s: sum(r.status == s for r in self.logs) for s in ("ok", "damaged", "failed", "skipped")}
        run = [r for r in self.logs if r.status in ("ok", "damaged")]
        frames = sum(r.frames or 0 for r in run)
        return {
            "memlog_version": __version__, "outdir": str(self.outdir), "seconds": round(self.seconds, 3),
            "exit_code": self.exit_code, "executor": self.executor, "settings": self.settings,
            "totals": {"logs": len(self.logs), **counts, "frames": frames, "kept": sum(r.kept or 0 for r in run),
                       "worker_failures": sum(r.worker_failures for r in self.logs),
                       "frames_per_s": round(frames / self.seconds, 4) if self.seconds > 0 else None},
            "logs": [r.to_dict() for r in self.logs],
        }


def read_manifest(path: str | os.PathLike[str]) -> list[str]:
    """The logs listed in a manifest: one path per line (relative to the manifest's directory),
    blank lines and ``#`` comments ignored."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(f"--manifest {p}: no such file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"--manifest {p}: cannot read it ({exc})") from None
    logs = []
    for line in text.splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            logs.append(line if os.path.isabs(line) else str(p.parent / line))
    return logs


def _outputs(outdir: Path, name: str, descriptors: bool = True) -> dict[str, str]:
    """The outputs of one log (no descriptor file when the map has no descriptors)."""
    return {kind: str(outdir / f"{name}{suffix}") for kind, suffix in OUTPUT_SUFFIXES.items()
            if descriptors or kind != "descriptors"}


def _file_stats(outputs: dict[str, str]) -> dict[str, dict[str, int]] | None:
    stats = {}
    for kind, path in outputs.items():
        try:
            st = os.stat(path)
        except OSError:
            return None
        stats[kind] = {"size": st.st_size, "mtime_ns": st.st_mtime_ns}
    return stats


def _read_summary(path: Path) -> dict[str, dict[str, Any]]:
    """The log records of an earlier summary by name (none when it is missing or unreadable)."""
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        return {str(r["name"]): r for r in data.get("logs", []) if isinstance(r, dict) and "name" in r}
    except (OSError, ValueError, AttributeError, TypeError, KeyError):
        return {}


class _Executors:
    """The executor of a run, made when the first log needs it (Ray is not started for a run
    that skips every log) and made again after a local pool broke."""

    def __init__(self, cfg: BatchConfig) -> None:
        self.cfg = cfg
        self.ex: Executor | None = None
        self.own_ray = False
        self.description: dict[str, Any] = {"kind": "ray" if cfg.ray else "processes", "started": False}
        self._lock = threading.RLock()  # logs running side by side share one executor

    def get(self) -> Executor:
        with self._lock:
            return self._get()

    def broken(self, ex: Executor) -> None:
        """``ex`` lost a worker process: the logs after this one get a new pool (the logs that
        shared it while it broke fail with this one)."""
        with self._lock:
            if self.ex is ex:
                self.ex = None
                ex.close()

    def _get(self) -> Executor:
        if self.ex is not None and getattr(self.ex, "broken", False):
            self.broken(self.ex)  # lost a worker while another log ran, before that log saw it
        if self.ex is not None:
            return self.ex
        cfg = self.cfg
        if not cfg.ray:
            workers = cfg.workers or cpu_count()
            self.ex = make_executor(workers)
            self.description = {"kind": "processes" if workers > 1 else "in-process", "started": True,
                                "workers": workers}
            return self.ex
        from memlog.progress import is_quiet
        from memlog.steps.ray_pool import RayActors, cluster_nodes, connect, plan_placement

        self.own_ray = connect(cfg.ray_address, quiet=is_quiet())
        try:
            nodes = cluster_nodes()
            cpus, gpus = sum(n.cpus for n in nodes), sum(n.gpus for n in nodes)
            placement = plan_placement(nodes, workers=cfg.workers, threads=cfg.map.score.threads,
                                       device=cfg.map.score.device, actors_per_gpu=cfg.actors_per_gpu)
            ex = RayActors(placement, device=cfg.map.score.device, max_retries=cfg.max_retries)
        except BaseException:
            self.close()
            raise
        self.ex = ex
        devices = sorted({str(i["providers"][0]).removesuffix("ExecutionProvider").lower() for i in ex.info})
        self.description = {"kind": "ray", "started": True, "address": cfg.ray_address, "cluster_cpus": cpus,
                            "cluster_gpus": gpus,
                            **placement.to_dict(), "devices": devices,
                            "hosts": sorted({str(i["host"]) for i in ex.info})}
        info(f"Ray: {placement.actors} actor(s) x {placement.threads} CPU"
             + (f" + {placement.gpus:g} GPU" if placement.gpus else "") + f" on {len(self.description['hosts'])} "
             f"node(s) ({cpus:g} CPUs, {gpus:g} GPUs); models run on {', '.join(devices)}")
        if placement.gpus and devices == ["cpu"]:
            warning("the actors hold GPUs but ONNX Runtime there has no CUDA provider; install "
                 "memlog[gpu] on the workers")
        return ex

    def restarts(self) -> int:
        return int(getattr(self.ex, "restarts", 0))

    def close(self) -> None:
        if self.ex is not None:
            self.ex.close()
            self.ex = None
        if self.own_ray:
            import importlib

            importlib.import_module("ray").shutdown()
            self.own_ray = False


@contextlib.contextmanager
def _locked(outdir: Path) -> Iterator[None]:
    """One batch at a time writes into ``outdir`` (an advisory lock on the directory)."""
    try:
        import fcntl
    except ImportError:  # not POSIX
        yield
        return
    fd = os.open(outdir, os.O_RDONLY)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise ConfigError(f"-o {outdir}: another memlog batch is writing there") from None
        yield
    finally:
        os.close(fd)


def _prepare(logs: Sequence[str], outdir: Path, descriptors: bool) -> list[tuple[str, str, dict[str, str]]]:
    """(log, name, outputs) per log, after creating ``outdir``; usage errors (names that collide,
    an output that is an input) before any work."""
    names = log_names(logs, outdir, "run them into different directories")
    outdir.mkdir(exist_ok=True)
    items = []
    for log, name in zip(logs, names):
        outs = _outputs(outdir, name, descriptors)
        for path in outs.values():
            check_output(path, logs, flag="-o")
        items.append((log, name, outs))
    return items


def batch(
    logs: Sequence[str | os.PathLike[str]],
    outdir: str | os.PathLike[str],
    config: BatchConfig | None = None,
    *,
    manifest: str | os.PathLike[str] | None = None,
    summary: str | os.PathLike[str] | None = None,
) -> BatchResult:
    """Score and map every log of ``logs`` (and of ``manifest``) into ``outdir`` (created when its
    parent exists); see the module doc. Writes the JSON summary to ``summary`` (default
    ``OUTDIR/batch.json``) after every log. A failing log does not stop the others: see each
    :class:`LogResult` and :attr:`BatchResult.exit_code`."""
    t0 = time.perf_counter()
    cfg = config or BatchConfig()
    all_logs = [str(x) for x in logs] + (read_manifest(manifest) if manifest is not None else [])
    if not all_logs:
        raise ConfigError("batch: no logs given (LOG... or --manifest FILE)")
    if cfg.ray:  # workers on other nodes have another working directory
        all_logs = [os.path.abspath(x) for x in all_logs]
    out = check_output(outdir, all_logs, flag="-o", directory=True)
    summary_path = Path(summary) if summary is not None else out / SUMMARY_NAME
    if summary is not None:
        check_output(summary_path, all_logs, flag="--summary")
    if cfg.ray:
        from memlog.steps.ray_pool import require_ray

        require_ray()
    else:
        choose_providers(cfg.map.score.device)  # --device cuda without CUDA: said before any work
    items = _prepare(all_logs, out, cfg.map.descriptor is not None)
    settings = cfg.output_settings()
    key = cfg.settings_key()
    window = cfg.window()
    with _locked(out):
        _remove_leftovers(out, items)
        previous = _read_summary(summary_path)
        results: list[LogResult] = []
        todo: list[tuple[LogResult, int | None]] = []
        for log, name, outs in items:
            r = _preflight(log, name, outs, window, key, previous.get(name) if cfg.resume else None)
            results.append(r)
            if r.status == "ok":
                todo.append((r, r.frames))
            elif r.status == "skipped":
                info(f"{name}: outputs up to date (same input and settings): skipped")
            else:
                info(f"{name}: failed: {r.error}")
        executors = _Executors(cfg)
        known = [n for _, n in todo]
        total = 2 * sum(n for n in known if n is not None) if None not in known else None  # score + map passes
        bar = Bar(total, "batch", "frame") if todo else None

        def sink(desc: str, unit: str) -> None:
            if unit == "frame" and bar is not None:
                bar.update()

        def save() -> BatchResult:
            res = BatchResult(out, summary_path, results, time.perf_counter() - t0, executors.description, settings)
            d = res.to_dict()
            mine = {r.name for r in results}
            d["logs"] += [r for n, r in previous.items() if n not in mine]  # other runs' logs stay resumable
            write_results(summary_path, d)
            return res

        try:
            with redirect(sink):
                runs = [r for r, _ in todo]
                for k, r in enumerate(_run_all(runs, cfg, window, key, executors, bar)):
                    line = f"[{k + 1}/{len(runs)}] {r.name}: {r.status}"
                    if r.status != "failed":
                        line += f", {r.frames} frames, {r.kept} kept, {r.seconds:.1f} s"
                    if r.worker_failures:
                        line += f", {r.worker_failures} worker failure(s) retried"
                    if r.notes:
                        line += "; " + "; ".join(r.notes)
                    (bar.write if bar is not None else info)(line + (f": {r.error}" if r.error else ""))
                    save()
        finally:
            if bar is not None:
                bar.close()
            executors.close()
        return save()


def _remove_leftovers(outdir: Path, items: list[tuple[str, str, dict[str, str]]]) -> None:
    """Temporary files of our outputs left by a run that was killed (``.NAME.*.tmp``, see
    :class:`~memlog.io.atomic.AtomicFile`): nobody else writes them while we hold the lock."""
    gone = 0
    for _, _, outs in items:
        for path in outs.values():
            for tmp in outdir.glob(f".{glob.escape(Path(path).name)}.*.tmp"):
                tmp.unlink(missing_ok=True)
                gone += 1
    if gone:
        info(f"removed {gone} temporary file(s) an interrupted run left in {outdir}")


def _preflight(log: str, name: str, outs: dict[str, str], window: FrameWindow, settings: str,
               prev: dict[str, Any] | None) -> LogResult:
    """The log's identity and frame count (status ok: to run), or skipped (up to date), or
    failed (missing, unreadable)."""
    r = LogResult(log, name, "ok", outs)
    if not os.path.exists(log):
        r.status, r.error = "failed", f"{log}: no such file or directory"
        return r
    try:
        r.identity = log_identity(log)
    except OSError as exc:
        r.status, r.error = "failed", f"{log}: cannot read it ({exc})"
        return r
    if prev is not None and prev.get("status") in ("ok", "damaged", "skipped") and prev.get("identity") == r.identity \
            and prev.get("settings_sha256") == settings and _file_stats(outs) == prev.get("files"):
        r.status = "skipped"
        r.frames, r.kept, r.damage = prev.get("frames"), prev.get("kept"), list(prev.get("damage") or [])
        r.files, r.settings = prev["files"], settings
        return r
    try:
        with open_log(log) as reader:
            reader.quiet_warnings()  # the run reports damage when it reads the frames
            r.frames = reader.count_frames(window)
    except MemlogError as exc:
        r.status, r.error = "failed", str(exc)
    return r


def _run_all(runs: list[LogResult], cfg: BatchConfig, window: FrameWindow, settings: str, executors: _Executors,
             bar: Bar | None) -> Iterator[LogResult]:
    """Run the logs, ``cfg.logs_at_once`` at a time (threads of this process sharing the workers),
    yielding each as it finishes."""
    if cfg.logs_at_once == 1 or len(runs) == 1 or isinstance(executors.get(), InProcess):  # (one process's
        # models are not shared by threads: the detector's OpenCV net is not thread-safe)
        for k, one in enumerate(runs):
            if bar is not None:
                bar.set_note(f"log {k + 1}/{len(runs)}: {one.name}")
            _run_one(one, cfg, window, settings, executors)
            yield one
        return
    from concurrent.futures import FIRST_COMPLETED, Future, ThreadPoolExecutor, wait

    it = iter(runs)
    running: dict[Future[None], LogResult] = {}
    with ThreadPoolExecutor(cfg.logs_at_once, thread_name_prefix="memlog-log") as pool:
        try:
            while True:
                while len(running) < cfg.logs_at_once:
                    nxt = next(it, None)
                    if nxt is None:
                        break
                    ctx = contextvars.copy_context()  # the progress sink and quiet setting of this run
                    running[pool.submit(ctx.run, _run_one, nxt, cfg, window, settings, executors)] = nxt
                if not running:
                    return
                if bar is not None:
                    bar.set_note("running " + ", ".join(r.name for r in running.values()))
                done, _ = wait(running, return_when=FIRST_COMPLETED)
                for f in done:
                    f.result()
                    yield running.pop(f)
        except BaseException:
            executors.close()  # the other logs' jobs fail now: their outputs are dropped, not finished
            raise


def _run_one(r: LogResult, cfg: BatchConfig, window: FrameWindow, settings: str, executors: _Executors) -> None:
    """Score, then map, one log (``r`` is filled in); a broken local pool is made again for the
    logs after it."""
    from concurrent.futures.process import BrokenProcessPool

    t0 = time.perf_counter()
    ex = executors.get()
    before = executors.restarts()
    try:
        with spool.job(r.log):  # (score's reads serve map's passes: memlog.io.spool)
            run = score(r.log, r.outputs["scored"], cfg.map.score, window, executor=ex, chunk_frames=cfg.chunk_frames)
            r.frames = sum(t.frames_seen for t in run.topics.values())
            res = make_map(r.log, r.outputs["map"], cfg.map, executor=ex)
        r.kept = res.frames_kept
        r.notes = [f"{t}: {short}" for t, sel in res.selections.items() if (short := sel.shortfall())]
        damage = run.report.damage()
        if res.report is not None:
            damage += [d for d in res.report.damage() if d not in damage]
        r.damage, r.report = damage, run.report
        r.status = "damaged" if damage else "ok"
        r.files = _file_stats(r.outputs) or {}
    except MemlogError as exc:
        r.status, r.error = "failed", str(exc)
    except BrokenProcessPool:
        r.status, r.error = "failed", "a worker process died (out of memory?); the pool was restarted"
        r.worker_failures = 1
        executors.broken(ex)
    except Exception as exc:  # a bug: the other logs still run; the summary says what happened
        if current().debug:  # MEMLOG_DEBUG
            import traceback

            traceback.print_exc()
        r.status, r.error = "failed", f"internal error: {type(exc).__name__}: {exc}"
    r.settings = settings
    r.worker_failures += max(0, executors.restarts() - before)
    r.seconds = time.perf_counter() - t0

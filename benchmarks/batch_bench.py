"""``memlog batch`` throughput: one process vs local worker processes vs a local Ray instance.

Runs ``batch`` (score + map per log, fresh output directory each time) over the shared logs in
each mode, ``--repeats`` times, and prints logs/hour and frames/s (frames = frames scored per log;
each is scored twice, by ``score`` and by ``map``) as min-max over the repeats, with the load
average around each run (the machine is shared). Then the Ray overhead per task: no-op jobs
through the Ray actors and through the process pool.

ResMem costs ~1-4 s per frame on 2 cores, so the default is every 24th frame of the three EuRoC
logs with the real model; ``--model stand-in`` uses the tests' stand-in ResMem (milliseconds per
frame) to show what the pipeline around the CNN costs::

    python benchmarks/batch_bench.py [--logs ...] [--stride 24] [--repeats 2] [--model real|stand-in]
"""

from __future__ import annotations

import argparse
import logging
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from memlog.progress import set_quiet  # noqa: E402
from memlog.steps.batch import BatchConfig, batch  # noqa: E402
from memlog.steps.map import MapConfig  # noqa: E402
from memlog.steps.parallel import Processes, cpu_count  # noqa: E402

SHARED = Path(os.environ.get("MEMLOG_SHARED_DATA", ROOT.parent / "shared" / "data"))
DEFAULT_LOGS = ["euroc_micro_ros2.mcap", "euroc_micro_ros1.bag", "euroc_micro_ros2_db3"]


def _noop(x: int) -> int:
    return x


def run_mode(name: str, logs: list[Path], cfg: BatchConfig, work: Path) -> dict[str, float]:
    out = work / name
    shutil.rmtree(out, ignore_errors=True)
    load0 = os.getloadavg()[0]
    t0 = time.perf_counter()
    res = batch(logs, out, cfg)
    dt = time.perf_counter() - t0
    load1 = os.getloadavg()[0]
    bad = [r.name for r in res.logs if r.status != "ok"]
    if bad:
        raise SystemExit(f"{name}: logs not ok: {bad}")
    frames = sum(r.frames or 0 for r in res.logs)
    return {"seconds": dt, "frames": frames, "logs": len(logs), "load": max(load0, load1)}


def task_overhead(n: int, workers: int) -> dict[str, float]:
    """Seconds per no-op job, in job order, through Ray actors and through the process pool."""
    from memlog.steps.ray_pool import Placement, RayActors

    out = {}
    ex = RayActors(Placement(workers, 1, 0.0))
    try:
        list(ex.map_ordered(_noop, [(i,) for i in range(20)]))  # warm
        t0 = time.perf_counter()
        assert list(ex.map_ordered(_noop, [(i,) for i in range(n)])) == list(range(n))
        out["ray"] = (time.perf_counter() - t0) / n
    finally:
        ex.close()
    pool = Processes(workers)
    try:
        list(pool.map_ordered(_noop, [(i,) for i in range(20)]))
        t0 = time.perf_counter()
        assert list(pool.map_ordered(_noop, [(i,) for i in range(n)])) == list(range(n))
        out["processes"] = (time.perf_counter() - t0) / n
    finally:
        pool.close()
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--logs", nargs="+", default=DEFAULT_LOGS, help="shared logs (names in the shared data folder)")
    ap.add_argument("--stride", type=int, default=24)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--model", choices=["real", "stand-in"], default="real")
    ap.add_argument("--modes", nargs="+", default=["one process", "--workers 2", "Ray local", "Ray, 2 at once"],
                    help="one process, --workers 2, Ray local, 'Ray, 2 at once' (--logs-at-once 2)")
    ap.add_argument("--tasks", type=int, default=500, help="no-op jobs for the per-task overhead")
    args = ap.parse_args()
    set_quiet(True)
    logs = [SHARED / n for n in args.logs]
    for log in logs:
        if not log.exists():
            raise SystemExit(f"{log}: missing (the shared data)")
    import ray

    runtime_env: dict[str, object] = {"env_vars": {"PYTHONPATH": str(ROOT)}}
    if args.model == "stand-in":
        import pytest

        from tests.stand_in import SWITCH_ENV, use_stand_in

        switch = Path(tempfile.mkdtemp()) / "on"
        switch.touch()
        runtime_env = {"env_vars": {"PYTHONPATH": str(ROOT), SWITCH_ENV: str(switch)},
                       "worker_process_setup_hook": "tests.stand_in.install"}
        use_stand_in(pytest.MonkeyPatch())  # this process and the forked local workers
    t0 = time.perf_counter()
    ray.init(num_cpus=cpu_count(), include_dashboard=False, logging_level=logging.WARNING, log_to_driver=False,
             runtime_env=runtime_env)
    ray_start = time.perf_counter() - t0
    mcfg = MapConfig(stride=args.stride)
    modes = {"one process": BatchConfig(map=mcfg, workers=1, resume=False),
             "--workers 2": BatchConfig(map=mcfg, workers=2, resume=False),
             "Ray local": BatchConfig(map=mcfg, ray=True, workers=2, resume=False),
             "Ray, 2 at once": BatchConfig(map=mcfg, ray=True, workers=2, resume=False, logs_at_once=2)}
    work = Path(tempfile.mkdtemp(prefix="memlog-batch-bench-"))
    runs: dict[str, list[dict[str, float]]] = {m: [] for m in args.modes}
    try:
        for rep in range(args.repeats):
            for m in args.modes:
                runs[m].append(run_mode(m.replace(" ", "_"), logs, modes[m], work))
                r = runs[m][-1]
                print(f"# repeat {rep + 1} {m}: {r['seconds']:.1f} s, {r['frames']:.0f} frames, load {r['load']:.1f}",
                      file=sys.stderr)
        overhead = task_overhead(args.tasks, 2)
    finally:
        ray.shutdown()
        shutil.rmtree(work, ignore_errors=True)

    def rng(vals: list[float], fmt: str) -> str:
        lo, hi = min(vals), max(vals)
        return format(lo, fmt) if f"{lo:{fmt}}" == f"{hi:{fmt}}" else f"{lo:{fmt}}-{hi:{fmt}}"

    frames = runs[args.modes[0]][0]["frames"]
    print(f"memlog batch, {len(logs)} logs ({', '.join(args.logs)}), every {args.stride}th frame: {frames:.0f} "
          f"frames, each scored by score and by map; ResMem {args.model}; {cpu_count()} cores; {args.repeats} "
          "repeat(s), min-max")
    print(f"{'mode':<16}{'seconds':>14}{'logs/hour':>14}{'frames/s':>14}{'load avg':>12}")
    for m in args.modes:
        rs = runs[m]
        print(f"{m:<16}{rng([r['seconds'] for r in rs], '.1f'):>14}"
              f"{rng([3600 * r['logs'] / r['seconds'] for r in rs], '.0f'):>14}"
              f"{rng([r['frames'] / r['seconds'] for r in rs], '.3f'):>14}{rng([r['load'] for r in rs], '.1f'):>12}")
    print(f"Ray start-up (ray.init, local instance): {ray_start:.1f} s; per no-op task in job order: Ray actors "
          f"{overhead['ray'] * 1e3:.2f} ms, process pool {overhead['processes'] * 1e3:.2f} ms ({args.tasks} tasks, "
          "2 workers)")


if __name__ == "__main__":
    main()

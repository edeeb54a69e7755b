#!/usr/bin/env python3
"""memlog benchmarks: print tables of throughput and peak memory on the shared logs.

    python benchmarks/run.py                 # every table
    python benchmarks/run.py io              # reading + decoding, convert
    python benchmarks/run.py score           # scorer: ms per stage, paper-literal vs exact vs fast
    python benchmarks/run.py descriptors     # descriptor extraction and matching
    python benchmarks/run.py search          # localization against a 100,000-frame map (search_bench.py)
    python benchmarks/run.py map             # memlog map end to end: all scores vs staged vs shortlists, workers
    python benchmarks/run.py threads         # fp32 ResMem per crop: 1 vs 2 threads vs two 1-thread processes

Each case runs in a fresh subprocess so its peak RSS (ru_maxrss) is its own.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
SHARED = Path(os.environ.get("MEMLOG_SHARED_DATA", ROOT.parent / "shared" / "data"))
LOGS = ["euroc_micro_ros2.mcap", "euroc_micro_foxglove.mcap", "euroc_micro_ros1.bag", "euroc_micro_ros2_db3",
        "nordland_dev_summer.mcap"]


def _case(kind: str, *args: str, script: str = __file__, env: dict[str, str] | None = None) -> dict[str, Any]:
    """Run ``case_<kind>(*args)`` of ``script`` in a fresh subprocess; its JSON result."""
    out = subprocess.run([sys.executable, script, "--case", kind, *args], capture_output=True, text=True, env=env)
    if out.returncode != 0:
        raise SystemExit(f"benchmark case {kind} {args} failed:\n{out.stderr}")
    res: dict[str, Any] = json.loads(out.stdout.strip().splitlines()[-1])
    return res


def run_case(case: list[str], cases: dict[str, Any]) -> int:
    """The subprocess side of :func:`_case`: print ``case_<kind>(*args)`` as JSON."""
    kind, *rest = case
    print(json.dumps(cases[f"case_{kind}"](*rest)))
    return 0


def _peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _size(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file()) if path.is_dir() else path.stat().st_size


# -- cases (run in the subprocess) -------------------------------------------------------
def case_read(log: str) -> dict[str, Any]:
    from memlog.io import open_log

    base = _peak_mb()
    t0 = time.perf_counter()
    n = nbytes = 0
    with open_log(SHARED / log) as r:
        for f in r.frames():
            f.decode_bgr()
            n += 1
            nbytes += len(f.payload.data)
    dt = time.perf_counter() - t0
    return {"frames": n, "seconds": dt, "mb": _size(SHARED / log) / 1e6, "peak_mb": _peak_mb(), "base_mb": base}


def make_big_log(path: Path, mb: int) -> int:
    """A large MCAP: the EuRoC raw frames repeated (new log times) until ``mb`` megabytes."""
    from memlog.io import McapLogWriter, open_log

    with open_log(SHARED / "euroc_micro_ros2.mcap") as log:
        msgs = list(log.messages(["/cam0/image_raw"]))
    n = 0
    span = msgs[-1].log_time - msgs[0].log_time + 50_000_000
    with McapLogWriter(path, profile="ros2", compression="none") as w:
        while n * len(msgs[0].data) < mb * 1e6:
            rep, m = divmod(n, len(msgs))
            src = msgs[m]
            t = src.log_time + rep * span
            w.write(w.channel_for(src.channel), t, src.data, t, n)
            n += 1
    return n


def case_big_read(path: str) -> dict[str, Any]:
    from memlog.io import open_log

    base = _peak_mb()
    t0 = time.perf_counter()
    n = 0
    with open_log(path) as r:
        for f in r.frames():
            f.decode_gray()
            n += 1
    dt = time.perf_counter() - t0
    return {"frames": n, "seconds": dt, "mb": Path(path).stat().st_size / 1e6, "peak_mb": _peak_mb(), "base_mb": base}


def case_big_convert(path: str) -> dict[str, Any]:
    from memlog.steps.convert import convert

    base = _peak_mb()
    out = Path(path).with_suffix(".converted.mcap")
    t0 = time.perf_counter()
    res = convert(path, out)
    dt = time.perf_counter() - t0
    out.unlink()
    return {"messages": res.messages, "seconds": dt, "mb": res.bytes_in / 1e6, "peak_mb": _peak_mb(), "base_mb": base}


def bench_big(mb: int) -> None:
    rows = []
    with tempfile.TemporaryDirectory() as d:
        small = Path(d) / "small.mcap"
        big = Path(d) / "big.mcap"
        make_big_log(small, max(1, mb // 20))
        make_big_log(big, mb)
        for p in (small, big):
            r = _case("big_read", str(p))
            c = _case("big_convert", str(p))
            rows.append([f"{r['mb']:.0f} MB", r["frames"], f"{r['frames'] / r['seconds']:.0f}", f"{r['mb'] / r['seconds']:.0f}",
                         f"{r['peak_mb']:.0f}", f"{c['mb'] / c['seconds']:.0f}", f"{c['peak_mb']:.0f}"])
    print("\n### Memory stays flat with log size (EuRoC raw frames repeated; read+decode and convert)\n")
    print(table(rows, ["log size", "frames", "read+decode frames/s", "read MB/s", "read peak RSS MB",
                       "convert MB/s", "convert peak RSS MB"]))


def case_convert(log: str) -> dict[str, Any]:
    from memlog.steps.convert import convert

    base = _peak_mb()
    with tempfile.TemporaryDirectory() as d:
        t0 = time.perf_counter()
        res = convert(SHARED / log, Path(d) / "out.mcap")
        dt = time.perf_counter() - t0
    return {"messages": res.messages, "seconds": dt, "mb": res.bytes_in / 1e6, "peak_mb": _peak_mb(), "base_mb": base}


def case_score(log: str, mode: str, limit: str, thresholds: str = "") -> dict[str, Any]:
    from memlog.scoring.config import ScoreConfig
    from memlog.io import open_log
    from memlog.scoring.scorer import Scorer

    th = dict(zip(("mt", "st", "et"), map(float, thresholds.split(",")))) if thresholds else {}
    base_mode = {"all-scores": "exact", "fast-int8": "fast"}.get(mode, mode)
    cfg = ScoreConfig(mode=base_mode, all_scores=mode == "all-scores", fast_refine=mode != "fast-int8", **th)
    scorer = Scorer(cfg).load()
    n_max = int(limit)
    decisions = []
    ms = []
    stages: dict[str, float] = {}
    crops = surrogate = 0
    base = _peak_mb()
    t0 = time.perf_counter()
    with open_log(SHARED / log) as r:
        topic = r.camera_topics()[0]
        total = next(t.count for t in r.info().topics if t.topic == topic)
        stride = max(1, total // n_max)  # frames spread over the whole log
        frames = (f for i, f in zip(range(n_max), r.frames([topic], stride=stride)))
        for _, s in scorer.score_stream(frames, lambda fr: fr.decode_bgr()):
            assert not isinstance(s, Exception), s
            decisions.append([s.selected, s.rejected_by])
            ms.append([s.ms, s.ss, s.es])
            crops += s.crops_scored
            surrogate += s.crops_surrogate
            for k, v in s.timing_ms.items():
                stages[k] = stages.get(k, 0.0) + v
    dt = time.perf_counter() - t0
    n = len(decisions)
    return {"frames": n, "seconds": dt, "fps": n / dt, "stage_ms": {k: v / n for k, v in stages.items()},
            "crops_per_frame": crops / n, "surrogate_per_frame": surrogate / n, "decisions": decisions, "ms": ms,
            "peak_mb": _peak_mb(), "base_mb": base}


def case_map(log: str, variant: str, stride: str, fraction: str, workers: str) -> dict[str, Any]:
    """``memlog map`` end to end (descriptors off) on every ``stride``-th frame of ``log``."""
    from memlog.scoring.config import ScoreConfig
    from memlog.selection.config import SelectionConfig
    from memlog.steps.map import MapConfig, make_map

    score_cfg = {"all-scores": ScoreConfig(all_scores=True), "fast-all-scores": ScoreConfig(all_scores=True, mode="fast")}
    kept = variant.endswith("-score-kept")  # K1-score-kept: --candidates 1 --score-kept
    name = variant.removesuffix("-score-kept")
    k: int | str = int(name[1:]) if name.startswith("K") else "all"
    cfg = MapConfig(score=score_cfg.get(variant, ScoreConfig()), select=SelectionConfig(keep_fraction=float(fraction)),
                    descriptor=None, stride=int(stride), workers=int(workers), candidates=k, score_kept=kept)
    base = _peak_mb()
    with tempfile.TemporaryDirectory() as d:
        t0 = time.perf_counter()
        res = make_map(SHARED / log, Path(d) / "map.mcap", cfg)
        dt = time.perf_counter() - t0
    kept = {t: s.kept_indices.tolist() for t, s in res.selections.items()}
    return {"frames": res.frames_in, "kept": res.frames_kept, "seconds": dt, "crops_run": res.crops_run,
            "crops_full": res.crops_full, "kept_indices": kept, "peak_mb": _peak_mb(), "base_mb": base}


MAP_VARIANTS = ("all-scores", "staged", "staged-2", "K1", "K1-score-kept", "K2", "K4", "fast-all-scores")


def bench_map(log: str, stride: int, fraction: float, variants: Sequence[str] = MAP_VARIANTS) -> None:
    """All scores vs the staged exact selection vs shortlists, 1 and 2 worker processes (the first
    variant is the reference of the speed-up and of "same map")."""
    rows = []
    ref = None
    for v in variants:
        variant, workers = (v[:-2], 2) if v.endswith("-2") else (v, 1)
        if variant.startswith("fast") and not _fast_ready():
            continue
        r = _case("map", log, variant, str(stride), str(fraction), str(workers))
        if ref is None:
            ref = r
        same = "yes" if r["kept_indices"] == ref["kept_indices"] else "no"
        rows.append([variant + ("" if workers == 1 else f", {workers} processes"), r["frames"], r["kept"],
                     f"{r['frames'] / r['seconds']:.3f}", f"{ref['seconds'] / r['seconds']:.1f}x",
                     f"{(r['crops_run'] or 0) / r['frames']:.1f}", same, f"{r['peak_mb']:.0f}"])
    print(f"\n### memlog map on {log} (every {stride}th frame, --keep-fraction {fraction:g})\n")
    print(table(rows, ["scoring", "frames", "kept", "frames/s", "vs all scores", "ResMem crops / frame",
                       "same map as all scores", "peak RSS MB"]))


# -- tables ------------------------------------------------------------------------------
def table(rows: list[list[Any]], header: list[str]) -> str:
    cells = [[str(c) for c in r] for r in [header, *rows]]
    w = [max(len(r[i]) for r in cells) for i in range(len(header))]
    line = lambda r: "| " + " | ".join(c.ljust(x) for c, x in zip(r, w)) + " |"  # noqa: E731
    return "\n".join([line(cells[0]), "|" + "|".join("-" * (x + 2) for x in w) + "|", *(line(r) for r in cells[1:])])


def bench_io() -> None:
    rows = []
    for log in LOGS:
        r = _case("read", log)
        c = _case("convert", log)
        rows.append([log, r["frames"], f"{r['mb']:.1f}", f"{r['frames'] / r['seconds']:.0f}",
                     f"{r['mb'] / r['seconds']:.0f}", f"{r['peak_mb']:.0f}",
                     f"{c['mb'] / c['seconds']:.0f}", f"{c['messages'] / c['seconds']:.0f}", f"{c['peak_mb']:.0f}"])
    print("\n### Log I/O (read + decode every camera frame; convert = copy every record to indexed MCAP)\n")
    print(table(rows, ["log", "frames", "MB", "read+decode frames/s", "read+decode MB/s", "peak RSS MB",
                       "convert MB/s", "convert msgs/s", "convert peak RSS MB"]))


def _fast_ready() -> bool:
    from memlog.errors import ModelError
    from memlog.models.quantize import resmem_int8_path

    try:
        resmem_int8_path()
        return True
    except (ModelError, ImportError):
        print("(fast mode skipped: run `memlog models prepare resmem-int8` first)")
        return False


def _agree(a: dict[str, Any], b: dict[str, Any]) -> tuple[int, int]:
    same = sum(x[0] == y[0] for x, y in zip(a["decisions"], b["decisions"]))
    return same, len(a["decisions"])


def bench_score(n: int) -> None:
    """Paper-literal, exact, all-scores and fast mode on the same frames, in one run, at two
    threshold settings: the paper's (these small frames all fail ET, so no frame reaches the
    CNN), and a stress setting where every frame reaches the memorability stage and MT is the
    median MS of those frames (half the frames lie near the threshold)."""
    fast = _fast_ready()
    rows = []
    agree_rows = []
    for log in ["euroc_micro_ros2_db3", "nordland_dev_summer.mcap"]:
        paper = _case("score", log, "paper", str(n))
        ms = sorted(float(v[0]) for v in paper["ms"])
        mt = round(ms[len(ms) // 2], 4)
        settings = (("paper 0.5/0.6/0.4", ""), ("MT 0.5, ST=ET=0 (every frame reaches the CNN)", "0.5,0,0"),
                    (f"stress MT={mt}, ST=ET=0", f"{mt},0,0"))
        for setting, th in settings:
            modes = ["exact", "all-scores"] + (["fast", "fast-int8"] if fast else [])
            # the paper-literal pipeline computes every score whatever the thresholds: decide again
            th_mt = float(th.split(",")[0]) if th else 0.0
            res = {"paper": paper if not th else
                   {**paper, "decisions": [[v[0] >= th_mt, None] for v in paper["ms"]]}}
            res.update({m: _case("score", log, m, str(n), th) for m in modes})
            p = res["paper"]
            for m, r in res.items():
                st = r["stage_ms"]
                rows.append([log, setting, "paper-literal" if m == "paper" else m, r["frames"],
                             *(f"{st.get(k, 0):.1f}" for k in ("decode", "resize", "staticity", "entropy", "memorability")),
                             f"{r['crops_per_frame']:.1f}", f"{r['surrogate_per_frame']:.1f}", f"{r['fps']:.3f}",
                             f"{r['fps'] / p['fps']:.1f}x", f"{r['peak_mb']:.0f}"])
            for m in [m for m in ("exact", "fast", "fast-int8") if m in res]:
                same, tot = _agree(p, res[m])
                row = [log, setting, m, f"{same}/{tot} ({100.0 * same / tot:.1f} %)"]
                if m.startswith("fast"):
                    s2, t2 = _agree(res["exact"], res[m])
                    row.append(f"{s2}/{t2} ({100.0 * s2 / t2:.1f} %)")
                else:
                    row.append("-")
                agree_rows.append(row + [sum(a[0] for a in res[m]["decisions"]), sum(a[0] for a in p["decisions"])])
    print(f"\n### Scorer ({n} frames per log, every mode measured in one run; ms per frame per stage)\n")
    print(table(rows, ["log", "thresholds", "mode", "frames", "decode", "resize", "staticity", "entropy",
                       "memorability", "fp32 crops/frame", "int8 crops/frame", "frames/s", "vs paper-literal",
                       "peak RSS MB"]))
    print("\nDecision agreement (selected yes/no):\n")
    print(table(agree_rows, ["log", "thresholds", "mode", "same as paper-literal", "same as exact", "selected",
                             "selected (paper-literal)"]))


def case_resmem(threads: str, crops: str) -> dict[str, Any]:
    """Seconds per crop of the fp32 ResMem session with ``threads`` threads, one crop per call."""
    import numpy as np

    from memlog.models.resmem import resmem_onnx_path, run_crops
    from memlog.models.runtime import make_session

    s = make_session(resmem_onnx_path(), threads=int(threads), device="cpu")
    x = np.random.default_rng(0).random((1, 3, 227, 227), dtype=np.float32)
    run_crops(s, x)  # warm-up
    t0 = time.perf_counter()
    for _ in range(int(crops)):
        run_crops(s, x)
    return {"s_per_crop": (time.perf_counter() - t0) / int(crops), "peak_mb": _peak_mb()}


def bench_threads(crops: int = 50) -> None:
    """Threads against processes per core: one session with 1 and with 2 threads, then two
    1-thread sessions in two processes at once."""
    one = _case("resmem", "1", str(crops))
    two = _case("resmem", "2", str(crops))
    procs = [subprocess.Popen([sys.executable, __file__, "--case", "resmem", "1", str(crops)], stdout=subprocess.PIPE,
                              text=True) for _ in range(2)]
    par = [json.loads(p.communicate()[0].strip().splitlines()[-1])["s_per_crop"] for p in procs]
    together = 1.0 / sum(1.0 / v for v in par)
    rows = [["1 process, 1 thread", f"{one['s_per_crop']:.3f}", "1.00x"],
            ["1 process, 2 threads", f"{two['s_per_crop']:.3f}", f"{one['s_per_crop'] / two['s_per_crop']:.2f}x"],
            ["2 processes, 1 thread each (together)", f"{together:.3f} ({par[0]:.3f}, {par[1]:.3f} each)",
             f"{one['s_per_crop'] / together:.2f}x"]]
    print(f"\n### fp32 ResMem, one 227x227 crop per call ({crops} calls)\n")
    print(table(rows, ["layout", "s per crop", "vs 1 thread"]))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("what", nargs="*", default=["io", "score", "descriptors"])
    ap.add_argument("--frames", type=int, default=12, help="frames per log for the scorer table")
    ap.add_argument("--big-mb", type=int, default=1000, help="size of the synthetic large log for the memory table")
    ap.add_argument("--map-stride", type=int, default=4, help="every n-th Nordland frame for the map table")
    ap.add_argument("--map-variants", nargs="+", choices=MAP_VARIANTS, default=list(MAP_VARIANTS),
                    help="map table: which runs (the first is the reference)")
    ap.add_argument("--case", nargs="+", help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.case:
        return run_case(a.case, globals())
    if "io" in a.what:
        bench_io()
        bench_big(a.big_mb)
    if "score" in a.what:
        bench_score(a.frames)
    if "descriptors" in a.what:
        bench_descriptors()
    if "map" in a.what:  # not in the default set: about an hour on two cores
        bench_map("nordland_dev_summer.mcap", a.map_stride, 0.1, a.map_variants)
    if "threads" in a.what:
        bench_threads()
    if "search" in a.what:  # not in the default set: it builds a ~1.1 GB map in /tmp once
        subprocess.run([sys.executable, str(Path(__file__).with_name("search_bench.py"))], check=True)
    return 0


def bench_descriptors() -> None:
    script = Path(__file__).with_name("descriptor_recall.py")
    if script.exists():
        subprocess.run([sys.executable, str(script)], check=True)


if __name__ == "__main__":
    sys.exit(main())

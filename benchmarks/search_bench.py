#!/usr/bin/env python3
"""Localization against a big map: load time, ms per query (exact / approximate), recall, peak RSS.

The map is synthetic but made of real pixels: a drive of ``--frames`` frames (default 100,000)
along the 800 Nordland summer places (``nordland_dev_summer.mcap``), each frame a blend of the
two nearest places plus pixel noise, described with memlog's 2048-d thumbnail descriptor and
written in memlog's Parquet format (float32, and a float16 copy). It is generated once into
``--dir`` (default ``/tmp/memlog-search-bench``; ~800 MB per 100,000 frames) and reused. The
queries are the 800 Nordland winter frames.

Every case runs in a fresh subprocess, so its peak RSS (``ru_maxrss``) is its own. The machine
is shared: run with ``--repeat 3`` to see the spread.

    python benchmarks/search_bench.py                 # the table (generates the map once)
    python benchmarks/search_bench.py --frames 20000  # a smaller map
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from run import _case as _run_case, _peak_mb, run_case, table

ROOT = Path(__file__).resolve().parent.parent
# benchmark this tree's memlog, or the checkout named by --code (e.g. main, for the "before" rows)
sys.path.insert(0, os.environ.get("MEMLOG_BENCH_CODE", str(ROOT)))
SHARED = Path(os.environ.get("MEMLOG_SHARED_DATA", ROOT.parent / "shared" / "data"))
SUMMER = "nordland_dev_summer.mcap"
WINTER = "nordland_dev_winter.mcap"
GENERATOR = "1"  # bump when the synthetic map changes


def _grey_frames(log: str) -> np.ndarray:
    from memlog.io import open_log

    with open_log(SHARED / log) as r:
        return np.stack([f.decode_gray() for f in r.frames()]).astype(np.float32)


def make_map(path: Path, n: int, dtype: str, seed: int = 0) -> None:
    """Write the synthetic map of ``n`` frames to ``path`` (see the module doc)."""
    from memlog.descriptors.registry import make_describer
    from memlog.descriptors.table import DescriptorTable
    from memlog.outputs.descriptor_table import write_descriptors

    f32 = map_path(path.parent, n, "float32")
    if dtype != "float32" and f32.exists():  # the same map, stored as float16
        from memlog.outputs.descriptor_table import read_descriptors

        write_descriptors(path, read_descriptors(f32), dtype=dtype)
        return
    src = _grey_frames(SUMMER)
    d = make_describer("thumbnail")
    rng = np.random.default_rng(seed)
    pos = np.linspace(0.0, len(src) - 1, n)
    desc = np.empty((n, d.dim), np.float32)
    for s in range(0, n, 4096):
        p = pos[s : s + 4096]
        i0 = np.floor(p).astype(int)
        i1 = np.minimum(i0 + 1, len(src) - 1)
        w = (p - i0)[:, None, None].astype(np.float32)
        imgs = (1 - w) * src[i0] + w * src[i1] + rng.normal(0.0, 4.0, size=(len(p),) + src.shape[1:])
        desc[s : s + len(p)] = d.describe(list(np.clip(imgs, 0, 255).astype(np.float32)))
    t = (np.arange(n, dtype=np.int64) * 100_000_000) + 1_600_000_000_000_000_000
    table = DescriptorTable(topic=["/camera/image_raw/compressed"] * n, frame_index=np.arange(n), log_time_ns=t,
                            stamp_ns=t, descriptors=desc, meta=d.meta(),
                            ms=rng.random(n), ss=rng.random(n), es=rng.random(n),
                            extra={"synthetic": f"search_bench v{GENERATOR}, {n} frames, seed {seed}"})
    kw = {} if dtype == "float32" else {"dtype": dtype}
    write_descriptors(path, table, **kw)


def map_path(base: Path, n: int, dtype: str) -> Path:
    return base / f"map-{n}-g{GENERATOR}-{dtype}.parquet"


# -- cases (each in its own subprocess) ---------------------------------------------------------
def case_make(path: str, n: str, dtype: str) -> dict[str, Any]:
    t0 = time.perf_counter()
    make_map(Path(path), int(n), dtype)
    return {"seconds": time.perf_counter() - t0}


def case_load(path: str) -> dict[str, Any]:
    from memlog.outputs.descriptor_table import read_descriptors

    base = _peak_mb()
    t0, c0 = time.perf_counter(), time.process_time()
    t = read_descriptors(path)
    dt, cpu = time.perf_counter() - t0, time.process_time() - c0
    return {"seconds": dt, "cpu_seconds": cpu, "peak_mb": _peak_mb(), "base_mb": base,
            "data_mb": t.descriptors.nbytes / 2**20}


def _winter_queries() -> np.ndarray:
    from memlog.descriptors.registry import make_describer
    from memlog.io import open_log

    d = make_describer("thumbnail")
    with open_log(SHARED / WINTER) as r:
        return d.describe([f.decode_bgr() for f in r.frames()])


def _recall(found: np.ndarray, exact: np.ndarray) -> tuple[float, float]:
    """recall@1 (same best frame) and recall@10 (share of the exact top 10 found) against exact search."""
    r10 = np.mean([len(set(a[:10]) & set(b[:10])) / 10 for a, b in zip(found, exact)])
    return float(np.mean(found[:, 0] == exact[:, 0])), float(r10)


def _place_recall(best: np.ndarray, n: int, n_places: int = 800) -> float:
    """R@1 against the Nordland truth: map frame t shows place t * 799 / (n - 1); correct within one place."""
    pos = best * (n_places - 1) / (n - 1)
    return float(np.mean(np.abs(pos - np.arange(len(best))) <= 1.0))


def _timed(fn: Any) -> tuple[Any, float, float]:
    t0, c0 = time.perf_counter(), time.process_time()
    out = fn()
    return out, time.perf_counter() - t0, time.process_time() - c0


def case_search(path: str, path16: str) -> dict[str, Any]:
    """Exact (batched, one at a time) and IVF search of the 800 winter queries; float16 map agreement."""
    from memlog.descriptors.approx import IVFIndex, default_nprobe
    from memlog.descriptors.search import Database, match, time_per_query
    from memlog.outputs.descriptor_table import read_descriptors

    q = _winter_queries()
    ref = read_descriptors(path)
    n = len(ref)
    db = Database.of(ref.descriptors)
    out: dict[str, Any] = {"n_queries": len(q), "n_map": n}
    (exact, _s), wall, cpu = _timed(lambda: match(q, db, k=10))
    out["exact"] = {"ms": 1e3 * wall / len(q), "cpu_ms": 1e3 * cpu / len(q), "place_r1": _place_recall(exact[:, 0], n)}
    single = time_per_query(q, db, repeats=1, k=10, max_queries=10, batched=False)
    out["exact_single_ms"] = 1e3 * single.seconds_per_query
    index, wall, cpu = _timed(lambda: IVFIndex(db))
    out["ivf_build"] = {"seconds": wall, "cpu_seconds": cpu, "nlist": index.nlist}
    out["ivf"] = []
    base = default_nprobe(index.nlist)
    for nprobe in (max(1, base // 2), base, 2 * base):
        (found, _s), wall, cpu = _timed(lambda: index.search(q, 10, nprobe))
        r1, r10 = _recall(found, exact)
        out["ivf"].append({"nprobe": nprobe, "ms": 1e3 * wall / len(q), "cpu_ms": 1e3 * cpu / len(q),
                           "recall1": r1, "recall10": r10, "place_r1": _place_recall(found[:, 0], n)})
        single_ivf, wall, _cpu = _timed(lambda: [index.search(q[i], 10, nprobe) for i in range(10)])
        out["ivf"][-1]["single_ms"] = 1e3 * wall / 10
    d32 = ref.descriptors
    d16 = read_descriptors(path16).descriptors
    (found, _s), wall, cpu = _timed(lambda: match(q, d16, k=10))
    r1, r10 = _recall(found, exact)
    out["float16"] = {"recall1": r1, "recall10": r10, "place_r1": _place_recall(found[:, 0], n),
                      "max_abs_error": float(np.max(np.abs(d16 - d32)))}
    return out


def case_localize(path: str, *flags: str) -> dict[str, Any]:
    """``memlog localize MAP nordland_dev_winter.mcap`` end to end through the step function."""
    import tempfile

    from memlog.steps.localize import LocalizeConfig, localize

    base = _peak_mb()
    kw: dict[str, Any] = {}
    for f in flags:
        key, value = f.split("=", 1)
        if key == "search":
            from memlog.descriptors.approx import SearchConfig

            kw[key] = SearchConfig(value)
        else:
            kw[key] = value == "1"
    with tempfile.TemporaryDirectory() as d:
        t0, c0 = time.perf_counter(), time.process_time()
        res = localize(path, SHARED / WINTER, Path(d) / "m.parquet", LocalizeConfig(k=10, **kw))
        dt, cpu = time.perf_counter() - t0, time.process_time() - c0
    return {"seconds": dt, "cpu_seconds": cpu, "peak_mb": _peak_mb(), "base_mb": base, "result": res.to_dict()}


# -- the tables ---------------------------------------------------------------------------------
def _case(kind: str, *args: str, code: Path | None = None) -> dict[str, Any]:
    return _run_case(kind, *args, script=__file__, env=dict(os.environ, MEMLOG_BENCH_CODE=str(code)) if code else None)


def _spread(values: list[float], fmt: str = "{:.1f}") -> str:
    """Median, and the range when there are several runs (the machine is shared: that is the noise)."""
    med = float(np.median(values))
    if len(values) == 1:
        return fmt.format(med)
    return f"{fmt.format(med)} ({fmt.format(min(values))}–{fmt.format(max(values))})"


def bench(a: argparse.Namespace) -> None:
    a.dir.mkdir(parents=True, exist_ok=True)
    paths = {dt: map_path(a.dir, a.frames, dt) for dt in ("float32", "float16")}
    for dt, p in paths.items():
        if not p.exists():
            print(f"generating {p} ...", file=sys.stderr)
            _case("make", str(p), str(a.frames), dt)
    data_mb = a.frames * 2048 * 4 / 2**20
    who = f"memlog of {a.code}" if a.code else "this tree"
    print(f"\n### Localization against a {a.frames:,}-frame map ({who}; 2048-d thumbnails, {data_mb:.0f} MiB of "
          f"float32 descriptors; 800 Nordland winter queries; {os.cpu_count()} cores, shared machine: median "
          f"(min–max) of {a.repeat} run(s))\n")
    rows = []
    for dt, p in paths.items():
        runs = [_case("load", str(p), code=a.code) for _ in range(a.repeat)]
        rows.append([f"read_descriptors, {dt} file ({p.stat().st_size / 1e6:.0f} MB)",
                     _spread([r["seconds"] for r in runs]), _spread([r["cpu_seconds"] for r in runs]),
                     _spread([r["peak_mb"] for r in runs], "{:.0f}"),
                     f"{np.median([r['peak_mb'] for r in runs]) / data_mb:.2f}"])
    print(table(rows, ["load", "seconds", "CPU seconds", "peak RSS MiB", "peak / data"]))
    print()
    rows = []
    for method in ([""] if a.code else ["exact", "ivf"]):
        flags = [f"search={method}"] if method else []
        runs = [_case("localize", str(paths["float32"]), *flags, code=a.code) for _ in range(a.repeat)]
        res = [r["result"] for r in runs]
        rows.append([f"localize {('--search ' + method) if method else '(before)'}",
                     _spread([r["seconds"] for r in runs]),
                     _spread([1e3 * x["match_seconds_per_query"]["seconds_per_query"] for x in res], "{:.2f}"),
                     _spread([x.get("search", {}).get("build_seconds", 0.0) for x in res]),
                     _spread([r["peak_mb"] for r in runs], "{:.0f}"),
                     f"{np.median([r['peak_mb'] for r in runs]) / data_mb:.2f}"])
    print(table(rows, ["run (float32 map, k=10, end to end)", "total s", "ms/query (search)", "index build s",
                       "peak RSS MiB", "peak / data"]))
    if a.code:
        return
    print()
    runs = [_case("search", str(paths["float32"]), str(paths["float16"])) for _ in range(a.repeat)]
    rows = [["exact, 800 queries at once", _spread([r["exact"]["ms"] for r in runs], "{:.2f}"),
             _spread([r["exact"]["cpu_ms"] for r in runs], "{:.2f}"),
             _spread([r["exact_single_ms"] for r in runs], "{:.1f}"), "1", "1", f"{runs[0]['exact']['place_r1']:.3f}"]]
    for i, first in enumerate(runs[0]["ivf"]):
        rows.append([f"ivf nlist {runs[0]['ivf_build']['nlist']}, nprobe {first['nprobe']}",
                     _spread([r["ivf"][i]["ms"] for r in runs], "{:.2f}"),
                     _spread([r["ivf"][i]["cpu_ms"] for r in runs], "{:.2f}"),
                     _spread([r["ivf"][i]["single_ms"] for r in runs], "{:.1f}"),
                     f"{first['recall1']:.3f}", f"{first['recall10']:.3f}", f"{first['place_r1']:.3f}"])
    f16 = runs[0]["float16"]
    rows.append(["exact on the float16 map", "", "", "", f"{f16['recall1']:.3f}", f"{f16['recall10']:.3f}",
                 f"{f16['place_r1']:.3f}"])
    print(table(rows, ["search (k=10)", "ms/query, batched", "CPU ms/query", "ms, one query alone",
                       "recall@1 vs exact", "recall@10 vs exact", "place R@1"]))
    print(f"\nIVF build (train + add): {_spread([r['ivf_build']['seconds'] for r in runs])} s, CPU "
          f"{_spread([r['ivf_build']['cpu_seconds'] for r in runs])} s; float16 storage: largest descriptor error "
          f"{f16['max_abs_error']:.2e}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=100_000)
    ap.add_argument("--dir", type=Path, default=Path("/tmp/memlog-search-bench"))
    ap.add_argument("--repeat", type=int, default=1, help="runs of each timed case (the spread is the noise)")
    ap.add_argument("--code", type=Path, help="time the load and localize rows with the memlog of another "
                                              "checkout (e.g. ../main: the 'before' figures)")
    ap.add_argument("--case", nargs="+", help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.case:
        return run_case(a.case, globals())
    bench(a)
    return 0


if __name__ == "__main__":
    sys.exit(main())

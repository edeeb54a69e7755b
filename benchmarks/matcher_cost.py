#!/usr/bin/env python3
"""Cost of the drive matcher (``match_tables``, what ``memlog localize`` calls): peak memory on
sparse maps and time per query on big maps, with the default settings.

A synthetic reference drive of ``--drive-frames`` frames (a smooth random walk of unit
descriptors, ``--dim`` dimensions, 10 Hz) is kept at a fraction (every 1/fraction-th frame: a
map as sparse as ``memlog map --keep-fraction`` makes it), and a query drive of ``--queries``
frames runs along it with noise. Each setting runs in its own process, so its peak RSS
(``ru_maxrss``) is its own.

    python benchmarks/matcher_cost.py                       # the README's table
    python benchmarks/matcher_cost.py --fractions 0.01 --drive-frames 100000

With the re-rank (default rows: off and on), the map and the query carry synthetic patch
features as a map stores them (64 x 64 float16 per frame) and each query's 20 best places are
re-ranked (``memlog.matching.rerank_by_patches``).

Prints a Markdown table: map frames, their spacing, re-rank, ms per query, peak RSS (MB).
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


def _walk(n: int, dim: int, rng: np.random.Generator) -> np.ndarray:
    """A smooth random walk of unit vectors (consecutive frames alike, far frames unlike)."""
    out = np.empty((n, dim), np.float32)
    x = rng.normal(size=dim)
    for i in range(n):
        x = 0.95 * x + 0.3 * rng.normal(size=dim)
        out[i] = x
    out /= np.linalg.norm(out, axis=1, keepdims=True)
    return out


def _table(desc: np.ndarray, frames: np.ndarray, stamps_ns: np.ndarray, patches: np.ndarray | None = None,
           pca: object = None) -> object:
    from memlog.descriptors.base import DescriptorMeta
    from memlog.descriptors.table import DescriptorTable

    n = len(frames)
    return DescriptorTable(["/cam"] * n, frames, stamps_ns, stamps_ns, desc, DescriptorMeta("synthetic", "1", desc.shape[1]),
                           moving_index=frames.copy(), patches=patches, patch_pca=pca)  # type: ignore[arg-type]


def _patches(n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` frames' unit patch features as a map stores them: 64 patches x 64 dims, float16."""
    from memlog.descriptors.patches import GRID, PATCH_DIM

    x = rng.normal(size=(n, GRID * GRID, PATCH_DIM)).astype(np.float32)
    return (x / np.linalg.norm(x, axis=-1, keepdims=True)).astype(np.float16)


def one(drive_frames: int, fraction: float, queries: int, dim: int, rerank: bool) -> dict[str, float]:
    """Match ``queries`` query frames against the map of every 1/fraction-th of ``drive_frames``
    (with ``rerank``: the map and the query carry patch features, and the default re-rank runs)."""
    from memlog.descriptors.patches import PATCH_DIM, PatchPCA
    from memlog.matching import SequenceConfig, match_tables

    rng = np.random.default_rng(0)
    drive = _walk(drive_frames, dim, rng)
    step = max(1, round(1 / fraction))
    kept = np.arange(0, drive_frames, step)
    start = drive_frames // 3
    qf = np.arange(start, min(drive_frames, start + queries))
    noisy = drive[qf] + 0.5 * rng.normal(size=(len(qf), dim)).astype(np.float32) / np.sqrt(dim)
    noisy /= np.linalg.norm(noisy, axis=1, keepdims=True)
    rp = qp = pca = None
    if rerank:  # an identity PCA names the space both are in
        pca = PatchPCA(np.zeros(PATCH_DIM), np.eye(PATCH_DIM))
        rp = _patches(len(kept), rng)
        near = np.minimum(np.round(qf / step).astype(np.int64), len(kept) - 1)
        qp = rp[near].astype(np.float32) + 0.05 * rng.normal(size=(len(qf), *rp.shape[1:])).astype(np.float32)
        qp = (qp / np.linalg.norm(qp, axis=-1, keepdims=True)).astype(np.float16)
    ref = _table(drive[kept], kept, kept * 100_000_000, rp, pca)
    query = _table(noisy.astype(np.float32), np.arange(len(qf)), np.arange(len(qf)) * 100_000_000, qp, pca)
    t0 = time.perf_counter()
    res = match_tables(query, ref, SequenceConfig(rerank=rerank), k=5)  # type: ignore[arg-type]
    seconds = time.perf_counter() - t0
    right = np.abs(kept[np.maximum(res.indices[:, 0], 0)] - qf) <= step
    return {"map_frames": len(kept), "spacing": step, "ms_per_query": 1e3 * seconds / len(qf),
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, "r1": float(right.mean()),
            "length_used": res.info["length_used"]}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--drive-frames", type=int, nargs="+", default=[100_000, 10_000])
    ap.add_argument("--fractions", type=float, nargs="+", default=[1.0, 0.01, 0.0025])
    ap.add_argument("--queries", type=int, default=500)
    ap.add_argument("--dim", type=int, default=256)
    ap.add_argument("--rerank", choices=["on", "off", "both"], default="both",
                    help="the patch re-rank (default: both, one row each)")
    ap.add_argument("--one", nargs=3, type=float, help=argparse.SUPPRESS)  # a child run: frames fraction rerank
    a = ap.parse_args()
    if a.one:
        print(json.dumps(one(int(a.one[0]), a.one[1], a.queries, a.dim, bool(a.one[2]))))
        return 0
    print("| drive frames | keep fraction | map frames | spacing (frames) | window used | re-rank | ms / query | "
          "peak RSS (MB) |")
    print("|---|---|---|---|---|---|---|---|")
    modes = {"on": [1], "off": [0], "both": [0, 1]}[a.rerank]
    for n in a.drive_frames:
        for f in a.fractions:
            if n * f < 2:
                continue
            for rr in modes:
                out = subprocess.run([sys.executable, __file__, "--one", str(n), str(f), str(rr), "--queries",
                                      str(a.queries), "--dim", str(a.dim)], check=True, capture_output=True,
                                     text=True).stdout
                r = json.loads(out.strip().splitlines()[-1])
                print(f"| {n:,} | {f:g} | {r['map_frames']:,} | {r['spacing']} | ±{r['length_used']} | "
                      f"{'on' if rr else 'off'} | {r['ms_per_query']:.1f} | {r['peak_rss_mb']:.0f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

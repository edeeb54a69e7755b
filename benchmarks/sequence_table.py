#!/usr/bin/env python3
"""Sequence matching against single frames on drive variants of the shared Nordland slice.

    python benchmarks/sequence_table.py                       # every table (~10 min; timings provisional)
    python benchmarks/sequence_table.py --tables quality maps  # some of them
    python benchmarks/sequence_table.py --cache /tmp/memlog-seq-bench

Drives: the variants of :mod:`benchmarks.drives` (winter = query: base, fast, stops, half-rate,
double-rate, mixed; summer = reference: base, half-rate, double-rate), written once as MCAP logs
with synthetic odometry and described with memlog's own code (``describe_log``, the ``auto``
descriptor of 64x32 frames = the thumbnail, whitened by a PCA fitted on the reference drive's
frames as ``memlog map`` does). Logs and descriptors are cached under ``--cache``.

Maps: the full reference drive, every 2nd (half) and every 4th (quarter) frame kept. Protocol:
map-only (only the map's frames are searched; a query is correct when its best map frame is in
its truth list, recomputed by source place, +-1 place; queries whose true places were dropped
can only be wrong). R@1, and AUC-PR with each method's confidence (single frames: best
similarity; sequences: the margin).

Tables (``--tables``):

* ``quality``: R@1 / AUC per query variant: single frames, sequence offline, causal; full map, base
  reference;
* ``maps``: the same at full / half / quarter maps, and against references at other frame rates;
* ``coords``: frames vs time vs positions coordinates;
* ``sweep``: N (frames before/after) and K (candidates per frame) sweeps, and the confidence
  (margin vs score vs exclusion width);
* ``speed``: speed range: R@1 and ms per query;
* ``size``: ms per query against synthetic maps of 10^4 and 10^5 frames (the 800 real summer
  frames inside a drive of noisy copies of them), exact search and FAISS IVF, single vs
  sequence.

Timings are provisional: this machine is shared (run again on a quiet machine); R@1 and AUC are
deterministic.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
SHARED = Path(os.environ.get("MEMLOG_SHARED_DATA", ROOT.parent / "shared" / "data"))
QUERY_VARIANTS = ["base", "fast", "stops", "half-rate", "double-rate", "mixed"]
REF_VARIANTS = ["base", "half-rate", "double-rate"]
GENERATOR = "1"  # bump when the cached drives change

from benchmarks import drives  # noqa: E402


class Drive:
    """One described drive variant: whitened descriptors, frame indices, stamps, positions."""

    def __init__(self, z: Any, variant: drives.Variant) -> None:
        self.raw = z["raw"]
        self.frame_index = z["frame_index"]
        self.stamp_ns = z["stamp_ns"]
        self.xyz = z["xyz"]
        # the frame index with the drive's stops left out (memlog's moving_index); the frame
        # index itself for caches written before it
        self.moving: np.ndarray = z["moving"] if "moving" in z else self.frame_index
        self.variant = variant
        self.desc: np.ndarray = self.raw

    def __len__(self) -> int:
        return len(self.frame_index)

    def table(self) -> Any:
        """The drive as the descriptor table ``memlog localize`` matches (its current descriptors)."""
        return as_table(self.desc, self.frame_index, self.stamp_ns, self.moving, self.xyz)


def as_table(desc: np.ndarray, frame_index: np.ndarray, stamp_ns: np.ndarray, moving: np.ndarray | None = None,
             xyz: np.ndarray | None = None) -> Any:
    """A DescriptorTable of one camera topic: what the drive matcher (``match_tables``) takes."""
    from memlog.descriptors.base import DescriptorMeta
    from memlog.descriptors.table import DescriptorTable

    pos = {c: xyz[:, i] for i, c in enumerate("xyz")} if xyz is not None and xyz.shape[1] == 3 else {}
    return DescriptorTable(["/cam"] * len(frame_index), frame_index, stamp_ns, stamp_ns, desc,
                           DescriptorMeta("thumbnail", "1", desc.shape[1]), positions=pos, moving_index=moving)


def _describe(log: Path, cache: Path) -> dict[str, np.ndarray]:
    path = cache / (log.stem + ".npz")
    if path.is_file():
        return dict(np.load(path))
    from memlog.descriptors.extract import describe_log
    from memlog.descriptors.registry import make_describer

    t, _report = describe_log(log, make_describer("thumbnail"))
    xyz = np.stack([t.positions[c] for c in ("x", "y", "z")], axis=1) if "x" in t.positions else np.zeros((len(t), 0))
    out = {"raw": t.descriptors, "frame_index": t.frame_index, "stamp_ns": t.stamp_ns, "xyz": xyz}
    if t.moving_index is not None:
        out["moving"] = t.moving_index
    np.savez(path, **out)
    return out


def load(cache: Path) -> tuple[dict[str, Drive], dict[str, Drive]]:
    """(query drives, reference drives) by variant name; the logs are written once."""
    cache.mkdir(parents=True, exist_ok=True)
    queries, refs = {}, {}
    for drive, names, out in (("winter", QUERY_VARIANTS, queries), ("summer", REF_VARIANTS, refs)):
        for n, name in enumerate(names):
            v = drives.variant(name)
            log = cache / f"g{GENERATOR}-nordland_{drive}_{name}.mcap"
            if not log.is_file():
                drives.write_variant(SHARED / drives.DRIVES[drive], v, log, positions=True,
                                     seed=(1 if drive == "winter" else 2) * 100 + n)
            out[name] = Drive(_describe(log, cache), v)
    return queries, refs


def whiten(ref: Drive, queries: list[Drive]) -> None:
    """Fit the whitening on the reference drive (as ``memlog map``), apply to it and the queries."""
    from memlog.descriptors.whitening import fit_whitening

    w = fit_whitening(ref.raw)
    ref.desc = w.apply(ref.raw)
    for q in queries:
        q.desc = w.apply(q.raw)


def truth_sets(q: Drive, r: Drive) -> list[set[int]]:
    t = drives.truth(q.variant, r.variant)
    return [set(m) for m in t["matches"]]


def run(q: Drive, r: Drive, mask: np.ndarray | None, cfg: Any, coordinate: str = "frames", k: int = 1,
        index: Any = None) -> tuple[dict[str, float], Any, float]:
    """(R@1, AUC, ...), the SequenceMatch, seconds per query: matched by the drive matcher
    ``memlog localize`` calls (``match_tables``), in ``coordinate``."""
    from dataclasses import replace

    from memlog.matching import match_tables
    from memlog.evaluation.metrics import pr_curve

    t0 = time.perf_counter()
    res = match_tables(q.table(), r.table(), replace(cfg, coordinate=coordinate), k=k, ref_mask=mask, index=index)
    dt = (time.perf_counter() - t0) / len(q)
    truth = truth_sets(q, r)
    best = res.indices[:, 0]
    correct = np.array([b >= 0 and int(b) in s for b, s in zip(best, truth)])
    curve = pr_curve(res.confidence, correct, np.array([bool(s) for s in truth]))
    score_curve = pr_curve(np.where(best >= 0, res.scores[:, 0], -np.inf), correct, np.array([bool(s) for s in truth]))
    return {"R@1": float(correct.mean()), "AUC": curve.auc, "AUC-score": score_curve.auc}, res, dt


def every(n: int, step: int) -> np.ndarray:
    m = np.zeros(n, bool)
    m[::step] = True
    return m


def table(rows: list[list[Any]], header: list[str]) -> str:
    cells = [[str(c) for c in r] for r in [header, *rows]]
    w = [max(len(r[i]) for r in cells) for i in range(len(header))]
    line = lambda r: "| " + " | ".join(c.ljust(x) for c, x in zip(r, w)) + " |"  # noqa: E731
    return "\n".join([line(cells[0]), "|" + "|".join("-" * (x + 2) for x in w) + "|", *(line(r) for r in cells[1:])])


def f3(m: dict[str, float]) -> str:
    return f"{m['R@1']:.3f} / {m['AUC']:.3f}"


def methods() -> dict[str, Any]:
    from memlog.matching import SequenceConfig

    base = SequenceConfig()
    return {"single": SequenceConfig(length=0), "offline": base, "causal": replace(base, causal=True)}


def tab_quality(qs: dict[str, Drive], refs: dict[str, Drive]) -> None:
    r = refs["base"]
    ms = methods()
    rows = []
    for name, q in qs.items():
        rows.append([name, len(q), *(f3(run(q, r, None, cfg)[0]) for cfg in ms.values())])
    print("\n### R@1 / AUC, full map (800 summer frames), frames coordinate, N = 10, K = 3, speeds 0..3\n")
    print(table(rows, ["query", "frames", *ms]))


def tab_maps(qs: dict[str, Drive], refs: dict[str, Drive]) -> None:
    ms = {k: v for k, v in methods().items() if k in ("single", "offline", "causal")}
    rows = []
    for rname, r in refs.items():
        whiten(r, list(qs.values()))
        for frac, step in (("full", 1), ("half", 2), ("quarter", 4)):
            mask = None if step == 1 else every(len(r), step)
            for qname in ("base", "stops", "fast", "mixed"):
                q = qs[qname]
                rows.append([rname, frac, qname, *(f3(run(q, r, mask, cfg)[0]) for cfg in ms.values())])
    whiten(refs["base"], list(qs.values()))
    print("\n### R@1 / AUC by map: reference variant, map fraction (every 2nd / 4th reference frame kept)\n")
    print(table(rows, ["reference", "map", "query", *ms]))


def tab_coords(qs: dict[str, Drive], refs: dict[str, Drive]) -> None:
    from memlog.matching import SequenceConfig

    rows = []
    for rname in ("base", "half-rate"):
        r = refs[rname]
        whiten(r, list(qs.values()))
        for frac, step in (("full", 1), ("quarter", 4)):
            mask = None if step == 1 else every(len(r), step)
            for qname in ("base", "mixed", "double-rate"):
                q = qs[qname]
                cells = []
                for kind in ("frames", "time", "positions"):
                    cells.append(f3(run(q, r, mask, SequenceConfig(), coordinate=kind)[0]))
                rows.append([rname, frac, qname, *cells])
    whiten(refs["base"], list(qs.values()))
    print("\n### R@1 / AUC by coordinate (offline, constant speed; speeds 0..3, positions 0.8..1.25)\n")
    print(table(rows, ["reference", "map", "query", "frames", "time", "positions"]))


def tab_sweep(qs: dict[str, Drive], refs: dict[str, Drive]) -> None:
    from memlog.matching import SequenceConfig

    r = refs["base"]
    cases = [("base", "full", None), ("mixed", "full", None), ("mixed", "quarter", every(len(r), 4))]
    rows = []
    for n in (0, 2, 5, 10, 15, 20):
        cells = []
        for qn, _f, mask in cases:
            for causal in (False, True):
                if n == 0 and causal:
                    cells.append("–")
                    continue
                cells.append(f3(run(qs[qn], r, mask, SequenceConfig(length=n, causal=causal))[0]))
        rows.append([n, *cells])
    hdr = [f"{qn} {f} {'causal' if c else 'offline'}" for qn, f, _m in cases for c in (False, True)]
    print("\n### N sweep (frames before/after): R@1 / AUC\n")
    print(table(rows, ["N", *hdr]))
    rows = []
    for kk in (1, 2, 3, 5, 10, 20, 50):
        cells = []
        for qn, _f, mask in cases:
            m, _res, dt = run(qs[qn], r, mask, SequenceConfig(candidates=kk))
            cells += [f3(m), f"{dt * 1e3:.2f}"]
        rows.append([kk, *cells])
    hdr = [x for qn, f, _m in cases for x in (f"{qn} {f}", "ms/q")]
    print("\n### K sweep (candidates per query frame), offline: R@1 / AUC, ms per query (provisional)\n")
    print(table(rows, ["K", *hdr]))
    rows = []
    for excl in (1, 2, 5, 10):
        cells = []
        for qn, _f, mask in cases:
            m, _res, _dt = run(qs[qn], r, mask, SequenceConfig(exclude=float(excl)))
            cells.append(f"{m['AUC']:.3f} / {m['AUC-score']:.3f}")
        rows.append([excl, *cells])
    print("\n### Confidence: AUC with the margin / with the score as confidence, by exclusion half-width "
          "(reference frames)\n")
    print(table(rows, ["exclude", *[f"{qn} {f}" for qn, f, _m in cases]]))


def tab_speed(qs: dict[str, Drive], refs: dict[str, Drive]) -> None:
    from memlog.matching import SequenceConfig

    r = refs["base"]
    rows = []
    for sp in ((1.0, 1.0), (0.5, 1.5), (0.0, 2.0), (0.0, 3.0), (0.0, 5.0)):
        cells = []
        for qn in ("base", "stops", "fast", "mixed", "half-rate", "double-rate"):
            m, _res, dt = run(qs[qn], r, None, SequenceConfig(speeds=sp))
            cells.append(f"{m['R@1']:.3f} ({dt * 1e3:.1f})")
        rows.append([f"{sp[0]:g}..{sp[1]:g}", *cells])
    print("\n### Speed range: R@1 (ms per query, provisional), full map, offline\n")
    print(table(rows, ["speeds", "base", "stops", "fast", "mixed", "half-rate", "double-rate"]))


def synthetic_map(r: Drive, n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(descriptors [n, d], frame coordinate [n], rows of the real drive inside): the 800 real
    frames at the middle of a drive of ``n`` frames; the rest are other "drives": each a noisy
    copy of the reference (descriptor noise of the same norm as the descriptor), so they are
    drive-like but far from every real frame."""
    rng = np.random.default_rng(seed)
    d = r.desc.shape[1]
    m = len(r)
    out = np.empty((n, d), np.float32)
    start = (n - m) // 2
    fill = np.r_[np.arange(start), np.arange(start + m, n)]
    for a in range(0, len(fill), 8192):
        rows = fill[a : a + 8192]
        x = r.desc[rows % m] + rng.normal(0, 1 / np.sqrt(d), (len(rows), d)).astype(np.float32) * 1.5
        out[rows] = x / np.linalg.norm(x, axis=1, keepdims=True)
    out[start : start + m] = r.desc
    return out, np.arange(n, dtype=np.float64), np.arange(start, start + m)


def tab_size(qs: dict[str, Drive], refs: dict[str, Drive], sizes: list[int]) -> None:
    from memlog.descriptors.approx import IVFIndex
    from memlog.descriptors.search import Database
    from memlog.matching import SequenceConfig, match_tables

    r = refs["base"]
    rows = []
    for n in sizes:
        desc, rc, real = synthetic_map(r, n)
        db = Database.of(desc)
        frames = rc.astype(np.int64)
        map_table = as_table(desc, frames, frames * 100_000_000, frames)
        index = None
        build = 0.0
        for method in ("exact", "ivf"):
            if method == "ivf":
                t0 = time.perf_counter()
                index = IVFIndex(db)
                build = time.perf_counter() - t0
            for qn in ("base", "mixed"):
                q = qs[qn]
                truth = truth_sets(q, r)
                for name, cfg in (("single", SequenceConfig(length=0)), ("sequence", SequenceConfig())):
                    t0 = time.perf_counter()
                    res = match_tables(q.table(), map_table, cfg, k=1, index=index if method == "ivf" else None)
                    dt = (time.perf_counter() - t0) / len(q) * 1e3
                    best = res.indices[:, 0] - real[0]
                    r1 = np.mean([int(b) in s for b, s in zip(best, truth)])
                    rows.append([n, method, qn, name, f"{r1:.3f}", f"{dt:.2f}",
                                 f"{build:.1f}" if method == "ivf" else "–"])
    print("\n### ms per query against big synthetic maps (all query frames matched in one call; provisional)\n")
    print(table(rows, ["map frames", "search", "query", "matching", "R@1", "ms/query", "index build s"]))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cache", type=Path, default=Path("/tmp/memlog-seq-bench"))
    ap.add_argument("--tables", nargs="+", default=["quality", "maps", "coords", "sweep", "speed", "size"])
    ap.add_argument("--sizes", type=int, nargs="+", default=[10_000, 100_000])
    a = ap.parse_args()
    qs, refs = load(a.cache)
    whiten(refs["base"], list(qs.values()))
    tabs: dict[str, Callable[[], None]] = {
        "quality": lambda: tab_quality(qs, refs), "maps": lambda: tab_maps(qs, refs),
        "coords": lambda: tab_coords(qs, refs), "sweep": lambda: tab_sweep(qs, refs),
        "speed": lambda: tab_speed(qs, refs), "size": lambda: tab_size(qs, refs, a.sizes),
    }
    for t in a.tables:
        tabs[t]()
    return 0


if __name__ == "__main__":
    sys.exit(main())

#!/usr/bin/env python3
"""Descriptor x whitening x selection on the shared Nordland slice, with the noise level.

    python benchmarks/desc_table.py [--kinds thumbnail dinov2-gem ...] [--fractions 0.5 0.25]
        [--scores /path/nordland_summer.scored.mcap] [--cache out/desc_table] [--limit N]

Reference: ``nordland_dev_summer.mcap``, queries: ``nordland_dev_winter.mcap`` (800 places,
64 x 32), truth ``nordland_dev_truth.json`` (+-1 place). Each drive is described once per kind
with memlog's own describers and cached (``--cache``). Whitening is fitted on every reference
frame (as ``memlog map`` does) and applied to the queries.

Tables (Markdown):

1. descriptor x whitening, full map: R@1 / AUC, unwhitened, whitened at 64/128 dims and by the
   default rule (``min(512, dim, N/2)``).
2. selection at each keep fraction, per descriptor (whitened): uniform, random (mean and std
   over 20 seeds), uniform maps at 90, 95, 98, 102, 105 and 110 % of the size (mean and std: the
   noise level of "another map of about this size"), distinctiveness alone (segment mode and paper mode), and, with ``--scores``
   (an annotated MCAP of ``memlog score --all-scores``), the paper rule, the calibrated rule,
   segment selection and segment selection with distinctiveness.
3. the paper protocol's three readings for every selection of table 2 against the full map's
   AUC: which reading gives the selected map an AUC *gain* over the full map (the paper's claim).

``--tune-distinct`` prints the window x exclusion grid the distinctiveness defaults came from.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
SHARED = Path(os.environ.get("MEMLOG_SHARED_DATA", ROOT.parent / "shared" / "data"))


def described(kind: str, cache: Path, limit: int | None) -> tuple[np.ndarray, np.ndarray]:
    """(reference, query) descriptors of ``kind`` (unwhitened), cached as npz."""
    from benchmarks.descriptor_recall import load_frames
    from memlog.descriptors.registry import make_describer

    path = cache / f"{kind}-{limit or 'all'}.npz"
    if path.is_file():
        z = np.load(path)
        return z["ref"], z["query"]
    d = make_describer(kind)
    ref = d.describe(load_frames(SHARED / "nordland_dev_summer.mcap", limit))
    q = d.describe(load_frames(SHARED / "nordland_dev_winter.mcap", limit))
    cache.mkdir(parents=True, exist_ok=True)
    np.savez(path, ref=ref, query=q)
    return ref, q


class Bench:
    """Evaluates map masks of one descriptor under both protocols."""

    def __init__(self, ref: np.ndarray, q: np.ndarray, truth: list[set[int]]) -> None:
        from memlog.descriptors.search import match

        self.ref, self.q, self.truth = ref, q, truth
        self.full = match(q, ref, k=1)

    def run(self, mask: np.ndarray) -> dict[str, float]:
        from memlog.descriptors.search import match
        from memlog.evaluation.metrics import PAPER_READINGS, evaluate_map_only, evaluate_paper

        mo = evaluate_map_only(match(self.q, self.ref, k=1, ref_mask=mask), self.truth, mask, ns=(1,))
        out = {"frames": float(mask.sum()), "R@1": mo.recall_at[1], "AUC": mo.auc, "coverage": mo.coverage}
        for reading in PAPER_READINGS:
            po = evaluate_paper(self.full, self.truth, mask, ns=(1,), discarded=reading)  # type: ignore[arg-type]
            out[f"paper-{reading}"] = po.auc
            out[f"paper-R@1-{reading}"] = po.recall_at[1]
        return out


def fmt(v: float, s: float | None = None) -> str:
    return f"{v:.3f}" + (f" ± {s:.3f}" if s is not None else "")


def score_table_of(scores: Path | None, n: int) -> Any:
    from memlog.outputs.annotated import read_scores
    from memlog.selection.table import ScoreTable
    from memlog.steps.map import score_table

    if scores is None:  # neutral scores: every frame passes, ties everywhere (distinctiveness decides)
        return ScoreTable(index=np.arange(n), t_ns=np.arange(n) * 10**8, ms=np.ones(n), ss=np.ones(n), es=np.ones(n))
    recs = next(iter(read_scores(scores).values()))
    by = {r["frame_index"]: r for r in recs}
    return score_table([by[i] for i in range(n)], "ref")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--kinds", nargs="+", default=["thumbnail", "dinov2-gem", "dinov2-cls", "dinov2-gem-l7",
                                                   "dinov2-gem-ms"])
    ap.add_argument("--fractions", type=float, nargs="+", default=[0.5, 0.25])
    ap.add_argument("--scores", type=Path, help="annotated MCAP of the summer drive (memlog score --all-scores)")
    ap.add_argument("--cache", type=Path, default=ROOT / "out" / "desc_table")
    ap.add_argument("--limit", type=int, help="first N places only")
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--tune-distinct", action="store_true")
    ap.add_argument("--whiten-dim", type=int, default=None, help="whitened dimension for tables 2 and 3 "
                                                                    "(64 or 128; default: the rule)")
    a = ap.parse_args()

    from memlog.descriptors.whitening import fit_whitening, whitening_dim
    from memlog.evaluation.metrics import parse_truth
    from memlog.selection import random_masks, uniform_mask
    from memlog.selection.config import SelectionConfig
    from memlog.selection.distinctiveness import DistinctConfig, distinctiveness

    truth_all = parse_truth(SHARED / "nordland_dev_truth.json", 800, 800)
    n = a.limit or 800
    truth = [{i for i in s if i < n} for s in truth_all[:n]]
    descs = {k: described(k, a.cache, a.limit) for k in a.kinds}
    print(f"Nordland slice: {n} summer references, {n} winter queries (64x32); chance R@1 ~ {3 / n:.4f}\n")

    # 1. descriptor x whitening
    print("| descriptor | raw R@1 | raw AUC | white-64 R@1 | white-64 AUC | white-128 R@1 | white-128 AUC "
          "| white (rule) R@1 | white (rule) AUC |")
    print("|---|---|---|---|---|---|---|---|---|")
    white: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    full_mask = np.ones(n, bool)
    for k, (r, q) in descs.items():
        cells = []
        b = Bench(r, q, truth).run(full_mask)
        cells += [fmt(b["R@1"]), fmt(b["AUC"])]
        for dim in (64, 128, None):
            w = fit_whitening(r, max_dim=dim)
            wr, wq = w.apply(r), w.apply(q)
            if dim == a.whiten_dim:
                white[k] = (wr, wq)
            b = Bench(wr, wq, truth).run(full_mask)
            cells += [fmt(b["R@1"]), fmt(b["AUC"])]
        print(f"| {k} ({r.shape[1]}-d, rule: {whitening_dim(n, r.shape[1])}-d) | " + " | ".join(cells) + " |",
              flush=True)
    print(f"\n(tables 2-3: whitened {'by the rule' if a.whiten_dim is None else f'to {a.whiten_dim} dims'})\n")

    if a.tune_distinct:
        print("| descriptor | window | exclusion | fraction | R@1 distinct (segment) | uniform R@1 |")
        print("|---|---|---|---|---|---|")
        table = score_table_of(None, n)
        for k, (wr, wq) in white.items():
            bench = Bench(wr, wq, truth)
            for win in (1, 2, 4):
                for exc in (5, 10, 20):
                    table.ds = distinctiveness(wr, DistinctConfig(window=win, exclusion=exc))
                    for fr in a.fractions:
                        sel = SelectionConfig(keep_fraction=fr, segment_by="count", weights=(0, 0, 0),
                                              distinct_weight=1.0, min_ss=0.0).run(table)
                        u = bench.run(uniform_mask(n, int(sel.keep.sum())))
                        print(f"| {k} | {win} | {exc} | {fr:g} | {fmt(bench.run(sel.keep)['R@1'])} | "
                              f"{fmt(u['R@1'])} |", flush=True)
        return 0

    # 2./3. selections
    table = score_table_of(a.scores, n)
    have_scores = a.scores is not None
    cols = ["R@1", "AUC", "coverage", "paper-false_negative", "paper-true_negative", "paper-uncovered_negative"]
    print("| descriptor | fraction | map | frames | R@1 | AUC | coverage | paper AUC (FN) | paper AUC (TN) "
          "| paper AUC (uncovered) |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for k, (wr, wq) in white.items():
        bench = Bench(wr, wq, truth)
        table.ds = distinctiveness(wr)
        full = bench.run(full_mask)
        print(f"| {k} | 1 | full map | {n} | " + " | ".join(fmt(full[c]) for c in cols) + " |")
        for fr in a.fractions:
            kk = max(1, int(np.floor(fr * n + 0.5)))
            rows: list[tuple[str, dict[str, float], dict[str, float] | None]] = []
            rows.append(("uniform", bench.run(uniform_mask(n, kk)), None))
            rand = [bench.run(m) for m in random_masks(n, kk, range(a.seeds))]
            rows.append((f"random ({a.seeds} seeds)", {c: float(np.mean([x[c] for x in rand])) for c in rand[0]},
                         {c: float(np.std([x[c] for x in rand])) for c in rand[0]}))
            sizes = {int(round(kk * f)) for f in (0.9, 0.95, 0.98, 1.02, 1.05, 1.1)} - {kk}
            nb = [bench.run(uniform_mask(n, m)) for m in sorted(sizes) if 0 < m <= n]
            rows.append(("uniform at 90-110 % size (6 maps)", {c: float(np.mean([x[c] for x in nb])) for c in nb[0]},
                         {c: float(np.std([x[c] for x in nb])) for c in nb[0]}))
            seg = SelectionConfig(keep_fraction=fr, segment_by="count", weights=(0, 0, 0), distinct_weight=1.0,
                                  min_ss=0.0).run(table)
            rows.append(("segment, distinctiveness alone", bench.run(seg.keep), None))
            pap = SelectionConfig(mode="paper", mt=0, st=0, et=0, dt=1.0 - fr).run(table)
            rows.append(("paper mode, distinctiveness alone (DT = 1 - fraction)", bench.run(pap.keep), None))
            if have_scores:
                rows.append(("paper rule calibrated (MS/SS/ES)",
                             bench.run(SelectionConfig(mode="paper", keep_fraction=fr).run(table).keep), None))
                rows.append(("segment (MS/SS/ES, geometric)",
                             bench.run(SelectionConfig(keep_fraction=fr).run(table).keep), None))
                rows.append(("segment (MS/SS/ES) + distinctiveness",
                             bench.run(SelectionConfig(keep_fraction=fr, distinct_weight=1.0).run(table).keep), None))
            for name, vals, std in rows:
                cells = [fmt(vals[c], std[c] if std else None) for c in cols]
                print(f"| {k} | {fr:g} | {name} | {int(vals['frames'])} | " + " | ".join(cells) + " |", flush=True)
        if have_scores:
            sel = SelectionConfig(mode="paper").run(table)  # the paper's fixed thresholds
            kk = int(sel.keep.sum())
            if kk:
                for name, m in (("paper rule (MT .5, ST .6, ET .4)", sel.keep), ("uniform, same size",
                                                                                uniform_mask(n, kk))):
                    vals = bench.run(m)
                    print(f"| {k} | {kk / n:.2f} | {name} | {kk} | " + " | ".join(fmt(vals[c]) for c in cols) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

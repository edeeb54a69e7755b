#!/usr/bin/env python3
"""Selection modes against uniform and random maps of the same size, on the shared Nordland slice.

    python benchmarks/selection_table.py [--out DIR] [--fractions 0.25 0.5 0.75] [--descriptor thumbnail]

Runs ``memlog evaluate`` (summer = reference, winter = query, the truth file) once per selection
mode and keep fraction. The reference is scored once with every score (DIR/base/reference.scored.mcap)
and described once; each run reuses those files through hard links. Prints a Markdown table:
R@1 and AUC under the map-only protocol, R@1 and AUC under the paper protocol, coverage.

    python benchmarks/selection_table.py --tune

prints the grid the segment-selection defaults were chosen from (after one normal run has
cached the scores and descriptors in DIR/base): every combination of criterion weights and
combination rule at each keep fraction, map-only R@1/AUC and paper-protocol R@1, next to
uniform and random maps of the same size.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
SHARED = Path(os.environ.get("MEMLOG_SHARED_DATA", ROOT.parent / "shared" / "data"))


def run(out: Path, select: str, fraction: float, descriptor: str, extra: dict[str, Any]) -> dict[str, Any]:
    from memlog.selection.config import SelectionConfig
    from memlog.steps.evaluate import EvaluateConfig, evaluate

    base = out / "base"
    d = out / (f"{select}-{fraction:g}" + ("-" + "-".join(f"{k}={v}" for k, v in sorted(extra.items())) if extra else ""))
    d.mkdir(parents=True, exist_ok=True)
    for name in ("reference.scored.mcap", f"reference.{descriptor}.parquet", f"query.{descriptor}.parquet"):
        if (base / name).is_file() and not (d / name).exists():
            os.link(base / name, d / name)
    cfg = EvaluateConfig(select=SelectionConfig(mode=select, keep_fraction=fraction, **extra),  # type: ignore[arg-type]
                         descriptor=descriptor, report=False)
    res = evaluate(SHARED / "nordland_dev_summer.mcap", SHARED / "nordland_dev_winter.mcap", d, cfg,
                   truth=SHARED / "nordland_dev_truth.json").results
    for name in ("reference.scored.mcap", f"reference.{descriptor}.parquet", f"query.{descriptor}.parquet"):
        if not (base / name).exists():
            base.mkdir(parents=True, exist_ok=True)
            os.link(d / name, base / name)
    return res


def row(name: str, r: dict[str, Any]) -> list[str]:
    def f(v: Any, std: Any = None) -> str:
        if v is None:
            return "-"
        return f"{v:.3f}" + (f" ± {std:.3f}" if std is not None else "")
    s, ps = r.get("std", {}), r["paper_protocol"].get("std", {})
    p = r["paper_protocol"]
    return [name, str(r["frames"]), f(r["coverage"], s.get("coverage")), f(r["recall@1"], s.get("recall@1")),
            f(r["auc"], s.get("auc")), f(p["recall@1"], ps.get("recall@1")), f(p["auc"], ps.get("auc"))]


def tune(out: Path, fractions: list[float], descriptor: str) -> None:
    """The segment-selection grid, evaluated in-process on the cached reference files."""
    import numpy as np

    from memlog.outputs.descriptor_table import read_descriptors
    from memlog.evaluation.metrics import evaluate_map_only, evaluate_paper, parse_truth
    from memlog.descriptors.search import match
    from memlog.outputs.annotated import read_scores
    from memlog.selection import random_masks, uniform_mask
    from memlog.selection.config import SelectionConfig
    from memlog.steps.map import score_table

    base = out / "base"
    recs = next(iter(read_scores(base / "reference.scored.mcap").values()))
    ref = read_descriptors(base / f"reference.{descriptor}.parquet")
    q = read_descriptors(base / f"query.{descriptor}.parquet")
    by_frame = {r["frame_index"]: r for r in recs}
    table = score_table([by_frame[int(i)] for i in ref.frame_index], "ref")
    truth_frames = parse_truth(SHARED / "nordland_dev_truth.json", None, None)
    row_of = {int(f): r for r, f in enumerate(ref.frame_index)}
    truth = [{row_of[j] for j in truth_frames[int(f)] if j in row_of} for f in q.frame_index]
    full = match(q.descriptors, ref.descriptors, k=1)

    def score(mask: np.ndarray) -> tuple[float, float, float, float]:
        mo = evaluate_map_only(match(q.descriptors, ref.descriptors, k=1, ref_mask=mask), truth, mask, ns=(1,))
        po = evaluate_paper(full, truth, mask, ns=(1,))
        return mo.recall_at[1], mo.auc, po.recall_at[1], mo.coverage

    def line(fr: float, name: str, vals: tuple[float, ...], frames: int) -> None:
        print(f"| {fr:g} | {name} | {frames} | " + " | ".join(f"{v:.3f}" for v in vals) + " |")
        sys.stdout.flush()

    print("| fraction | selection | frames | R@1 (map-only) | AUC (map-only) | R@1 (paper) | coverage |")
    print("|---|---|---|---|---|---|---|")
    n = len(ref)
    weights = [(1, 1, 1), (1, 0, 0), (0, 0, 1), (1, 0, 1), (2, 0, 1), (1, 0, 2)]
    for fr in fractions:
        sel = SelectionConfig(mode="paper", keep_fraction=fr).run(table)
        line(fr, "paper rule (calibrated)", score(sel.keep), int(sel.keep.sum()))
        k = 0
        for w in weights:
            for comb in ("rank", "geometric"):
                sel = SelectionConfig(keep_fraction=fr, weights=w, combine=comb).run(table)  # type: ignore[arg-type]
                k = int(sel.keep.sum())
                line(fr, f"segment w(ms,ss,es)={w} {comb}", score(sel.keep), k)
        for comb in ("rank", "geometric"):  # the minimum scores: dark frames (tunnels) dropped or not
            sel = SelectionConfig(keep_fraction=fr, combine=comb, min_ms=0.05, min_es=0.05).run(table)  # type: ignore[arg-type]
            line(fr, f"segment {comb}, min_ms = min_es = 0.05", score(sel.keep), int(sel.keep.sum()))
        line(fr, "uniform", score(uniform_mask(n, k)), k)
        rand = np.array([score(m) for m in random_masks(n, k, range(20))])
        line(fr, "random (mean of 20)", tuple(rand.mean(axis=0)), k)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default=str(ROOT / "out" / "nordland"))
    ap.add_argument("--fractions", type=float, nargs="+", default=[0.25, 0.5, 0.75])
    ap.add_argument("--descriptor", default="thumbnail")
    ap.add_argument("--segment", default="{}", help="JSON of extra segment settings to try")
    ap.add_argument("--tune", action="store_true", help="print the segment-selection grid (needs one normal run first)")
    a = ap.parse_args()
    out = Path(a.out)
    if a.tune:
        tune(out, a.fractions, a.descriptor)
        return 0
    seg_extra = json.loads(a.segment)
    print("| fraction | map | frames | coverage | R@1 (map-only) | AUC (map-only) | R@1 (paper) | AUC (paper) |")
    print("|---|---|---|---|---|---|---|---|")
    for fr in a.fractions:
        paper = run(out, "paper", fr, a.descriptor, {})
        seg = run(out, "segment", fr, a.descriptor, seg_extra)
        rows = [row("full map", paper["full"]), row("paper rule (calibrated)", paper["memorable"]),
                row("segment", seg["memorable"]), row("uniform", paper["uniform"]),
                row(f"random ({paper['random']['seeds']} seeds)", paper["random"])]
        if seg["memorable"]["frames"] != paper["memorable"]["frames"]:
            rows.append(row("uniform (segment size)", seg["uniform"]))
            rows.append(row("random (segment size)", seg["random"]))
        for r in rows:
            print(f"| {fr:g} | " + " | ".join(r) + " |")
        sys.stdout.flush()
    return 0


if __name__ == "__main__":
    sys.exit(main())

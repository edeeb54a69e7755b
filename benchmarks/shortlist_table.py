#!/usr/bin/env python3
"""How good are maps whose segments run ResMem on only K candidates (``memlog map --candidates K``)?

On the shared Nordland pair (summer = reference, winter = query, 800 places, +-1 frame), from a
scoring run with every score of every summer frame (``memlog score --all-scores``; pass it with
--scores, it takes about an hour of CNN on two cores), this replays the map step's segment
choice (:func:`memlog.selection.staged.choose_in_segment`, the same code) with the recorded MS:
exact (every frame that can win is scored) and shortlists of K = 1, 2, 4, 8 frames per segment
(the best by SS and ES, spread over the segment), at several keep fractions, and evaluates each
map under the map-only protocol (R@1, AUC) against uniform and random maps of the same size
(random: mean and std of 20 seeds, the noise level). Descriptors are whitened like the map
step's default (``--no-whiten``: raw).

    python benchmarks/shortlist_table.py --scores /path/nordland_summer.scored.mcap
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


def main() -> int:
    from memlog.descriptors.extract import describe_log
    from memlog.descriptors.registry import make_describer
    from memlog.descriptors.search import match
    from memlog.descriptors.whitening import fit_whitening
    from memlog.evaluation.metrics import evaluate_map_only, parse_truth
    from memlog.io import FrameWindow
    from memlog.outputs.annotated import read_scores
    from memlog.selection import random_masks, uniform_mask
    from memlog.selection.config import SelectionConfig
    from memlog.selection.segment import SegmentConfig, cut_segments
    from memlog.selection.staged import MSResult, choose_in_segment
    from memlog.steps.map import score_table

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scores", required=True, help="annotated MCAP of the summer log with every score")
    ap.add_argument("--fractions", type=float, nargs="+", default=[0.1, 0.25, 0.5])
    ap.add_argument("--ks", type=int, nargs="+", default=[1, 2, 4, 8])
    ap.add_argument("--descriptor", default="thumbnail")
    ap.add_argument("--no-whiten", action="store_true",
                    help="raw descriptors (default: PCA-whitened like `memlog map`, fitted on every summer frame)")
    a = ap.parse_args()

    recs = next(iter(read_scores(a.scores).values()))
    table = score_table(recs, "ref")
    d = make_describer(a.descriptor)
    ref, _ = describe_log(SHARED / "nordland_dev_summer.mcap", d, FrameWindow())
    q, _ = describe_log(SHARED / "nordland_dev_winter.mcap", d, FrameWindow())
    if not a.no_whiten:  # the map step's default: fitted on every reference frame, applied to both drives
        w = fit_whitening(ref.descriptors)
        ref_desc, q_desc = w.apply(ref.descriptors), w.apply(q.descriptors)
    else:
        ref_desc, q_desc = ref.descriptors, q.descriptors
    row_of = {int(f): r for r, f in enumerate(ref.frame_index)}
    truth_frames = parse_truth(SHARED / "nordland_dev_truth.json")
    truth = [{row_of[j] for j in truth_frames[int(f)] if j in row_of} for f in q.frame_index]
    assert np.array_equal(ref.frame_index, table.index), "descriptor rows must be the scored frames"

    def score(mask: np.ndarray) -> tuple[float, float]:
        mo = evaluate_map_only(match(q_desc, ref_desc, k=1, ref_mask=mask), truth, mask, ns=(1,))
        return mo.recall_at[1], mo.auc

    print("| kept | map | frames | R@1 | AUC | frames scored by ResMem |")
    print("|---|---|---|---|---|---|")
    for fr in a.fractions:
        sel = SelectionConfig(keep_fraction=fr)
        seg, coord, _ = cut_segments(table, SegmentConfig(**sel.segment_settings()))
        passing = (table.ss >= sel.min_ss) & (table.es >= sel.min_es)
        rows: list[tuple[str, np.ndarray, int]] = []
        for k in [None, *a.ks]:
            keep = np.zeros(table.n, bool)
            scored = 0
            for sid in np.unique(seg):
                cand = [int(r) for r in np.flatnonzero((seg == sid) & passing)]

                def fn(r: int, thr: float | None, known: Any) -> MSResult:
                    v = float(table.ms[r])
                    return MSResult(v, v, True, None, 25)

                winner, states = choose_in_segment(cand, table.ss, table.es, fn, weights=sel.weights,
                                                   min_ms=sel.min_ms, shortlist=k, coord=coord,
                                                   centre_tolerance=sel.centre_tolerance)
                scored += sum(st.scored for st in states.values())
                if winner is not None:
                    keep[winner] = True
            rows.append(("exact" if k is None else f"K = {k}", keep, scored))
        full_sel = sel.run(table).keep
        assert np.array_equal(rows[0][1], full_sel), "the replayed exact choice is the selection's"
        n = int(rows[0][1].sum())
        for name, keep, scored in rows:
            r1, auc = score(keep)
            print(f"| {fr:g} | segment, {name} | {int(keep.sum())} | {r1:.3f} | {auc:.3f} | {scored} of {table.n} |")
        r1, auc = score(uniform_mask(table.n, n))
        print(f"| {fr:g} | uniform | {n} | {r1:.3f} | {auc:.3f} | - |")
        rand = np.array([score(m) for m in random_masks(table.n, n, range(20))])
        mean, std = rand.mean(axis=0), rand.std(axis=0)
        print(f"| {fr:g} | random (20 seeds) | {n} | {mean[0]:.3f} ± {std[0]:.3f} | {mean[1]:.3f} ± {std[1]:.3f} | - |")
        sys.stdout.flush()
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""What ``memlog evaluate`` reports beside each map's protocols: the paper's threshold sweeps, the
criterion contribution, the mean and spread of the random maps, and the truth taken from both drives'
positions."""

from __future__ import annotations

from typing import Any

import numpy as np

from memlog.descriptors.table import DescriptorTable
from memlog.errors import EvaluationError
from memlog.evaluation.matching import Matching
from memlog.evaluation.metrics import Discarded, ProtocolResult, evaluate_map_only, evaluate_paper, truth_from_positions
from memlog.selection import ScoreTable
from memlog.selection.paper import first_failing

__all__ = ["SWEEP_STEPS", "CRITERIA", "MAP_ROWS", "sweeps", "contribution", "mean_std", "among", "position_truth", "local_positions"]

SWEEP_STEPS = tuple(round(0.1 * i, 1) for i in range(11))
CRITERIA = {1: "staticity", 2: "entropy", 3: "memorability"}
#: The maps ``memlog evaluate`` compares, in the order every table gives them (results.json key -> label).
MAP_ROWS = {"full": "full", "memorable": "memorable", "memorable_exact": "memorable (exact)",
            "uniform": "every k-th", "uniform_phases": "every k-th, its start offsets",
            "uniform_distance": "uniform by distance", "random": "random"}


def position_truth(ref_t: DescriptorTable, q_t: DescriptorTable, tol_m: float) -> list[set[int]]:
    """Truth by position, indexed by frame index (like a truth file)."""
    def arr(t: DescriptorTable) -> tuple[np.ndarray, bool]:
        p = t.positions
        if "lat" in p:
            return np.stack([p["lat"], p["lon"]], axis=1), True
        if "x" in p:
            return np.stack([p["x"], p["y"]], axis=1), False
        raise EvaluationError("no --truth file and the logs have no positions (NavSatFix, pose or odometry)")

    qp, geo_q = arr(q_t)
    rp, geo_r = arr(ref_t)
    if geo_q != geo_r:
        raise EvaluationError("reference and query positions are in different frames (GNSS vs local pose)")
    rows = truth_from_positions(qp, rp, tol_m, geographic=geo_q)
    n_q = int(q_t.frame_index.max()) + 1
    by_frame: list[set[int]] = [set() for _ in range(n_q)]
    for r, s in enumerate(rows):
        by_frame[int(q_t.frame_index[r])] = {int(ref_t.frame_index[j]) for j in s}
    return by_frame


def local_positions(t: DescriptorTable) -> np.ndarray | None:
    """The table's positions in metres ([N, 2]; geographic ones projected about their mean)."""
    from memlog.io.positions import geo_origin, geo_to_local

    p = t.positions
    if "x" in p:
        return np.stack([p["x"], p["y"]], axis=1)
    if "lat" in p:
        ll = np.stack([p["lat"], p["lon"]], axis=1)
        ok = np.all(np.isfinite(ll), axis=1)
        if not ok.any():
            return None
        return np.asarray(geo_to_local(ll, geo_origin(ll[ok])), dtype=np.float64)
    return None


def mean_std(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """The maps ``rows`` (results of one kind of baseline) as one row: the mean of each figure, and
    its ``std``, ``min`` and ``max`` over the maps (the paper protocol's mean and std)."""
    def agg(key_path: tuple[str, ...]) -> tuple[float, float, float, float]:
        vals = []
        for r in rows:
            v: Any = r
            for k in key_path:
                v = v[k]
            vals.append(np.nan if v is None else float(v))
        a = np.asarray(vals)
        return float(np.nanmean(a)), float(np.nanstd(a)), float(np.nanmin(a)), float(np.nanmax(a))

    out: dict[str, Any] = {"frames": rows[0]["frames"], "seeds": len(rows), "std": {}, "min": {}, "max": {}}
    if "single_frame" in rows[0]:
        out["single_frame"] = mean_std([r["single_frame"] for r in rows])
    for key in ("coverage", "auc", "recall@1", "recall@5", "recall@10", "precision@100%recall",
                "match_seconds_per_query"):
        if rows[0].get(key) is None:
            out[key] = None
            continue
        out[key], out["std"][key], out["min"][key], out["max"][key] = agg((key,))
    out["paper_protocol"] = {"std": {}}
    for key in ("auc", "recall@1", "recall@5", "recall@10", "coverage"):
        if rows[0]["paper_protocol"].get(key) is None:
            continue
        m, s, _lo, _hi = agg(("paper_protocol", key))
        out["paper_protocol"][key] = m
        out["paper_protocol"]["std"][key] = s
    return out


def among(memorable: dict[str, Any], maps: list[dict[str, Any]]) -> dict[str, float]:
    """Where the memorable map lies among baseline ``maps`` of its size: the share of them whose
    R@1 is below, equal to and above its own."""
    mine = memorable["recall@1"]
    vals = np.array([m["recall@1"] for m in maps], dtype=np.float64)
    return {"below": float(np.mean(vals < mine - 1e-12)), "tied": float(np.mean(np.abs(vals - mine) <= 1e-12)),
            "above": float(np.mean(vals > mine + 1e-12))}


def sweeps(table: ScoreTable, matching: Matching, truth_rows: list[set[int]], k: int, paper_discarded: Discarded
           ) -> dict[str, list[dict[str, Any]]]:
    """The paper's sweeps: each threshold from 0 to 1 by 0.1 with the other two at 0 (matched
    as the main results are)."""
    full_idx, full_sim = matching.ranked(None, k)
    out: dict[str, list[dict[str, Any]]] = {}
    for name in ("mt", "st", "et"):
        rows = []
        for v in SWEEP_STEPS:
            th = {"mt": 0.0, "st": 0.0, "et": 0.0, name: v}
            keep = first_failing(table, th["mt"], th["st"], th["et"]) == 0
            row: dict[str, Any] = {"threshold": v, "frames": int(keep.sum())}
            if keep.any():
                ns = (1,)
                idx, sim = matching.ranked(keep, 1)
                mo = evaluate_map_only((idx, sim), truth_rows, keep, ns=ns)
                po = evaluate_paper((full_idx[:, :1], full_sim[:, :1]), truth_rows, keep, ns=ns,
                                    discarded=paper_discarded)
                row.update({"auc": mo.auc, "recall@1": mo.recall_at[1], "coverage": mo.coverage,
                            "paper_auc": po.auc, "paper_recall@1": po.recall_at[1]})
            else:
                row.update({"auc": 0.0, "recall@1": 0.0, "coverage": 0.0, "paper_auc": 0.0, "paper_recall@1": 0.0})
            rows.append(row)
        out[name] = rows
    return out


def contribution(table: ScoreTable, full: ProtocolResult, th: dict[str, float]) -> dict[str, Any]:
    """Of the queries the full map mismatched, which criterion would have discarded their (wrong) best match."""
    codes = first_failing(table, th["mt"], th["st"], th["et"])
    wrong = ~full.correct & (full.best_index >= 0)
    counts = {"staticity": 0, "entropy": 0, "memorability": 0, "kept": 0}
    for b in full.best_index[wrong]:
        c = int(codes[int(b)])
        counts[CRITERIA.get(c, "kept")] += 1
    return {"mismatched_queries": int(wrong.sum()), "wrong_match_discarded_by": counts,
            "thresholds": dict(th),
            "note": "for each query the full map mismatched, the first criterion (staticity, entropy, "
                    "memorability) that the paper's rule at these thresholds fails for the wrongly matched "
                    "reference frame; 'kept' = that frame passes all three"}

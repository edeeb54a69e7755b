"""Pipeline step: ``memlog evaluate`` — does the memorable map help localization?

Given a reference log, a query log and ground truth (a JSON ``matches`` file, or positions in
both logs with a distance tolerance), it scores the reference with every score
(``OUT/reference.scored.mcap``), describes both drives (``OUT/{reference,query}.<kind>.parquet``),
writes the memorable-map log (``OUT/map.mcap`` + ``OUT/map.parquet``) and evaluates, under the
map-only and the paper protocol, the full map, the memorable map and the baselines of the same
size (uniform; random, 20 seeds). It adds the paper's threshold sweeps, the criterion
contribution, map size and matching time, writes ``OUT/results.json`` and ``OUT/report.html``.
Outputs already in OUT are reused when they were made with the same settings.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from memlog import __version__
from memlog.config import ScoreConfig
from memlog.descriptors.base import make_describer
from memlog.descriptors.parquet import DescriptorTable, check_compatible, read_descriptors, write_descriptors
from memlog.errors import EvaluationError
from memlog.evaluate.metrics import (
    ProtocolResult,
    evaluate_map_only,
    evaluate_paper,
    parse_truth,
    truth_from_positions,
)
from memlog.localize.match import match, time_per_query
from memlog.localize.pipeline import describe_log
from memlog.progress import info
from memlog.selection import ScoreTable, random_masks, uniform_mask
from memlog.selection.paper import first_failing

__all__ = ["evaluate", "EvalOptions", "SWEEP_STEPS"]

SWEEP_STEPS = tuple(round(0.1 * i, 1) for i in range(11))
_CRITERIA = {1: "staticity", 2: "entropy", 3: "memorability"}


@dataclass
class EvalOptions:
    """Settings of an evaluation (the scoring settings are a :class:`ScoreConfig`)."""

    descriptor: str = "thumbnail"
    select: str = "segment"
    keep_fraction: float | None = None
    dedup: float | None = None
    tol_m: float = 25.0
    k: int = 10
    seeds: int = 20
    paper_discarded: str = "false_negative"
    reference_topic: str | None = None
    query_topic: str | None = None
    segment: dict[str, Any] = field(default_factory=dict)
    report: bool = True


def _proto(r: ProtocolResult) -> dict[str, Any]:
    return {"auc": r.auc, "recall@1": r.recall_at.get(1), "recall@5": r.recall_at.get(5),
            "recall@10": r.recall_at.get(10), "precision@100%recall": r.precision_at_full_recall,
            "coverage": r.coverage}


def _evaluate_mask(ref: DescriptorTable, q: DescriptorTable, truth: list[set[int]], mask: np.ndarray,
                   full_idx: np.ndarray, full_sim: np.ndarray, opts: EvalOptions) -> tuple[dict[str, Any], ProtocolResult, ProtocolResult]:
    k = min(opts.k, max(1, int(mask.sum())))
    ns = tuple(n for n in (1, 5, 10) if n <= max(k, 1))
    idx, sim = match(q.descriptors, ref.descriptors, k=max(ns), ref_mask=mask)
    mo = evaluate_map_only((idx, sim), truth, mask, ns=ns)
    po = evaluate_paper((full_idx[:, : max(ns)], full_sim[:, : max(ns)]), truth, mask, ns=ns,
                        discarded=opts.paper_discarded)  # type: ignore[arg-type]
    timing = time_per_query(q.descriptors, ref.descriptors, repeats=3, ref_mask=mask, max_queries=50)
    out = {"frames": int(mask.sum()), **_proto(mo), "match_seconds_per_query": timing.seconds_per_query,
           "paper_protocol": _proto(po)}
    return out, mo, po


def _rows_for(table: DescriptorTable, n_frames: int) -> np.ndarray:
    """Row of each frame index 0..n-1 in ``table`` (-1 when the frame was not described)."""
    rows = np.full(n_frames, -1, dtype=np.int64)
    ok = table.frame_index < n_frames
    rows[table.frame_index[ok]] = np.nonzero(ok)[0]
    return rows


def _truth_rows(truth_frames: list[set[int]], q: DescriptorTable, ref_rows: np.ndarray) -> list[set[int]]:
    """Truth re-indexed from frame indices to descriptor rows (queries = rows of q)."""
    out = []
    for fi in q.frame_index:
        s = truth_frames[int(fi)] if int(fi) < len(truth_frames) else set()
        out.append({int(ref_rows[j]) for j in s if j < len(ref_rows) and ref_rows[j] >= 0})
    return out


def _reuse_scores(path: Path, cfg: ScoreConfig) -> bool:
    from memlog.score import run_config

    if not path.is_file():
        return False
    try:
        used = run_config(path)
    except Exception:
        return False
    return used is not None and used.replace(threads=0) == cfg.replace(threads=0)


def _described(log: str, path: Path, describer: Any, topic: str | None,
               scores: dict[str, dict[int, dict[str, Any]]] | None = None) -> DescriptorTable:
    if path.is_file():
        t = read_descriptors(path)
        try:
            check_compatible(t.meta, describer.meta())
            if t.extra.get("log") == str(Path(log)):
                return t
        except Exception:
            pass
    t = describe_log(log, describer, topics=[topic] if topic else None, scores=scores)
    write_descriptors(path, t)
    return t


def evaluate(
    reference: str | os.PathLike[str],
    query: str | os.PathLike[str],
    out_dir: str | os.PathLike[str],
    config: ScoreConfig | None = None,
    *,
    truth: str | os.PathLike[str] | None = None,
    options: EvalOptions | None = None,
) -> dict[str, Any]:
    """Run the evaluation (see module doc); returns what is written to ``results.json``."""
    from memlog.mapping import EmptyMapError, choose_frames, make_map, score_table
    from memlog.score import read_scores, score_log

    t_start = time.perf_counter()
    opts = options or EvalOptions()
    base_cfg = config or ScoreConfig()
    cfg = base_cfg.replace(all_scores=True)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    reference, query = str(reference), str(query)

    # 1. score the reference drive (every score: sweeps and calibration need them)
    scored = out / "reference.scored.mcap"
    if _reuse_scores(scored, cfg):
        info(f"memlog: reusing {scored}")
    else:
        score_log(reference, scored, cfg, topics=[opts.reference_topic] if opts.reference_topic else None)
    all_recs = read_scores(scored)
    ref_topic = opts.reference_topic or sorted(all_recs)[0]
    recs = all_recs[ref_topic]
    score_by_frame = {ref_topic: {r["frame_index"]: r for r in recs}}

    # 2. descriptors of every reference and query frame
    describer = make_describer(opts.descriptor)
    ref_t = _described(reference, out / f"reference.{opts.descriptor}.parquet", describer, ref_topic, score_by_frame)
    q_t = _described(query, out / f"query.{opts.descriptor}.parquet", describer, opts.query_topic)
    n_ref = int(ref_t.frame_index.max()) + 1 if len(ref_t) else 0

    # 3. ground truth, as descriptor rows
    if truth is not None:
        truth_frames = parse_truth(truth, None, None)
        truth_src = str(truth)
    else:
        truth_frames = _position_truth(ref_t, q_t, opts.tol_m)
        truth_src = f"positions within {opts.tol_m} m"
    ref_rows = _rows_for(ref_t, max(n_ref, max((max(s) + 1 for s in truth_frames if s), default=0)))
    truth_rows = _truth_rows(truth_frames, q_t, ref_rows)

    # 4. the memorable selection (on the reference scores, rows aligned with ref_t)
    table = score_table([score_by_frame[ref_topic][int(i)] for i in ref_t.frame_index], ref_topic,
                        None, ref_t.descriptors if opts.dedup is not None or opts.segment.get("by") == "view" else None)
    if ref_t.positions and opts.select == "segment":
        table = _with_positions(table, ref_t)
    sel = choose_frames(table, opts.select, keep_fraction=opts.keep_fraction,
                        thresholds={"mt": cfg.mt, "st": cfg.st, "et": cfg.et}, dedup_distance=opts.dedup,
                        **opts.segment)
    mask = sel.keep.copy()
    if not mask.any():
        raise EmptyMapError(
            f"{reference}: the memorable map is empty at thresholds {sel.thresholds} ({len(mask)} frames scored); "
            "low-resolution drives score low entropy: use --keep-fraction 0.25 (or lower --mt/--st/--et)"
        )
    # the map log itself, from the same scores
    map_res = make_map(reference, out / "map.mcap", cfg, scores=scored, topics=[ref_topic], mode=opts.select,
                       keep_fraction=opts.keep_fraction, dedup_distance=opts.dedup, descriptor=opts.descriptor,
                       segment=opts.segment or None)

    # 5. variants under both protocols
    full_idx, full_sim = match(q_t.descriptors, ref_t.descriptors, k=opts.k)
    results: dict[str, Any] = {"memlog_version": __version__}
    per_variant: dict[str, tuple[ProtocolResult, ProtocolResult]] = {}
    kk = int(mask.sum())
    variants = {"full": np.ones(len(ref_t), bool), "memorable": mask, "uniform": uniform_mask(len(ref_t), kk)}
    for name, m in variants.items():
        res, mo, po = _evaluate_mask(ref_t, q_t, truth_rows, m, full_idx, full_sim, opts)
        results[name] = res
        per_variant[name] = (mo, po)
    results["memorable"].update({"thresholds": sel.thresholds, "select": opts.select,
                                 "keep_fraction": opts.keep_fraction, "gaps": len(sel.gaps)})
    rand = [_evaluate_mask(ref_t, q_t, truth_rows, m, full_idx, full_sim, opts)[0]
            for m in random_masks(len(ref_t), kk, range(opts.seeds))]
    results["random"] = _mean_std(rand)

    # 6. sweeps, contribution, size and time
    results["sweeps"] = _sweeps(table, ref_t, q_t, truth_rows, full_idx, full_sim, opts)
    th = sel.thresholds if opts.select == "paper" and sel.thresholds else {"mt": cfg.mt, "st": cfg.st, "et": cfg.et}
    results["criterion_contribution"] = _contribution(table, per_variant["full"][0], th)
    results["map_size"] = map_res.to_dict()
    results["map_size"].pop("topics", None)
    results["truth"] = truth_src
    results["settings"] = {"score": cfg.to_dict(), "descriptor": describer.meta().to_dict(),
                           "options": {k: v for k, v in opts.__dict__.items()}, "reference": reference,
                           "query": query, "reference_topic": ref_topic,
                           "protocols": {
                               "map-only": "only map frames are searched; a query is correct iff its best map frame "
                                           "is in its truth set; queries whose true places are all missing from "
                                           "the map stay positives and can only be wrong",
                               "paper": "the full reference database is searched; a query whose best match is a "
                                        "discarded frame reports no match (never accepted at any threshold); with "
                                        "discarded=false_negative it still counts in the recall denominator",
                           }}
    results["seconds"] = round(time.perf_counter() - t_start, 1)
    (out / "results.json").write_text(json.dumps(results, indent=2, default=_json_default))
    if opts.report:
        from memlog.evaluate.report import write_report

        write_report(out / "report.html", results, table, sel, per_variant, ref_t, reference, ref_topic)
    return results


def _json_default(o: Any) -> Any:
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.floating,)):
        return float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(type(o).__name__)


def _with_positions(table: ScoreTable, ref_t: DescriptorTable) -> ScoreTable:
    from memlog.io.positions import EARTH_RADIUS_M

    p = ref_t.positions
    if "lat" in p:
        lat0, lon0 = np.nanmean(p["lat"]), np.nanmean(p["lon"])
        x = np.radians(p["lon"] - lon0) * EARTH_RADIUS_M * np.cos(np.radians(lat0))
        y = np.radians(p["lat"] - lat0) * EARTH_RADIUS_M
        pos = np.stack([x, y], axis=1)
    else:
        pos = np.stack([p["x"], p["y"]], axis=1)
    return ScoreTable(table.index, table.t_ns, table.ms, table.ss, table.es, positions=pos,
                      descriptors=table.descriptors, topic=table.topic)


def _position_truth(ref_t: DescriptorTable, q_t: DescriptorTable, tol_m: float) -> list[set[int]]:
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


def _mean_std(rows: list[dict[str, Any]]) -> dict[str, Any]:
    def agg(key_path: tuple[str, ...]) -> tuple[float, float]:
        vals = []
        for r in rows:
            v: Any = r
            for k in key_path:
                v = v[k]
            vals.append(np.nan if v is None else float(v))
        a = np.asarray(vals)
        return float(np.nanmean(a)), float(np.nanstd(a))

    out: dict[str, Any] = {"frames": rows[0]["frames"], "seeds": len(rows), "std": {}}
    for key in ("coverage", "auc", "recall@1", "recall@5", "recall@10", "precision@100%recall",
                "match_seconds_per_query"):
        if rows[0].get(key) is None:
            out[key] = None
            continue
        out[key], out["std"][key] = agg((key,))
    out["paper_protocol"] = {"std": {}}
    for key in ("auc", "recall@1", "recall@5", "recall@10", "coverage"):
        if rows[0]["paper_protocol"].get(key) is None:
            continue
        m, s = agg(("paper_protocol", key))
        out["paper_protocol"][key] = m
        out["paper_protocol"]["std"][key] = s
    return out


def _sweeps(table: ScoreTable, ref_t: DescriptorTable, q_t: DescriptorTable, truth_rows: list[set[int]],
            full_idx: np.ndarray, full_sim: np.ndarray, opts: EvalOptions) -> dict[str, list[dict[str, Any]]]:
    """The paper's sweeps: each threshold from 0 to 1 by 0.1 with the other two at 0."""
    out: dict[str, list[dict[str, Any]]] = {}
    for name in ("mt", "st", "et"):
        rows = []
        for v in SWEEP_STEPS:
            th = {"mt": 0.0, "st": 0.0, "et": 0.0, name: v}
            keep = first_failing(table, th["mt"], th["st"], th["et"]) == 0
            row: dict[str, Any] = {"threshold": v, "frames": int(keep.sum())}
            if keep.any():
                ns = (1,)
                idx, sim = match(q_t.descriptors, ref_t.descriptors, k=1, ref_mask=keep)
                mo = evaluate_map_only((idx, sim), truth_rows, keep, ns=ns)
                po = evaluate_paper((full_idx[:, :1], full_sim[:, :1]), truth_rows, keep, ns=ns,
                                    discarded=opts.paper_discarded)  # type: ignore[arg-type]
                row.update({"auc": mo.auc, "recall@1": mo.recall_at[1], "coverage": mo.coverage,
                            "paper_auc": po.auc, "paper_recall@1": po.recall_at[1]})
            else:
                row.update({"auc": 0.0, "recall@1": 0.0, "coverage": 0.0, "paper_auc": 0.0, "paper_recall@1": 0.0})
            rows.append(row)
        out[name] = rows
    return out


def _contribution(table: ScoreTable, full: ProtocolResult, th: dict[str, float]) -> dict[str, Any]:
    """Of the queries the full map mismatched, which criterion would have discarded their (wrong) best match."""
    codes = first_failing(table, th["mt"], th["st"], th["et"])
    wrong = ~full.correct & (full.best_index >= 0)
    counts = {"staticity": 0, "entropy": 0, "memorability": 0, "kept": 0}
    for b in full.best_index[wrong]:
        c = int(codes[int(b)])
        counts[_CRITERIA.get(c, "kept")] += 1
    return {"mismatched_queries": int(wrong.sum()), "wrong_match_discarded_by": counts,
            "thresholds": dict(th),
            "note": "for each query the full map matched wrongly, the first criterion (staticity, entropy, "
                    "memorability) that the paper's rule at these thresholds fails for the wrongly matched "
                    "reference frame; 'kept' = that frame passes all three"}

"""VPR evaluation: PR curve and AUC (the paper's trapezoid rule), Recall@N, map coverage,
the two map protocols, and ground truth from JSON or positions.

Conventions used throughout (written down so that scores are reproducible):

* Every query reports its best match, with that match's similarity as confidence. A query
  "has a true match" when its truth set (over the *full* reference database) is non-empty.
* **PR curve** (:func:`pr_curve`): thresholds are the distinct reported confidences in
  descending order; at threshold ``t`` the accepted queries are those with confidence
  ``>= t``; precision = correct accepted / accepted; recall = correct accepted / number of
  queries that have a true match (queries without one can only add false positives). With
  distinct confidences there is one point per reporting query: the paper's ``N`` points,
  the first being the single most confident query. No ``(recall 0, precision 1)`` start
  point is added unless ``prepend_zero_recall=True``. A query that reports no match
  (confidence NaN or -inf) is never accepted: a false negative if it has a true match.
* **AUC** (:func:`auc_pr_trapezoid`): the paper's eq. 2 over the curve's points in order,
  ``sum_{i=1}^{N-1} (p_i + p_{i+1}) / 2 * (r_{i+1} - r_i)``.
* **Map-only protocol** (:func:`evaluate_map_only`): the database is the map frames only; a
  query is correct iff its best map frame is in its truth set; a query whose true places were
  all discarded can only be wrong (it stays in the recall denominator).
* **Paper protocol** (:func:`evaluate_paper`): the full reference database is searched;
  discarded frames stay in it but count as negatives: a query whose best match is a discarded
  frame reports "no match". By default (``discarded="false_negative"``) such a query is never
  accepted and, if it has a true match, is a false negative (recall denominator unchanged).
  ``discarded="true_negative"`` is the lenient literal reading of the paper ("treated as true
  negatives"): those queries are dropped from the positives (recall denominator) as well.
  ``discarded="uncovered_negative"`` is the third reading the wording allows: a query none of
  whose true places is in the map has nothing to find, so it is a negative (out of the
  positives); a query with a true place in the map whose best match was discarded stays a
  false negative.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import numpy.typing as npt

from memlog.descriptors.search import topk
from memlog.errors import EvaluationError
from memlog.io.positions import geo_origin, geo_to_local

__all__ = [
    "auc_pr_trapezoid",
    "PRCurve",
    "pr_curve",
    "recall_at_n",
    "precision_at_full_recall",
    "recall_at_full_precision",
    "coverage",
    "ProtocolResult",
    "evaluate_map_only",
    "evaluate_paper",
    "parse_truth",
    "truth_from_positions",
    "PAPER_READINGS",
    "Discarded",
]

#: The readings of the paper protocol's "a discarded best match" (see :func:`evaluate_paper`).
PAPER_READINGS = ("false_negative", "true_negative", "uncovered_negative")
#: one of :data:`PAPER_READINGS`
Discarded = Literal["false_negative", "true_negative", "uncovered_negative"]

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]
BoolArray = npt.NDArray[np.bool_]
Truth = Sequence[Collection[int]]
Scores = npt.ArrayLike | tuple[npt.ArrayLike, npt.ArrayLike]


def auc_pr_trapezoid(precision: npt.ArrayLike, recall: npt.ArrayLike) -> float:
    """Area under the PR curve by the paper's trapezoid rule (eq. 2), points taken in order.

    ``AUC = sum_{i=1}^{N-1} (p_i + p_{i+1}) / 2 * (r_{i+1} - r_i)``; 0 for fewer than 2 points.
    """
    p = np.asarray(precision, dtype=np.float64)
    r = np.asarray(recall, dtype=np.float64)
    if p.ndim != 1 or p.shape != r.shape:
        raise EvaluationError(f"precision {p.shape} and recall {r.shape} must be 1-d of equal length")
    if p.size < 2:
        return 0.0
    return float(np.sum((p[:-1] + p[1:]) / 2.0 * np.diff(r)))


@dataclass
class PRCurve:
    """Points of a precision-recall curve (one per distinct accepted confidence, descending)."""

    thresholds: F64
    precision: F64
    recall: F64
    n_queries: int
    n_positives: int  # queries with a true match: the recall denominator

    @property
    def auc(self) -> float:
        """AUC by :func:`auc_pr_trapezoid`."""
        return auc_pr_trapezoid(self.precision, self.recall)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict (infinite thresholds become None)."""
        return {
            "thresholds": [float(t) if math.isfinite(t) else None for t in self.thresholds],
            "precision": [float(x) for x in self.precision],
            "recall": [float(x) for x in self.recall],
            "n_queries": self.n_queries,
            "n_positives": self.n_positives,
            "auc": self.auc,
        }


def _bool_vec(x: npt.ArrayLike, n: int, name: str) -> BoolArray:
    a = np.asarray(x)
    if a.shape != (n,):
        raise EvaluationError(f"{name} must have shape ({n},), got {a.shape}")
    if a.dtype != np.bool_:
        if not np.all(np.isin(a, (0, 1))):
            raise EvaluationError(f"{name} must be boolean")
        a = a.astype(bool)
    out: BoolArray = a
    return out


def pr_curve(
    confidences: npt.ArrayLike,
    correct: npt.ArrayLike,
    has_match: npt.ArrayLike | None = None,
    *,
    prepend_zero_recall: bool = False,
) -> PRCurve:
    """PR curve from per-query best-match confidences and correctness (see module notes).

    ``has_match`` (default: all True) marks the queries that have a true match; ``correct``
    must imply ``has_match``. Confidence NaN or -inf means "no match reported" (never
    accepted). Queries with equal confidence enter together (one point per distinct value).
    ``prepend_zero_recall`` adds a first point ``(recall 0, precision 1, threshold +inf)``.
    """
    conf = np.asarray(confidences, dtype=np.float64)
    if conf.ndim != 1:
        raise EvaluationError(f"confidences must be 1-d, got shape {conf.shape}")
    n = conf.shape[0]
    ok = _bool_vec(correct, n, "correct")
    pos = np.ones(n, dtype=bool) if has_match is None else _bool_vec(has_match, n, "has_match")
    if np.any(ok & ~pos):
        raise EvaluationError("a query marked correct has no true match (correct must imply has_match)")
    n_pos = int(pos.sum())
    reported = ~np.isnan(conf) & (conf > -np.inf)
    c, k = conf[reported], ok[reported]
    order = np.argsort(-c, kind="stable")
    c, k = c[order], k[order]
    tp = np.cumsum(k)
    accepted = np.arange(1, c.size + 1)
    last_of_group = np.r_[c[1:] != c[:-1], True] if c.size else np.zeros(0, bool)
    thr, tp, accepted = c[last_of_group], tp[last_of_group], accepted[last_of_group]
    precision = tp / accepted
    recall = tp / n_pos if n_pos else np.zeros_like(precision)
    if prepend_zero_recall:
        thr = np.r_[np.inf, thr]
        precision = np.r_[1.0, precision]
        recall = np.r_[0.0, recall]
    return PRCurve(thr.astype(np.float64), precision.astype(np.float64), recall.astype(np.float64), n, n_pos)


def _check_truth(truth: Truth, n_query: int, n_ref: int | None = None) -> list[set[int]]:
    if len(truth) != n_query:
        raise EvaluationError(f"truth has {len(truth)} entries for {n_query} queries")
    sets = [set(int(i) for i in t) for t in truth]
    if n_ref is not None:
        for q, s in enumerate(sets):
            if s and (min(s) < 0 or max(s) >= n_ref):
                raise EvaluationError(f"truth of query {q} has reference index outside 0..{n_ref - 1}")
    return sets


def recall_at_n(ranked_indices: npt.ArrayLike, truth_sets: Truth, ns: Sequence[int] = (1, 5, 10)) -> dict[int, float]:
    """Share of queries with a true match that have one among their top ``n`` candidates.

    ``ranked_indices`` is ``[Q, k]`` (best first, -1 = empty slot), ``k >= max(ns)``.
    Queries with an empty truth set are left out of the denominator; 0.0 when none remain.
    """
    idx = np.asarray(ranked_indices, dtype=np.int64)
    if idx.ndim != 2:
        raise EvaluationError(f"ranked_indices must be [Q, k], got shape {idx.shape}")
    sets = _check_truth(truth_sets, idx.shape[0])
    if any(n < 1 or n > idx.shape[1] for n in ns):
        raise EvaluationError(f"every N in {tuple(ns)} must be in 1..{idx.shape[1]} (the number of candidates)")
    hit_rank = np.full(idx.shape[0], np.iinfo(np.int64).max)
    for q, s in enumerate(sets):
        for r, i in enumerate(idx[q]):
            if i >= 0 and int(i) in s:
                hit_rank[q] = r
                break
    pos = np.array([bool(s) for s in sets], dtype=bool)
    n_pos = int(pos.sum())
    return {int(n): (float(np.sum(pos & (hit_rank < n))) / n_pos if n_pos else 0.0) for n in ns}


def precision_at_full_recall(precision: npt.ArrayLike, recall: npt.ArrayLike) -> float:
    """Precision at the first point where recall reaches 1; 0.0 if it never does."""
    p, r = np.asarray(precision, dtype=np.float64), np.asarray(recall, dtype=np.float64)
    full = np.flatnonzero(r >= 1.0 - 1e-12)
    return float(p[full[0]]) if full.size else 0.0


def recall_at_full_precision(precision: npt.ArrayLike, recall: npt.ArrayLike) -> float:
    """Highest recall among points with precision 1; 0.0 if there is none."""
    p, r = np.asarray(precision, dtype=np.float64), np.asarray(recall, dtype=np.float64)
    sel = p >= 1.0 - 1e-12
    return float(r[sel].max()) if np.any(sel) else 0.0


def _map_mask(map_mask: npt.ArrayLike, n_ref: int | None = None) -> BoolArray:
    m = np.asarray(map_mask)
    if m.ndim != 1 or (n_ref is not None and m.shape[0] != n_ref):
        raise EvaluationError(f"map_mask must have shape ({n_ref},), got {m.shape}")
    return _bool_vec(m, m.shape[0], "map_mask")


def coverage(truth_sets: Truth, map_mask: npt.ArrayLike) -> float:
    """Share of queries with a true match that keep >= 1 true reference in the map.

    Queries with an empty truth set are left out; 0.0 when none remain.
    """
    mask = _map_mask(map_mask)
    sets = _check_truth(truth_sets, len(truth_sets), mask.shape[0])
    pos = [s for s in sets if s]
    if not pos:
        return 0.0
    return sum(1 for s in pos if any(mask[i] for i in s)) / len(pos)


@dataclass
class ProtocolResult:
    """Scores of one evaluation protocol, with per-query details for error analysis."""

    protocol: str
    n_queries: int
    n_refs: int
    n_map: int
    n_positives: int
    coverage: float
    recall_at: dict[int, float]
    auc: float
    precision_at_full_recall: float
    recall_at_full_precision: float
    curve: PRCurve
    best_index: I64  # best candidate per query, full-database row (paper: may be discarded); -1 = none
    confidence: F64  # reported confidence (-inf = no match reported)
    correct: BoolArray
    has_match: BoolArray  # counted in the recall denominator
    options: dict[str, Any] = field(default_factory=dict)

    def to_dict(self, per_query: bool = False, curve: bool = False) -> dict[str, Any]:
        """JSON-ready summary; ``per_query``/``curve`` add the per-query lists / PR points."""
        out: dict[str, Any] = {
            "protocol": self.protocol,
            "n_queries": self.n_queries,
            "n_refs": self.n_refs,
            "n_map": self.n_map,
            "n_positives": self.n_positives,
            "coverage": self.coverage,
            "recall_at": {str(k): v for k, v in self.recall_at.items()},
            "auc": self.auc,
            "precision_at_full_recall": self.precision_at_full_recall,
            "recall_at_full_precision": self.recall_at_full_precision,
            "options": dict(self.options),
        }
        if per_query:
            out["per_query"] = {
                "best_index": [int(i) for i in self.best_index],
                "confidence": [float(c) if math.isfinite(c) else None for c in self.confidence],
                "correct": [bool(c) for c in self.correct],
                "has_match": [bool(c) for c in self.has_match],
            }
        if curve:
            out["curve"] = self.curve.to_dict()
        return out


def _ranked(scores: Scores, k: int, ref_mask: BoolArray | None, n_ref: int) -> tuple[I64, F64]:
    """(indices [Q, >=k], similarities) from a similarity matrix or a (indices, sims) pair."""
    if isinstance(scores, tuple):
        idx = np.asarray(scores[0], dtype=np.int64)
        sim = np.asarray(scores[1], dtype=np.float64)
        if idx.ndim != 2 or idx.shape != sim.shape or idx.shape[1] < 1:
            raise EvaluationError(f"indices {idx.shape} and similarities {sim.shape} must both be [Q, k>=1]")
        if idx.size and (idx.max() >= n_ref or idx.min() < -1):
            raise EvaluationError(f"candidate indices outside -1..{n_ref - 1}")
        if ref_mask is not None and np.any((idx >= 0) & ~ref_mask[np.maximum(idx, 0)]):
            raise EvaluationError("candidates include frames outside the map; match with ref_mask=map_mask")
        return idx, sim
    s = np.asarray(scores, dtype=np.float32)
    if s.ndim != 2 or s.shape[1] != n_ref:
        raise EvaluationError(f"similarity matrix must be [Q, {n_ref}], got {s.shape}")
    i, v = topk(s, k, ref_mask)
    return i, v.astype(np.float64)


def _summarise(protocol: str, idx: I64, best: I64, conf: F64, correct: BoolArray, has_match: BoolArray,
               sets: list[set[int]], mask: BoolArray, ns: Sequence[int], options: dict[str, Any]) -> ProtocolResult:
    ns_ok = [n for n in ns if n <= idx.shape[1]]
    if len(ns_ok) != len(ns):
        raise EvaluationError(f"need at least {max(ns)} candidates per query for Recall@{max(ns)}, got {idx.shape[1]}")
    curve = pr_curve(conf, correct, has_match)
    truth_for_recall = [s if h else set() for s, h in zip(sets, has_match)]
    return ProtocolResult(
        protocol=protocol,
        n_queries=idx.shape[0],
        n_refs=mask.shape[0],
        n_map=int(mask.sum()),
        n_positives=int(has_match.sum()),
        coverage=coverage(sets, mask),
        recall_at=recall_at_n(idx, truth_for_recall, ns),
        auc=curve.auc,
        precision_at_full_recall=precision_at_full_recall(curve.precision, curve.recall),
        recall_at_full_precision=recall_at_full_precision(curve.precision, curve.recall),
        curve=curve,
        best_index=best.copy(),
        confidence=conf,
        correct=correct,
        has_match=has_match,
        options=options,
    )


def _protocol_inputs(
    scores: Scores, truth: Truth, map_mask: npt.ArrayLike, ns: Sequence[int], *, masked: bool
) -> tuple[BoolArray, list[set[int]], I64, F64]:
    """What both protocols start from: the map mask, the truth sets and the ranked candidates
    (searched in the map only when ``masked``, else in the full database)."""
    mask = _map_mask(map_mask)
    sets = _check_truth(truth, len(truth), mask.shape[0])
    idx, sim = _ranked(scores, max(ns), mask if masked else None, mask.shape[0])
    if idx.shape[0] != len(sets):
        raise EvaluationError(f"{idx.shape[0]} queries scored but truth has {len(sets)} entries")
    return mask, sets, idx, sim


def evaluate_map_only(
    scores: Scores, truth: Truth, map_mask: npt.ArrayLike, ns: Sequence[int] = (1, 5, 10)
) -> ProtocolResult:
    """Map-only protocol: the database is the map frames only.

    ``scores`` is the full similarity matrix ``[Q, R]`` (masked here) or ``(indices, sims)``
    from :func:`memlog.descriptors.search.match` with ``ref_mask=map_mask``. A query is correct
    iff its best map frame is in its truth set (truth over the full database); queries whose
    true places were all discarded stay positives and can only be wrong.
    """
    mask, sets, idx, sim = _protocol_inputs(scores, truth, map_mask, ns, masked=True)
    best = idx[:, 0]
    conf = np.where(best >= 0, sim[:, 0], -np.inf)
    correct = np.array([b >= 0 and int(b) in s for b, s in zip(best, sets)], dtype=bool)
    has_match = np.array([bool(s) for s in sets], dtype=bool)
    return _summarise("map-only", idx, best, conf, correct, has_match, sets, mask, ns, {})


def evaluate_paper(
    scores: Scores,
    truth: Truth,
    map_mask: npt.ArrayLike,
    ns: Sequence[int] = (1, 5, 10),
    discarded: Discarded = "false_negative",
) -> ProtocolResult:
    """Paper protocol: search the full database; a best match outside the map is "no match".

    ``scores`` is ``[Q, R]`` or ``(indices, sims)`` from an unmasked search. A query whose
    best match is a discarded frame reports no match: it is never accepted at any threshold.
    ``discarded="false_negative"`` (default): it stays in the recall denominator when it has
    a true match (a false negative). ``"true_negative"``: it is removed from the positives
    (the lenient reading). ``"uncovered_negative"``: queries with no true place in the map are
    removed from the positives instead. Recall@N counts a hit only on map frames of the full
    ranking.
    """
    if discarded not in PAPER_READINGS:
        raise EvaluationError(f"discarded must be one of {', '.join(PAPER_READINGS)}, not {discarded!r}")
    mask, sets, idx, sim = _protocol_inputs(scores, truth, map_mask, ns, masked=False)
    best = idx[:, 0]
    reported = (best >= 0) & mask[np.maximum(best, 0)]
    conf = np.where(reported, sim[:, 0], -np.inf)
    correct = np.array([bool(r) and int(b) in s for b, r, s in zip(best, reported, sets)], dtype=bool)
    has_match = np.array([bool(s) for s in sets], dtype=bool)
    if discarded == "true_negative":
        has_match &= reported
    elif discarded == "uncovered_negative":
        has_match &= np.array([any(mask[i] for i in x) for x in sets], dtype=bool)
    map_ranked = np.where((idx >= 0) & mask[np.maximum(idx, 0)], idx, -1)
    return _summarise("paper", map_ranked, best, conf, correct, has_match, sets, mask, ns, {"discarded": discarded})


def parse_truth(
    source: str | os.PathLike[str] | Mapping[str, Any], n_query: int | None = None, n_ref: int | None = None
) -> list[set[int]]:
    """Truth sets from ``{"matches": [[ref, ...], ...]}`` (a JSON file or an already parsed dict).

    ``matches[q]`` lists the reference indices that are correct for query ``q``. Raises
    :class:`EvaluationError` (naming the file) for unreadable or invalid JSON, a missing or
    malformed ``matches``, a length other than ``n_query`` or an index outside ``0..n_ref-1``.
    """
    if isinstance(source, Mapping):
        name, data = "truth", source
    else:
        name = str(source)
        try:
            text = Path(source).read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as exc:
            raise EvaluationError(f"{name}: cannot read ground truth ({exc})") from None
        try:
            data = json.loads(text)
        except ValueError as exc:
            raise EvaluationError(f"{name}: invalid JSON ({exc})") from None
    if not isinstance(data, Mapping) or "matches" not in data:
        raise EvaluationError(f'{name}: expected a JSON object with a "matches" list')
    matches = data["matches"]
    if not isinstance(matches, list):
        raise EvaluationError(f'{name}: "matches" must be a list of lists')
    if n_query is not None and len(matches) != n_query:
        raise EvaluationError(f'{name}: "matches" has {len(matches)} entries, expected one per query ({n_query})')
    out: list[set[int]] = []
    for q, row in enumerate(matches):
        if not isinstance(row, list) or not all(isinstance(i, int) and not isinstance(i, bool) for i in row):
            raise EvaluationError(f"{name}: matches[{q}] must be a list of integers, got {row!r}")
        bad = [i for i in row if i < 0 or (n_ref is not None and i >= n_ref)]
        if bad:
            limit = f"0..{n_ref - 1}" if n_ref is not None else ">= 0"
            raise EvaluationError(f"{name}: matches[{q}] has reference index {bad[0]} outside {limit}")
        out.append(set(row))
    return out


def truth_from_positions(
    query_pos: npt.ArrayLike,
    ref_pos: npt.ArrayLike,
    tol_m: float = 25.0,
    *,
    geographic: bool = False,
    block_rows: int = 1024,
) -> list[set[int]]:
    """Truth sets: the references within ``tol_m`` metres of each query position.

    Positions are ``[N, 2]`` or ``[N, 3]``. ``geographic=True``: columns are latitude,
    longitude in degrees (a third, altitude, is ignored), projected to local metres with the
    equirectangular approximation about the mean latitude/longitude of all points (good to
    well under 1 % over tens of km). Otherwise the columns are metres (x, y[, z]), all used.
    Rows with NaN get an empty truth set.
    """
    q = np.asarray(query_pos, dtype=np.float64)
    r = np.asarray(ref_pos, dtype=np.float64)
    if q.ndim != 2 or r.ndim != 2 or q.shape[1] not in (2, 3) or r.shape[1] != q.shape[1]:
        raise EvaluationError(f"positions must be [N, 2] or [N, 3] with equal columns, got {q.shape} and {r.shape}")
    if tol_m < 0:
        raise EvaluationError("tol_m must be >= 0")
    if geographic:
        both = np.vstack([q[:, :2], r[:, :2]])
        fin = both[np.all(np.isfinite(both), axis=1)]
        if fin.size and (np.abs(fin[:, 0]).max() > 90 or np.abs(fin[:, 1]).max() > 360):
            raise EvaluationError("geographic positions must be (lat, lon) in degrees")
        origin = geo_origin(both)
        q, r = geo_to_local(q, origin), geo_to_local(r, origin)
    out: list[set[int]] = []
    r_ok = np.all(np.isfinite(r), axis=1)
    r_idx = np.flatnonzero(r_ok)
    rr = r[r_ok]
    for start in range(0, q.shape[0], block_rows):
        qb = q[start : start + block_rows]
        d2 = ((qb[:, None, :] - rr[None, :, :]) ** 2).sum(axis=2)
        within = d2 <= tol_m * tol_m  # NaN query rows compare False
        out.extend({int(i) for i in r_idx[np.flatnonzero(row)]} for row in within)
    return out

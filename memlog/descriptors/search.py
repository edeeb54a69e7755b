"""Exact nearest-neighbour search of query descriptors in a reference database (numpy).

Descriptors are L2-normalised rows, so cosine similarity is the dot product. The similarity
matrix is computed one block of query rows at a time (about ``max_block_elems`` floats per
block) so memory stays bounded for large maps. Results are the ``k`` most similar reference
rows per query, best first; ties are broken by the lower reference index. When the database
(after ``ref_mask``) has fewer than ``k`` rows, the missing entries are index ``-1`` with
similarity ``-inf``.
"""

from __future__ import annotations

import statistics
import time
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from memlog.errors import DescriptorError

__all__ = ["match", "topk", "Confidence", "confidence", "QueryTiming", "time_per_query"]

F32 = npt.NDArray[np.float32]
I64 = npt.NDArray[np.int64]
BoolArray = npt.NDArray[np.bool_]

MAX_BLOCK_ELEMS = 1 << 24  # 64 MiB of float32 similarities per block


def _as_2d(x: npt.ArrayLike, name: str) -> F32:
    a = np.asarray(x, dtype=np.float32)
    if a.ndim == 1:
        a = a[None, :]
    if a.ndim != 2:
        raise DescriptorError(f"{name} must be [N, dim], got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise DescriptorError(f"{name} contains NaN or infinite values")
    return np.ascontiguousarray(a)


def _mask_index(ref_mask: npt.ArrayLike | None, n_refs: int) -> I64 | None:
    if ref_mask is None:
        return None
    m = np.asarray(ref_mask)
    if m.dtype != np.bool_ or m.shape != (n_refs,):
        raise DescriptorError(f"ref_mask must be a boolean array of shape ({n_refs},), got {m.dtype} {m.shape}")
    idx: I64 = np.flatnonzero(m).astype(np.int64)
    return idx


def _topk_block(sim: F32, k: int) -> tuple[I64, F32]:
    """Top ``k`` columns of each row of ``sim`` (k <= columns), best first, ties by index."""
    n_cols = sim.shape[1]
    if k < n_cols:
        part = np.argpartition(-sim, k - 1, axis=1)[:, :k]
    else:
        part = np.broadcast_to(np.arange(n_cols), sim.shape)
    vals = np.take_along_axis(sim, part, axis=1)
    order = np.lexsort((part, -vals), axis=-1)
    return np.take_along_axis(part, order, axis=1).astype(np.int64), np.take_along_axis(vals, order, axis=1)


def _empty(n_query: int, k: int) -> tuple[I64, F32]:
    return np.full((n_query, k), -1, dtype=np.int64), np.full((n_query, k), -np.inf, dtype=np.float32)


def match(
    query: npt.ArrayLike,
    refs: npt.ArrayLike,
    k: int = 10,
    ref_mask: npt.ArrayLike | None = None,
    *,
    block_rows: int | None = None,
) -> tuple[I64, F32]:
    """The ``k`` best references of each query: ``(indices [Q, k], similarities [Q, k])``.

    ``query`` is ``[Q, d]`` (or one ``[d]`` row), ``refs`` is ``[R, d]``; ``ref_mask`` (bool
    ``[R]``) restricts the database to the rows where it is True; returned indices are rows
    of the full ``refs``. ``block_rows`` (default: bounded by memory) sets the query rows
    per block.
    """
    if k < 1:
        raise DescriptorError(f"k must be >= 1, got {k}")
    q = _as_2d(query, "query")
    r = _as_2d(refs, "refs") if np.asarray(refs).size else np.zeros((0, q.shape[1]), np.float32)
    if q.shape[1] != r.shape[1]:
        raise DescriptorError(f"query descriptors are {q.shape[1]}-d but references are {r.shape[1]}-d")
    idx = _mask_index(ref_mask, r.shape[0])
    return _search(q, r if idx is None else r[idx], k, idx, block_rows)


def _search(q: F32, db: F32, k: int, idx: I64 | None, block_rows: int | None) -> tuple[I64, F32]:
    """Top-``k`` search of validated ``q`` in ``db`` (rows ``idx`` of the full database)."""
    indices, sims = _empty(q.shape[0], k)
    if db.shape[0] == 0 or q.shape[0] == 0:
        return indices, sims
    kk = min(k, db.shape[0])
    rows = block_rows or max(1, MAX_BLOCK_ELEMS // db.shape[0])
    for start in range(0, q.shape[0], rows):
        qb = q[start : start + rows]
        # one query: a matrix-vector product is several times faster than a 1-row GEMM
        sim = (db @ qb[0])[None, :] if qb.shape[0] == 1 else qb @ db.T
        bi, bs = _topk_block(sim, kk)
        indices[start : start + rows, :kk] = bi if idx is None else idx[bi]
        sims[start : start + rows, :kk] = bs
    return indices, sims


def topk(sim: npt.ArrayLike, k: int = 10, ref_mask: npt.ArrayLike | None = None) -> tuple[I64, F32]:
    """Like :func:`match` but on a precomputed similarity matrix ``sim [Q, R]``."""
    if k < 1:
        raise DescriptorError(f"k must be >= 1, got {k}")
    s = np.asarray(sim, dtype=np.float32)
    if s.ndim != 2:
        raise DescriptorError(f"similarity matrix must be [Q, R], got shape {s.shape}")
    idx = _mask_index(ref_mask, s.shape[1])
    sub = s if idx is None else s[:, idx]
    indices, sims = _empty(s.shape[0], k)
    if sub.shape[1] == 0 or s.shape[0] == 0:
        return indices, sims
    kk = min(k, sub.shape[1])
    bi, bs = _topk_block(np.nan_to_num(sub, nan=-np.inf), kk)
    indices[:, :kk] = bi if idx is None else idx[bi]
    sims[:, :kk] = bs
    return indices, sims


@dataclass
class Confidence:
    """Per-query confidence of the best match.

    ``best``: similarity of the best match (the VPR confidence used for PR curves);
    ``margin``: best minus second-best similarity; ``ratio``: Lowe-style distance ratio
    d1 / d2 with d = sqrt(2 - 2 s) (the Euclidean distance of unit vectors; lower is more
    distinctive). ``margin``/``ratio`` are NaN when there is no second candidate.
    """

    best: F32
    margin: F32
    ratio: F32

    def to_dict(self) -> dict[str, list[float]]:
        """JSON-ready dict of lists."""
        return {k: [float(x) for x in v] for k, v in asdict(self).items()}


def confidence(similarities: npt.ArrayLike) -> Confidence:
    """Confidence measures from the ``[Q, k]`` similarities returned by :func:`match`."""
    s = np.asarray(similarities, dtype=np.float32)
    if s.ndim != 2 or s.shape[1] < 1:
        raise DescriptorError(f"similarities must be [Q, k>=1], got shape {s.shape}")
    best = s[:, 0].copy()
    if s.shape[1] < 2:
        nan = np.full(s.shape[0], np.nan, dtype=np.float32)
        return Confidence(best, nan, nan.copy())
    second = s[:, 1]
    ok = np.isfinite(best) & np.isfinite(second)
    with np.errstate(invalid="ignore", divide="ignore"):
        margin = np.where(ok, best - second, np.nan).astype(np.float32)
        d1 = np.sqrt(np.maximum(0.0, 2.0 - 2.0 * best))
        d2 = np.sqrt(np.maximum(0.0, 2.0 - 2.0 * second))
        ratio = np.where(ok & (d2 > 0), d1 / np.where(d2 > 0, d2, 1.0), np.where(ok, 1.0, np.nan)).astype(np.float32)
    return Confidence(best, margin, ratio)


@dataclass
class QueryTiming:
    """Time to match one query against the whole database (seconds)."""

    seconds_per_query: float  # median over repeats of the mean time per query
    min_seconds_per_query: float
    n_refs: int
    dim: int
    n_queries: int
    repeats: int

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict."""
        return asdict(self)


def time_per_query(
    query: npt.ArrayLike,
    refs: npt.ArrayLike,
    repeats: int = 5,
    ref_mask: npt.ArrayLike | None = None,
    *,
    k: int = 1,
    max_queries: int = 100,
) -> QueryTiming:
    """Wall time of matching one query row against all (masked) references.

    Each of the first ``max_queries`` query rows is matched on its own (the search of
    :func:`match` with a single row, top ``k``; inputs are validated once, outside the
    timing); the database is gathered by ``ref_mask`` once beforehand, so the time is that
    of searching a database of the map's size. ``repeats`` passes; the median
    of the per-pass mean is reported.
    """
    if repeats < 1:
        raise DescriptorError("repeats must be >= 1")
    q = _as_2d(query, "query")[:max_queries]
    r = _as_2d(refs, "refs")
    idx = _mask_index(ref_mask, r.shape[0])
    db = np.ascontiguousarray(r if idx is None else r[idx])
    if q.shape[0] == 0:
        raise DescriptorError("no query descriptors to time")
    _search(q[:1], db, k, None, None)  # warm-up
    per_pass: list[float] = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for i in range(q.shape[0]):
            _search(q[i : i + 1], db, k, None, None)
        per_pass.append((time.perf_counter() - t0) / q.shape[0])
    return QueryTiming(statistics.median(per_pass), min(per_pass), int(db.shape[0]), int(q.shape[1]),
                       int(q.shape[0]), repeats)

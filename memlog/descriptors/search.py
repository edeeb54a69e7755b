"""Exact nearest-neighbour search of query descriptors in a reference database (numpy).

Descriptors are L2-normalised rows, so cosine similarity is the dot product. Results are the
``k`` most similar reference rows per query, best first; ties are broken by the lower
reference index. When the database (after ``ref_mask``) has fewer than ``k`` rows, the missing
entries are index ``-1`` with similarity ``-inf``.

Queries are matched in blocks (:data:`QUERY_BLOCK` rows) against tiles of the database, one
float32 matrix product per tile with at most :data:`MAX_BLOCK_ELEMS` similarities, so many
queries share each pass over the map and memory stays bounded. The top ``k`` of a tile are found
without sorting it: the maxima of groups of columns bound the ``k``-th value from below, and
only the columns above that bound are kept. The kept candidates are then scored again in
float64, one (query, reference) pair at a time, and ranked by that score: a float32 product's
rounding depends on the BLAS kernel, which depends on the block's shape, so candidates are
kept within the product's worst-case rounding error (``gamma_d * |q| * max|r|``) of the
``k``-th and the float64 score decides. The result is the same whatever the blocking: matching
queries one by one or all at once gives identical indices and similarities.
"""

from __future__ import annotations

import statistics
import time
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from memlog.errors import DescriptorError

__all__ = ["match", "topk", "Confidence", "confidence", "QueryTiming", "time_per_query", "Database",
           "QUERY_BLOCK"]

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]
BoolArray = npt.NDArray[np.bool_]

MAX_BLOCK_ELEMS = 1 << 23  # 32 MiB of float32 similarities per tile
QUERY_BLOCK = 256  # queries per matrix product (throughput is flat from ~128 on 2 cores)
GROUP = 128  # columns per group maximum in the top-k bound
CHECK_ELEMS = 1 << 22  # elements per chunk when validating a matrix (16 MiB)
RESCORE_ELEMS = 1 << 20  # float64 elements per chunk when re-scoring candidates (8 MiB)
LARGEST_NORM = 1e15  # |q| * |r| above this could overflow float32 products


def _as_2d(x: npt.ArrayLike, name: str) -> F32:
    a = np.asarray(x, dtype=np.float32)
    if a.ndim == 1:
        a = a[None, :]
    if a.ndim != 2:
        raise DescriptorError(f"{name} must be [N, dim], got shape {a.shape}")
    return np.ascontiguousarray(a)


def _row_norms(a: F32, name: str) -> F32:
    """Euclidean norm of every row of ``a``; DescriptorError for NaN or infinite values.

    Works in chunks, so checking a large map needs no matrix-sized temporary.
    """
    out = np.empty(a.shape[0], dtype=np.float32)
    rows = max(1, CHECK_ELEMS // max(1, a.shape[1]))
    for s in range(0, a.shape[0], rows):
        c = a[s : s + rows]
        sq = np.einsum("ij,ij->i", c, c)
        if not np.all(np.isfinite(sq)) and not np.all(np.isfinite(c)):
            raise DescriptorError(f"{name} contains NaN or infinite values")
        out[s : s + rows] = np.sqrt(sq)
    return out


@dataclass
class Database:
    """A validated reference matrix with what the search needs to know about it.

    ``rows`` are the float32 ``[R, d]`` descriptors searched; ``index`` maps them to rows of the
    caller's full database (None: the identity); ``max_norm`` is the largest row norm (it bounds
    the rounding error of the float32 products).
    """

    rows: F32
    index: I64 | None
    max_norm: float

    @classmethod
    def of(cls, refs: npt.ArrayLike, ref_mask: npt.ArrayLike | None = None, dim: int | None = None) -> Database:
        """Validate ``refs`` (``[R, d]``; NaN/inf refused) restricted to ``ref_mask``."""
        r = _as_2d(refs, "refs") if np.asarray(refs).size else np.zeros((0, dim or 0), np.float32)
        if dim is not None and r.shape[1] != dim:
            raise DescriptorError(f"query descriptors are {dim}-d but references are {r.shape[1]}-d")
        idx = _mask_index(ref_mask, r.shape[0])
        db = r if idx is None else r[idx]
        norms = _row_norms(db, "refs")
        return cls(db, idx, float(norms.max()) if len(norms) else 0.0)


def _queries(query: npt.ArrayLike) -> tuple[F32, F32]:
    q = _as_2d(query, "query")
    return q, _row_norms(q, "query")


def _mask_index(ref_mask: npt.ArrayLike | None, n_refs: int) -> I64 | None:
    if ref_mask is None:
        return None
    m = np.asarray(ref_mask)
    if m.dtype != np.bool_ or m.shape != (n_refs,):
        raise DescriptorError(f"ref_mask must be a boolean array of shape ({n_refs},), got {m.dtype} {m.shape}")
    idx: I64 = np.flatnonzero(m).astype(np.int64)
    return idx


def _candidates(sim: F32, k: int, margin: F32) -> tuple[I64, I64, F32]:
    """(row, column, value) of every entry of ``sim`` within ``margin[row]`` of its row's ``k``-th largest.

    ``k <= sim.shape[1]``; every row gets at least its ``k`` largest entries. With many
    columns, the maxima of groups of :data:`GROUP` columns are computed first: the ``k``-th
    largest group maximum is a lower bound of the ``k``-th largest entry (the ``k`` largest
    group maxima are ``k`` distinct entries), so only the groups whose maximum reaches that
    bound are looked at.
    """
    b, c = sim.shape
    ng = c // GROUP
    if ng >= 2 * k and ng >= 8:
        full = ng * GROUP
        groups = np.lib.stride_tricks.as_strided(  # [b, ng, GROUP] view of the first ng * GROUP columns
            sim, shape=(b, ng, GROUP), strides=(sim.strides[0], GROUP * sim.strides[1], sim.strides[1]),
            writeable=False)
        gmax = groups.max(axis=2)
        tail = sim[:, full:]
        allmax = np.concatenate([gmax, tail.max(axis=1, keepdims=True)], axis=1) if full < c else gmax
        low = np.partition(allmax, allmax.shape[1] - k, axis=1)[:, allmax.shape[1] - k] - margin
        gr, gg = np.nonzero(gmax >= low[:, None])
        hit_r, hit_j = np.nonzero(groups[gr, gg] >= low[gr][:, None])
        rows, cols = gr[hit_r], gg[hit_r] * GROUP + hit_j
        if full < c:
            tr, tc = np.nonzero(tail >= low[:, None])
            rows, cols = np.concatenate([rows, tr]), np.concatenate([cols, tc + full])
    else:
        low = np.partition(sim, c - k, axis=1)[:, c - k] - margin
        rows, cols = np.nonzero(sim >= low[:, None])
    return _near_kth(rows.astype(np.int64), cols.astype(np.int64), sim[rows, cols], k, margin)


def _near_kth(rows: I64, cols: I64, vals: F32, k: int, margin: F32) -> tuple[I64, I64, F32]:
    """The entries within ``margin[row]`` of their row's ``k``-th largest value (rows have >= k)."""
    order = np.lexsort((-vals, rows))  # by row, best first
    rows, cols, vals = rows[order], cols[order], vals[order]
    kth = vals[np.searchsorted(rows, np.arange(len(margin))) + k - 1]
    keep = vals >= (kth - margin)[rows]
    return rows[keep], cols[keep], vals[keep]


def _rescore(q: F32, db: F32, rows: I64, cols: I64) -> F64:
    """float64 dot product of query ``rows`` with database ``cols``, pair by pair."""
    out = np.empty(len(rows), dtype=np.float64)
    step = max(1, RESCORE_ELEMS // max(1, q.shape[1]))
    for s in range(0, len(rows), step):
        a = q[rows[s : s + step]].astype(np.float64)
        b = db[cols[s : s + step]].astype(np.float64)
        out[s : s + step] = np.einsum("ij,ij->i", a, b)
    return out


def _best(rows: I64, cols: I64, vals: F64, b: int, k: int) -> tuple[I64, F64]:
    """The ``k`` best (value desc, column asc) entries of each of ``b`` rows (each has >= k)."""
    order = np.lexsort((cols, -vals, rows))
    r, c, v = rows[order], cols[order], vals[order]
    take = np.searchsorted(r, np.arange(b))[:, None] + np.arange(k)[None, :]
    return c[take], v[take]


def _rounding_margin(dim: int, q_norms: F32, max_norm: float) -> F32:
    """Twice the worst-case rounding error of a float32 dot product of length ``dim``."""
    u = 2.0**-24
    gamma = (dim + 2) * u / (1 - (dim + 2) * u)
    bound = q_norms.astype(np.float64) * max_norm
    if bound.size and float(bound.max()) > LARGEST_NORM:
        raise DescriptorError(f"descriptor norms up to {float(bound.max()):.3g}: too large for float32 "
                              "similarities; descriptors should be L2-normalised")
    margin: F32 = (2.0 * 1.01 * gamma * bound).astype(np.float32)
    return margin


def _empty(n_query: int, k: int) -> tuple[I64, F32]:
    return np.full((n_query, k), -1, dtype=np.int64), np.full((n_query, k), -np.inf, dtype=np.float32)


def match(
    query: npt.ArrayLike,
    refs: npt.ArrayLike | Database,
    k: int = 10,
    ref_mask: npt.ArrayLike | None = None,
    *,
    block_rows: int | None = None,
) -> tuple[I64, F32]:
    """The ``k`` best references of each query: ``(indices [Q, k], similarities [Q, k])``.

    ``query`` is ``[Q, d]`` (or one ``[d]`` row), ``refs`` is ``[R, d]`` (or a
    :class:`Database` validated once for many calls); ``ref_mask`` (bool ``[R]``) restricts
    the database to the rows where it is True; returned indices are rows of the full
    ``refs``. ``block_rows`` (default :data:`QUERY_BLOCK`) sets the query rows per block; it
    changes speed and memory, never the result.
    """
    if k < 1:
        raise DescriptorError(f"k must be >= 1, got {k}")
    q, q_norms = _queries(query)
    if isinstance(refs, Database):
        if ref_mask is not None:
            raise DescriptorError("ref_mask applies to a matrix of references, not to a Database")
        db = refs
        if db.rows.shape[0] and db.rows.shape[1] != q.shape[1]:
            raise DescriptorError(f"query descriptors are {q.shape[1]}-d but references are {db.rows.shape[1]}-d")
    else:
        db = Database.of(refs, ref_mask, dim=q.shape[1])
    return _search(q, q_norms, db, k, block_rows)


def _search(q: F32, q_norms: F32, db: Database, k: int, block_rows: int | None) -> tuple[I64, F32]:
    """Top-``k`` search of validated ``q`` in ``db`` (see the module doc)."""
    indices, sims = _empty(q.shape[0], k)
    n_refs = db.rows.shape[0]
    if n_refs == 0 or q.shape[0] == 0:
        return indices, sims
    kk = min(k, n_refs)
    zero = q_norms == 0
    if zero.any():  # an all-zero query (a blank frame) ties with every map frame at 0: the first k
        first = np.arange(kk) if db.index is None else db.index[:kk]
        indices[np.flatnonzero(zero), :kk] = first
        sims[np.flatnonzero(zero), :kk] = 0.0
        if zero.all():
            return indices, sims
        rest = np.flatnonzero(~zero)
        sub_i, sub_s = _search(q[rest], q_norms[rest], db, k, block_rows)
        indices[rest], sims[rest] = sub_i, sub_s
        return indices, sims
    rows = max(1, block_rows or QUERY_BLOCK)
    tile = max(kk, MAX_BLOCK_ELEMS // min(rows, q.shape[0]))
    margin = _rounding_margin(q.shape[1], q_norms, db.max_norm)
    for start in range(0, q.shape[0], rows):
        qb = q[start : start + rows]
        b = qb.shape[0]
        mb = margin[start : start + b]
        parts = []
        for t0 in range(0, n_refs, tile):
            sim = qb @ db.rows[t0 : t0 + tile].T
            r, c, v = _candidates(sim, min(kk, sim.shape[1]), mb)
            parts.append((r, c + t0, v))
        r, c, v = parts[0]
        if len(parts) > 1:  # the union of the tiles' candidates, near the k-th of all of them
            r, c, v = _near_kth(np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts]),
                                np.concatenate([p[2] for p in parts]), kk, mb)
        best_i, best_v = _best(r, c, _rescore(qb, db.rows, r, c), b, kk)
        indices[start : start + b, :kk] = best_i if db.index is None else db.index[best_i]
        sims[start : start + b, :kk] = best_v
    return indices, sims


def topk(sim: npt.ArrayLike, k: int = 10, ref_mask: npt.ArrayLike | None = None) -> tuple[I64, F32]:
    """Like :func:`match` but on a precomputed similarity matrix ``sim [Q, R]`` (NaN = no match)."""
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
    sub = np.nan_to_num(sub, nan=-np.inf)
    r, c, v = _candidates(sub, kk, np.zeros(sub.shape[0], np.float32))
    bi, bs = _best(r, c, v.astype(np.float64), sub.shape[0], kk)
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
    """Time to match one query against the whole database (seconds).

    ``batched``: queries matched together as :func:`match` does (time per query of the
    batch), or one at a time (the latency of a single query).
    """

    seconds_per_query: float  # median over repeats of the mean time per query
    min_seconds_per_query: float
    n_refs: int
    dim: int
    n_queries: int
    repeats: int
    batched: bool = True

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict."""
        return asdict(self)


def time_per_query(
    query: npt.ArrayLike,
    refs: npt.ArrayLike | Database,
    repeats: int = 5,
    ref_mask: npt.ArrayLike | None = None,
    *,
    k: int = 1,
    max_queries: int = 100,
    batched: bool = True,
) -> QueryTiming:
    """Wall time of matching a query against all (masked) references.

    The first ``max_queries`` query rows are matched (top ``k``) all at once as :func:`match`
    does (``batched``; the time per query of that batch) or one at a time (the latency of one
    query). Inputs are validated once, outside the timing, and the database is gathered by
    ``ref_mask`` once beforehand, so the time is that of searching a database of the map's
    size. ``repeats`` passes; the median of the per-pass mean is reported.
    """
    if repeats < 1:
        raise DescriptorError("repeats must be >= 1")
    q, q_norms = _queries(query)
    q, q_norms = q[:max_queries], q_norms[:max_queries]
    if q.shape[0] == 0:
        raise DescriptorError("no query descriptors to time")
    if isinstance(refs, Database):
        db = refs
    else:
        db = Database.of(refs, ref_mask, dim=q.shape[1])
    groups = [(0, q.shape[0])] if batched else [(i, i + 1) for i in range(q.shape[0])]
    _search(q[:1], q_norms[:1], db, k, None)  # warm-up
    per_pass: list[float] = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for a, b in groups:
            _search(q[a:b], q_norms[a:b], db, k, None)
        per_pass.append((time.perf_counter() - t0) / q.shape[0])
    return QueryTiming(statistics.median(per_pass), min(per_pass), int(db.rows.shape[0]), int(q.shape[1]),
                       int(q.shape[0]), repeats, batched)

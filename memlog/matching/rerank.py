"""The patch re-rank: each query's best places ordered by the patch features along their paths, and the
ranking helper the drive HMM shares."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
import numpy.typing as npt

from memlog.descriptors.search import Database
from memlog.descriptors.table import DescriptorTable
from memlog.matching.config import F32, F64, I64, SequenceConfig, SequenceMatch
from memlog.matching.coordinates import _nearest
from memlog.matching.paths import _run_bounds, window_rows
from memlog.matching.sequences import _median_step, _ratio

__all__ = ["rerank_by_patches", "PairScores", "RERANK_PLACES", "RERANK_BLOCK"]



RERANK_BLOCK = 64  # query rows re-ranked per block (their pairs scored once each)
RERANK_PLACES = 20  # places per query the patch re-rank orders (the best of the descriptor match)


def _patch_plan(cfg: SequenceConfig, query: DescriptorTable, reference: DescriptorTable
                ) -> tuple[DescriptorTable, str | None]:
    """The query (its raw patches projected by the map's PCA) and why the patch re-rank does not
    run (None: it runs)."""
    if not cfg.rerank:
        return query, "turned off (--no-rerank)"
    if reference.patches is None or reference.patch_pca is None:
        return query, (f"the map stores no patch features ({reference.meta.kind} descriptors give none, or the map "
                       "was written before memlog stored them)")
    query = query.projected(reference.patch_pca)
    if query.patches is None:
        return query, "the query has no patch features in the map's PCA space (described with another descriptor " \
                      "or another map's PCA)"
    return query, None


class PairScores:
    """:func:`~memlog.descriptors.patches.pair_scores` of one query's patches against one map's, each
    pair computed once however often it is asked for (the whitening ensemble's members re-rank
    mostly the same pairs: :mod:`memlog.matching.ensemble`)."""

    def __init__(self, q_patches: npt.NDArray[Any], r_patches: npt.NDArray[Any]) -> None:
        self.q_patches = q_patches
        self.r_patches = r_patches
        self._width = max(1, len(r_patches))
        self._keys = np.zeros(0, np.int64)  # sorted (query row * width + map row)
        self._scores = np.zeros(0, np.int64)

    @classmethod
    def kept_in(cls, cache: dict[str, PairScores] | None, q_patches: npt.NDArray[Any], q_order: I64,
                r_patches: npt.NDArray[Any]) -> PairScores:
        """The pair scores of ``q_patches`` (rows taken in ``q_order``) against ``r_patches``, kept in
        ``cache`` across calls on the same two tables (made there on first use; new without one)."""
        if cache is not None and "pairs" in cache:
            return cache["pairs"]
        pairs = cls(q_patches[q_order], r_patches)
        if cache is not None:
            cache["pairs"] = pairs
        return pairs

    def __call__(self, q_rows: I64, r_rows: I64) -> I64:
        """The score of each pair ``(q_rows[n], r_rows[n])``."""
        from memlog.descriptors.patches import pair_scores

        key = np.asarray(q_rows, dtype=np.int64) * self._width + np.asarray(r_rows, dtype=np.int64)
        out = np.empty(len(key), dtype=np.int64)
        pos = np.minimum(np.searchsorted(self._keys, key), max(0, len(self._keys) - 1))
        known = self._keys[pos] == key if len(self._keys) else np.zeros(len(key), dtype=bool)
        out[known] = self._scores[pos[known]]
        new = ~known
        if new.any():
            out[new] = pair_scores(self.q_patches, self.r_patches, key[new] // self._width, key[new] % self._width)
            keys = np.concatenate([self._keys, key[new]])
            order = np.argsort(keys, kind="stable")
            self._keys, self._scores = keys[order], np.concatenate([self._scores, out[new]])[order]
        return out


def rerank_by_patches(res: SequenceMatch, q_desc: F32, r_desc: F32, q_patches: npt.NDArray[Any],
                      r_patches: npt.NDArray[Any], qc: F64, rc: F64, map_rows: I64, labels: I64,
                      cfg: SequenceConfig, k: int, unit: float, pairs: PairScores | None = None) -> SequenceMatch:
    """Re-rank each query's places by patch features (:mod:`memlog.descriptors.patches`).

    A place's patch score is the mean :func:`~memlog.descriptors.patches.pair_scores` of the
    window's query frames against the map frames aligned with them along the place's path (the
    query's best speed; a frame matched alone: itself against the place). The places are ranked
    by it (ties keep their order), the ``k`` best kept; ``margin`` and the confidence become the
    best patch score minus the best of another place (one scale for every row), ``ratio`` is
    taken to the new second place. ``rc``: every reference row's coordinate; ``map_rows``: the
    rows that make the map; ``labels``: the query's runs. ``pairs``: the pair scores of these same
    patches kept from an earlier re-rank (default: a new :class:`PairScores`).
    """
    score_pairs = pairs if pairs is not None else PairScores(q_patches, r_patches)
    n_q, n_c = res.indices.shape
    n_ref = max(1, len(rc))
    mr = map_rows[np.argsort(rc[map_rows], kind="stable")]
    mc = rc[mr]
    if not n_q or not len(mr):
        return res
    spacing = _median_step(mc)
    lo, hi = _run_bounds(labels, qc)
    length = int(res.info.get("length_used", cfg.length))
    offs = np.arange(-length, 1 if cfg.causal else length + 1, dtype=np.int64)
    cand = res.indices
    patch = np.full((n_q, n_c), np.nan)
    for a in range(0, n_q, RERANK_BLOCK):
        rows = np.arange(a, min(n_q, a + RERANK_BLOCK))
        t, inside = window_rows(rows, offs, lo, hi, False)
        valid = (inside & res.sequence[rows][:, None]) | (offs[None, :] == 0)
        t = np.where(valid, t, rows[:, None])
        c = cand[rows]
        v = np.where(res.sequence[rows], res.speed[rows], 0.0)
        pred = rc[np.maximum(c, 0)][:, :, None] + v[:, None, None] * (qc[t] - qc[rows][:, None])[:, None, :]
        near = mr[_nearest(mc, pred)]
        use = (valid[:, None, :] & (c >= 0)[:, :, None] & (pred >= mc[0] - spacing / 2)
               & (pred <= mc[-1] + spacing / 2))
        tq = np.broadcast_to(t[:, None, :], pred.shape)[use]
        key = tq * n_ref + near[use]
        uk, inv = np.unique(key, return_inverse=True)
        total = np.zeros(pred.shape)
        total[use] = score_pairs(uk // n_ref, uk % n_ref)[inv]
        count = use.sum(axis=2)
        patch[rows] = np.where(c >= 0, total.sum(axis=2) / np.maximum(count, 1), np.nan)
    res = replace(res, rerank=patch, info={**res.info, "patch_rerank": n_c})  # the places re-ranked
    return _ranked_by(res, np.where(cand >= 0, np.nan_to_num(patch, nan=0.0), -np.inf), q_desc, r_desc, rc,
                      cfg.exclude * unit, nan_without_second=True).top(min(k, n_c))


def _ranked_by(res: SequenceMatch, key: F64, q_desc: F32, r_desc: F32, rc: F64, excl: float,
               nan_without_second: bool = False) -> SequenceMatch:
    """``res`` with each row's places ordered by ``key`` ``[Q, K]`` (highest first, ties in their
    order; -inf: no place), the margin the best key minus the best of another place (outside
    ``excl`` coordinate units; NaN, or the best key alone with ``nan_without_second`` false, when
    there is none) and Lowe's ratio taken to that place."""
    n_q = res.indices.shape[0]
    order = np.argsort(-key, axis=1, kind="stable")
    idx = np.take_along_axis(res.indices, order, axis=1)
    ks = np.take_along_axis(key, order, axis=1)
    other = (idx[:, 1:] >= 0) & (np.abs(rc[np.maximum(idx[:, 1:], 0)] - rc[np.maximum(idx[:, :1], 0)]) > excl)
    has = other.any(axis=1)
    col = np.where(has, np.argmax(other, axis=1) + 1, 0)
    rows_q = np.arange(n_q)
    alone = np.full(n_q, np.nan) if nan_without_second else np.zeros(n_q)
    margin = np.where(idx[:, 0] >= 0, np.where(has, ks[:, 0] - ks[rows_q, col], alone + ks[:, 0]), np.nan)
    second = np.where(has, idx[rows_q, col], -1)
    ratio = _ratio(q_desc, Database.of(r_desc), idx[:, 0], second, np.arange(len(r_desc), dtype=np.int64))

    def by(a: F64 | None) -> F64 | None:
        return None if a is None else np.take_along_axis(a, order, axis=1)

    return replace(res, indices=idx, scores=np.take_along_axis(res.scores, order, axis=1),
                   similarities=np.take_along_axis(res.similarities, order, axis=1), margin=margin, ratio=ratio,
                   rerank=by(res.rerank), posterior=by(res.posterior))

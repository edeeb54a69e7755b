"""The whitening ensemble: a small map's drive matched in several whitened dimensions, and one
drive HMM deciding between every member's places.

**Why.** A map's whitening is fitted on the map's own kept frames (:mod:`memlog.descriptors.whitening`).
On a map of a few dozen to a few hundred frames that fit is a noisy estimate, and the places the
descriptor stage proposes, with the speeds and centres of their paths, move with it; the patch
re-rank and the drive HMM then decide between different candidates. On the Stromovka drive pair
(``docs/defaults.md``, "Drives as cameras record them"), refitting the full map's whitening on a
random 85 % of its own frames gave R@1 from 0.46 to 0.82, its half map's from 0.52 to 0.88: a map
and its half, whitened on different frames, landed at different points of that spread, which is how
a denser map could localize worse than its half. Pooling the places several whitenings propose
(bagging) narrows the spread and raises the mean.

**How.** The stored whitening's columns are its principal directions in order of variance, so the
first ``d`` columns of a whitened descriptor, renormalised, are the descriptor whitened to ``d``
dimensions (:func:`leading`): the members cost no storage and the query is described and whitened
once. The matcher (:func:`memlog.matching.match_tables`) runs the descriptor stage and the patch
re-rank once per dimension of :func:`ensemble_dims` (the whitening's :data:`FRACTIONS` of its
dimensions); :func:`union` pools every member's places, each scored by its mean re-rank score over
the members that proposed it, and the drive HMM decides between them once: one most likely path
through the pooled places, not an average of paths. (Averaging each member's HMM probabilities, the
first version, let a frame's decision mix members that disagreed on the path: a stop between two
places could land on neither; ``docs/defaults.md`` has both.)

**When.** Only where the drive HMM decides (a map with patch features), the map is whitened, its
whitening was fitted on fewer than :data:`BELOW` frames (each member runs the descriptor stage and
the re-rank, sharing the re-rank's pair scores; a larger fit is a steadier estimate), and the search
is exact. ``--no-ensemble`` turns it off; ``info["ensemble"]`` records the dimensions, or why it
did not run.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from memlog.descriptors.base import l2_normalize
from memlog.descriptors.search import _rescore
from memlog.descriptors.whitening import Whitening
from memlog.matching.config import F32, F64, SequenceMatch

__all__ = ["FRACTIONS", "BELOW", "MIN_DIM", "ensemble_dims", "leading", "union"]

FRACTIONS = (1.0, 0.8, 0.6, 0.4)  # the whitened dimensions matched, as fractions of the map's
BELOW = 1024  # maps whose whitening was fitted on fewer frames get the ensemble
MIN_DIM = 8  # no member has fewer dimensions


def ensemble_dims(whitening: Whitening) -> list[int]:
    """The whitened dimensions of the ensemble's members, the whole whitening first (distinct,
    at least :data:`MIN_DIM` each)."""
    dims: list[int] = []
    for f in FRACTIONS:
        d = max(MIN_DIM, int(round(whitening.dim_out * f)))
        if d <= whitening.dim_out and d not in dims:
            dims.append(d)
    return dims


def leading(desc: F32, d: int) -> F32:
    """Whitened descriptors ``[N, D]`` cut to their ``d`` leading dimensions and renormalised (a
    blank row stays zero): the same frames whitened to ``d`` dimensions."""
    return l2_normalize(np.asarray(desc)[:, :d])


def union(runs: list[SequenceMatch], q_desc: F32, r_desc: F32) -> SequenceMatch:
    """One result from the members' re-ranked places (query rows in the same order), for the drive
    HMM to decide between once: each row's places are those the members proposed, each with its
    re-rank score averaged over the members that proposed it (each member scores a place along the
    path its own descriptors found). At most as many places as a member has columns are kept, the
    highest re-rank score summed over the members first (a place that more members proposed
    tends to come first). A place's descriptor score comes from the first member that proposed it,
    the whole whitening first; its similarity is the query frame's to it in the whole whitening
    (``q_desc``, ``r_desc``: the whitened query rows and map rows); the rows' own fields (speed,
    window, fallback) come from the whole whitening."""
    main = runs[0]
    n_q, n_c = main.indices.shape
    idx = np.concatenate([r.indices for r in runs], axis=1)
    assert all(r.rerank is not None for r in runs)
    rr = np.concatenate([np.nan_to_num(np.asarray(r.rerank), nan=0.0) for r in runs], axis=1)
    scores = np.concatenate([r.scores for r in runs], axis=1)
    rows = np.broadcast_to(np.arange(n_q)[:, None], idx.shape)
    ok = idx >= 0
    width = int(idx.max()) + 2 if ok.any() else 1
    key = rows[ok].astype(np.int64) * width + idx[ok]
    # np.unique's first index is the earliest in row-major order: the first member proposing the place
    uk, first, inv = np.unique(key, return_index=True, return_inverse=True)
    total: F64 = np.bincount(inv, weights=rr[ok], minlength=len(uk)).astype(np.float64)
    mean = total / np.bincount(inv, minlength=len(uk))
    u_row, u_idx = uk // width, uk % width
    order = np.lexsort((-total, u_row))  # by row, then the highest summed score first
    u_row, u_idx, mean, first = u_row[order], u_idx[order], mean[order], first[order]
    rank = np.arange(len(u_row)) - np.searchsorted(u_row, u_row)
    keep = rank < n_c
    r_, c_ = u_row[keep], rank[keep]
    src = np.flatnonzero(ok)[first[keep]]  # flat position of each kept place's source column
    out_idx = np.full((n_q, n_c), -1, dtype=np.int64)
    out_idx[r_, c_] = u_idx[keep]
    out_rr = np.full((n_q, n_c), np.nan)
    out_rr[r_, c_] = mean[keep]
    out_scores = np.full((n_q, n_c), -np.inf)
    out_scores[r_, c_] = scores.reshape(-1)[src]
    sims = np.full((n_q, n_c), -np.inf, dtype=np.float32)
    sims[r_, c_] = _rescore(q_desc, r_desc, r_.astype(np.int64), u_idx[keep].astype(np.int64)).astype(np.float32)
    return replace(main, indices=out_idx, scores=out_scores, similarities=sims, rerank=out_rr, posterior=None)

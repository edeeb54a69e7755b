"""Baselines of the same size as a selection: uniform subsampling and random subsets.

Uniform: the K row indices ``np.rint(np.linspace(0, N - 1, K))`` (round half to even),
which include the first and, for K >= 2, the last frame; for K <= N consecutive
linspace points are >= 1 apart, so the rounded indices are K distinct rows.
Every k-th frame from other start offsets (:func:`phase_masks`): the uniform rows shifted by each of
``0 .. ceil(s) - 1`` frames (``s = (N - 1) / (K - 1)`` the spacing; with ``P`` offsets asked for, by
``rint(j * s / P)``, ``j = 0 .. P - 1``), a row shifted past the last frame wrapping to the first ones:
shift 0 is the uniform baseline, and a map of every other frame has two phases (the even frames and the
odd ones).
One every-k-th map is one draw of where its frames fall, and which phase holds the one frame a stop
needs can decide it.
Random: ``np.random.default_rng(seed).choice(N, K, replace=False)``, sorted, so a seed
always gives the same subset (for a given numpy version's PCG64 stream).
"""

from __future__ import annotations

import numbers
from collections.abc import Iterable
from typing import Any

import numpy as np
from numpy.typing import NDArray

from memlog.errors import ConfigError
from memlog.selection.coordinates import bin_along
from memlog.selection.table import ScoreTable, Selection

__all__ = [
    "uniform_indices",
    "uniform_mask",
    "phase_masks",
    "random_indices",
    "random_mask",
    "random_masks",
    "baseline_selection",
    "distance_uniform_mask",
]


def _check(n: Any, k: Any) -> tuple[int, int]:
    for name, v in (("n", n), ("k", k)):
        if isinstance(v, bool) or not isinstance(v, numbers.Integral) or v < 0:
            raise ConfigError(f"baseline {name} must be an integer >= 0, got {v!r}")
    if k > n:
        raise ConfigError(f"cannot pick k={k} frames out of n={n}")
    return int(n), int(k)


def uniform_indices(n: int, k: int) -> NDArray[np.int64]:
    """K evenly spaced row indices in [0, N-1]: ``np.rint(np.linspace(0, N-1, K))``."""
    n, k = _check(n, k)
    if k == 0:
        return np.zeros(0, dtype=np.int64)
    return np.rint(np.linspace(0, n - 1, k)).astype(np.int64)


def _mask(n: int, rows: NDArray[np.int64]) -> NDArray[np.bool_]:
    m = np.zeros(n, dtype=bool)
    m[rows] = True
    return m


def uniform_mask(n: int, k: int) -> NDArray[np.bool_]:
    """Bool mask of :func:`uniform_indices`."""
    return _mask(int(n), uniform_indices(n, k))




def phase_masks(n: int, k: int, phases: int | None = None) -> NDArray[np.bool_]:
    """Every k-th frame from evenly spaced start offsets (module doc), bool ``[P', N]``: the
    first is :func:`uniform_mask`, each has K rows, no two are the same (``P' <= phases``; None:
    every offset, as many as the spacing)."""
    n, k = _check(n, k)
    if phases is not None and (isinstance(phases, bool) or not isinstance(phases, numbers.Integral) or phases < 1):
        raise ConfigError(f"phases must be an integer >= 1, got {phases!r}")
    base = uniform_indices(n, k)
    if k < 2:  # (k == n: a spacing of 1, one offset below)
        return _mask(n, base)[None, :]
    s = (n - 1) / (k - 1)
    every = int(np.ceil(s - 1e-9))  # the offsets 0 .. every - 1 (each < s: the rows stay distinct)
    p = every if phases is None else min(int(phases), every)
    shifts = dict.fromkeys(int(np.rint(j * s / p)) if p < every else j for j in range(p))  # distinct, 0 first
    return np.stack([_mask(n, (base + d) % n) for d in shifts])  # (a shift < s < n: the rows stay distinct)


def distance_uniform_mask(positions: Any, k: int) -> NDArray[np.bool_] | None:
    """Frames evenly spaced along the travelled distance (``positions`` [N, 2|3] metres, NaN rows
    unknown: they carry the last known distance): the distance is cut as a map of K frames is cut
    by distance (:func:`~memlog.selection.coordinates.count_cut`: equal parts of which K hold a
    frame, so a fast stretch whose frames are further apart than a part does not shrink the map),
    and each part that holds a frame keeps the one nearest its middle (ties, and a stop's frames
    at one distance: the earlier). K frames, fewer only where the drive has fewer distinct places;
    where one more part gains several, the parts' frames are thinned evenly to K. None when there
    is no travelled distance."""
    pos = np.asarray(positions, dtype=np.float64)
    n, k = _check(len(pos), k)
    rows = np.flatnonzero(np.all(np.isfinite(pos), axis=1))
    if rows.size < 2 or k == 0:
        return None
    s_known = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pos[rows], axis=0), axis=1))])
    if s_known[-1] <= 0:
        return None
    where = np.searchsorted(rows, np.arange(n), side="right") - 1
    s = np.where(where >= 0, s_known[np.clip(where, 0, None)], 0.0)  # non-decreasing
    part, width = bin_along(s, None, k)
    starts = np.flatnonzero(np.diff(part, prepend=-1))  # each held part's first row
    ends = np.append(starts[1:], n)
    keep = np.empty(len(starts), dtype=np.int64)
    for j, (a, b) in enumerate(zip(starts, ends)):
        middle = (part[a] + 0.5) * width
        keep[j] = a + int(np.argmin(np.abs(s[a:b] - middle)))  # the first of the nearest
    if len(keep) > k:
        keep = keep[uniform_indices(len(keep), k)]
    return _mask(n, keep)


def random_indices(n: int, k: int, seed: int) -> NDArray[np.int64]:
    """K distinct row indices drawn uniformly without replacement with ``seed``, sorted."""
    n, k = _check(n, k)
    rng = np.random.default_rng(seed)
    return np.sort(rng.choice(n, size=k, replace=False)).astype(np.int64)


def random_mask(n: int, k: int, seed: int) -> NDArray[np.bool_]:
    """Bool mask of :func:`random_indices`."""
    return _mask(int(n), random_indices(n, k, seed))


def random_masks(n: int, k: int, seeds: Iterable[int] = range(20)) -> NDArray[np.bool_]:
    """Stack of :func:`random_mask` for each seed: bool[len(seeds), N]."""
    masks = [random_mask(n, k, s) for s in seeds]
    if not masks:
        return np.zeros((0, int(n)), dtype=bool)
    return np.stack(masks)


def baseline_selection(table: ScoreTable, k: int, seed: int | None = None) -> Selection:
    """Uniform (``seed=None``) or seeded random selection of ``k`` frames of ``table``;
    the others have reason "not-sampled"."""
    n = table.n
    keep = uniform_mask(n, k) if seed is None else random_mask(n, k, seed)
    return Selection(
        mode="uniform" if seed is None else "random",
        index=table.index,
        keep=keep,
        reason=[None if x else "not-sampled" for x in keep.tolist()],
        info={"k": int(k), "seed": seed},
    )

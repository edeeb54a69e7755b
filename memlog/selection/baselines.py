"""Baselines of the same size as a selection: uniform subsampling and random subsets.

Uniform: the K row indices ``np.rint(np.linspace(0, N - 1, K))`` (round half to even),
which include the first and, for K >= 2, the last frame; for K <= N consecutive
linspace points are >= 1 apart, so the rounded indices are K distinct rows.
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
from memlog.selection.table import ScoreTable, Selection

__all__ = [
    "uniform_indices",
    "uniform_mask",
    "random_indices",
    "random_mask",
    "random_masks",
    "baseline_selection",
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

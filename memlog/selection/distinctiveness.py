"""Distinctiveness: a fourth criterion, computed from the reference drive alone.

A frame makes a good map entry when a query taken at its place retrieves it, and a poor one
when it looks like other parts of the drive (it then attracts queries from those places: the
wrong matches the paper's thesis is about). With L2-normalised (whitened) descriptors ``d``
of the drive's frames in log order:

* ``near_i`` = mean cosine similarity of frame i to the frames within ``window`` rows of it
  (its own place: how well its neighbours, hence a query there, retrieve it);
* ``far_i`` = largest cosine similarity of frame i to any frame more than ``exclusion`` rows
  away (how strongly it is aliased to a distant part of the drive);
* ``margin_i = near_i - far_i`` and the criterion ``DS_i`` = the percentile rank of
  ``margin_i`` within the drive (mid-rank of ties, in (0, 1); like MS/SS/ES, higher is better).

Frames whose descriptor is unknown (NaN) get NaN. The ranking makes DS scale-free (it does not
depend on the descriptor's similarity range), so it combines with MS/SS/ES in segment mode
(``distinct_weight``) and thresholds in paper mode (``dt``: keep DS >= dt, i.e. drop the
``dt`` share of the most aliased frames). Cost: one pass of ``N x N`` similarities in blocks
of rows, O(N^2 d), bounded memory.

Defaults (``window = 2``, ``exclusion = 10`` rows) were chosen on the Nordland slice, where one
row is one place (~10 source frames apart) and the truth tolerance is +-1 row; for other drives
give them in frames of that drive.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from memlog.errors import ConfigError, SelectionError
from memlog.selection._checks import positive_int
from memlog.selection.segment import percentile_ranks

__all__ = ["DistinctConfig", "distinctiveness", "margins"]


@dataclass(frozen=True)
class DistinctConfig:
    """Rows counted as the frame's own place (``window``) and rows beyond which another frame is
    a distant part of the drive (``exclusion`` > ``window``); ``block_rows`` bounds memory."""

    window: int = 2
    exclusion: int = 10
    block_rows: int = 1024

    def __post_init__(self) -> None:
        positive_int("distinct window", self.window)
        positive_int("distinct exclusion", self.exclusion)
        positive_int("block_rows", self.block_rows)
        if self.exclusion <= self.window:
            raise ConfigError(f"distinct exclusion ({self.exclusion}) must be larger than the window ({self.window})")

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def margins(descriptors: ArrayLike, config: DistinctConfig | None = None) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``(near, far)`` per row (see the module docstring); NaN where undefined."""
    cfg = config or DistinctConfig()
    d = np.asarray(descriptors, dtype=np.float32)
    if d.ndim != 2:
        raise SelectionError(f"descriptors must be [N, d], got shape {d.shape}")
    n = d.shape[0]
    ok = np.all(np.isfinite(d), axis=1)
    dz = np.where(ok[:, None], d, 0.0).astype(np.float32)
    near = np.full(n, np.nan)
    far = np.full(n, np.nan)
    cols = np.arange(n)
    for start in range(0, n, cfg.block_rows):
        rows = np.arange(start, min(n, start + cfg.block_rows))
        sim = (dz[rows] @ dz.T).astype(np.float64)
        sim[:, ~ok] = np.nan
        gap = np.abs(rows[:, None] - cols[None, :])
        own = (gap >= 1) & (gap <= cfg.window)
        distant = gap > cfg.exclusion
        with np.errstate(invalid="ignore"):
            s_own = np.where(own, sim, np.nan)
            cnt = np.sum(np.isfinite(s_own), axis=1)
            near[rows] = np.where(cnt > 0, np.nansum(s_own, axis=1) / np.maximum(cnt, 1), np.nan)
            s_far = np.where(distant & np.isfinite(sim), sim, -np.inf)
            best = s_far.max(axis=1) if n else np.zeros(0)
            far[rows] = np.where(np.isfinite(best), best, np.nan)
    near[~ok] = np.nan
    far[~ok] = np.nan
    return near, far


def distinctiveness(descriptors: ArrayLike, config: DistinctConfig | None = None) -> NDArray[np.float64]:
    """The criterion DS per row: percentile rank (in (0, 1)) of ``near - far``; NaN where unknown.

    A frame with no distant frame (a drive shorter than the exclusion) has ``far`` undefined and
    counts as not aliased (margin = near); with no neighbour either, DS is NaN.
    """
    near, far = margins(descriptors, config)
    return percentile_ranks(near - np.where(np.isfinite(far), far, 0.0))

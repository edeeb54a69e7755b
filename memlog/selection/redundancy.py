"""Drop kept frames that repeat an earlier kept frame (loops, stops, revisits).

Kept frames are visited in table (log-time) order; a frame is a near-duplicate when it
matches ANY frame kept before it (not just the last one, so returning to a place is
caught). Matching uses every active condition (a condition is active when its setting
is not None):

* descriptors: cosine distance ``1 - <d_i, d_j>`` < ``dup_distance``;
* positions: Euclidean distance <= ``dup_radius_m``.

With both active a duplicate must look alike AND be nearby (guards against perceptual
aliasing). A frame whose descriptor/position is unknown never matches on that condition.
A duplicate is attributed to the most similar matching kept frame (smallest descriptor
distance, else smallest position distance; ties to the earliest). Duplicates are not
added to the kept set. Cost is O(N*K*d) for K kept frames: candidates go in blocks of
up to 256 rows, matched by float32 matrix products against a growing matrix of kept
descriptors (in column chunks so one block has at most ``block_elements`` entries), then
resolved in order within the block.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from memlog.errors import ConfigError, SelectionError
from memlog.selection._checks import finite_number, positive_int, positive_number
from memlog.selection.table import ScoreTable, Selection

__all__ = ["RedundancyConfig", "Duplicates", "find_duplicates", "drop_duplicates"]


@dataclass(frozen=True)
class RedundancyConfig:
    """Duplicate conditions (None = inactive; at least one active) and the work budget
    (``block_elements``: max entries of one candidate-by-kept distance block)."""

    dup_distance: float | None = 0.1
    dup_radius_m: float | None = None
    block_elements: int = 1 << 22

    def __post_init__(self) -> None:
        if self.dup_distance is None and self.dup_radius_m is None:
            raise ConfigError("redundancy needs dup_distance or dup_radius_m (both are None)")
        if self.dup_distance is not None:
            v = finite_number("dup_distance", self.dup_distance)
            if not 0.0 < v <= 2.0:
                raise ConfigError(f"dup_distance must be in (0, 2], got {self.dup_distance!r}")
        if self.dup_radius_m is not None:
            positive_number("dup_radius_m", self.dup_radius_m)
        positive_int("block_elements", self.block_elements)

    def to_dict(self) -> dict[str, Any]:
        """Settings as a plain dict."""
        return asdict(self)


@dataclass(eq=False)
class Duplicates:
    """Result of :func:`find_duplicates`, per table row.

    ``keep``: the filtered mask; ``duplicate_of``: row of the kept frame a dropped frame
    repeats (-1 otherwise); ``distance``: its descriptor distance (or position distance
    when descriptors are not used; NaN otherwise).
    """

    keep: NDArray[np.bool_]
    duplicate_of: NDArray[np.int64]
    distance: NDArray[np.float64]

    @property
    def dropped_rows(self) -> NDArray[np.int64]:
        """Rows dropped as duplicates."""
        return np.flatnonzero(self.duplicate_of >= 0).astype(np.int64)


def _pos_sqdist(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """Pairwise squared Euclidean distances [len(a), len(b)] (NaN rows give NaN)."""
    sq = np.zeros((a.shape[0], b.shape[0]))
    for k in range(a.shape[1]):
        sq += (a[:, k, None] - b[None, :, k]) ** 2
    return sq


class _KeptFrames:
    """The candidates' descriptors and positions and the growing set of kept frames they are
    matched against (rows of the kept arrays in keeping order), for :func:`find_duplicates`."""

    def __init__(self, table: ScoreTable, cand: NDArray[np.intp], cfg: RedundancyConfig) -> None:
        m = cand.size
        self.use_d = cfg.dup_distance is not None
        self.use_p = cfg.dup_radius_m is not None
        self.dd = float(cfg.dup_distance) if cfg.dup_distance is not None else 0.0
        self.rr = float(cfg.dup_radius_m) if cfg.dup_radius_m is not None else 0.0
        # (inactive conditions get empty columns: they are never read)
        self.dsc = np.zeros((m, 0), dtype=np.float32)
        self.d_ok = np.zeros(m, dtype=bool)
        self.kept_d = np.zeros((m, 0), dtype=np.float32)
        self.kept_dok = np.zeros(m, dtype=bool)
        self.pos = np.zeros((m, 0), dtype=np.float64)
        self.p_ok = np.zeros(m, dtype=bool)
        self.kept_p = np.zeros((m, 0), dtype=np.float64)
        self.kept_pok = np.zeros(m, dtype=bool)
        if self.use_d:
            assert table.descriptors is not None
            dsc = table.descriptors[cand]
            self.d_ok = np.all(np.isfinite(dsc), axis=1)
            self.dsc = np.where(self.d_ok[:, None], dsc, 0.0).astype(np.float32)
            self.kept_d = np.empty((m, self.dsc.shape[1]), dtype=np.float32)
        if self.use_p:
            assert table.positions is not None
            self.pos = table.positions[cand]
            self.p_ok = np.all(np.isfinite(self.pos), axis=1)
            self.kept_p = np.empty((m, self.pos.shape[1]), dtype=np.float64)
        self.kept_rows = np.empty(m, dtype=np.int64)  # table rows of kept frames
        self.n_kept = 0

    def cost(self, rows: slice, ref: slice, kept: bool) -> NDArray[np.float32]:
        """Ranking cost of candidates ``rows`` against reference frames ``ref`` (rows of the
        kept arrays if ``kept``, else candidate rows): descriptor distance, else position
        distance (squared); +inf where a pair does not match every active condition."""
        out: NDArray[np.float32] | None = None
        if self.use_d:
            rd, rok = (self.kept_d[ref], self.kept_dok[ref]) if kept else (self.dsc[ref], self.d_ok[ref])
            dist = np.float32(1.0) - self.dsc[rows] @ rd.T
            bad = ~((dist < self.dd) & self.d_ok[rows][:, None] & rok[None, :])
            dist[bad] = np.inf
            out = dist
        if self.use_p:
            rp, rok = (self.kept_p[ref], self.kept_pok[ref]) if kept else (self.pos[ref], self.p_ok[ref])
            pd = _pos_sqdist(self.pos[rows], rp)
            with np.errstate(invalid="ignore"):
                bad = ~((pd <= self.rr * self.rr) & self.p_ok[rows][:, None] & rok[None, :])
            if out is None:
                pd[bad] = np.inf
                out = pd.astype(np.float32)
            else:
                out[bad] = np.inf
        assert out is not None
        return out

    def best_kept(self, blk: slice, chunk: int) -> tuple[NDArray[np.int64], NDArray[np.float32]]:
        """Each candidate of ``blk``'s best match among the frames kept so far (row of the kept
        arrays, -1: none) and its cost, ``chunk`` kept frames at a time."""
        rows_b = np.arange(blk.stop - blk.start)
        best_old = np.full(blk.stop - blk.start, -1, dtype=np.int64)
        best_old_v = np.full(blk.stop - blk.start, np.inf, dtype=np.float32)
        for k0 in range(0, self.n_kept, chunk):
            k1 = min(self.n_kept, k0 + chunk)
            c = self.cost(blk, slice(k0, k1), True)
            arg = np.argmin(c, axis=1)
            val = c[rows_b, arg]
            better = val < best_old_v  # strict: ties stay with the earlier kept frame
            best_old[better] = arg[better] + k0
            best_old_v[better] = val[better]
        return best_old, best_old_v

    def keep(self, new: NDArray[np.int64], cand: NDArray[np.intp]) -> None:
        """Add the candidates ``new`` (candidate rows, in order) to the kept frames."""
        k_new = self.n_kept + new.size
        self.kept_rows[self.n_kept:k_new] = cand[new]
        if self.use_d:
            self.kept_d[self.n_kept:k_new] = self.dsc[new]
            self.kept_dok[self.n_kept:k_new] = self.d_ok[new]
        if self.use_p:
            self.kept_p[self.n_kept:k_new] = self.pos[new]
            self.kept_pok[self.n_kept:k_new] = self.p_ok[new]
        self.n_kept = k_new


def _check_inputs(table: ScoreTable, mask: NDArray[Any], cfg: RedundancyConfig) -> None:
    """Raise when ``mask`` is no bool mask of the table's rows or an active condition lacks its column."""
    n = table.n
    if mask.dtype != bool or mask.shape != (n,):
        raise SelectionError(f"keep must be a bool mask of shape ({n},), got {mask.dtype} {mask.shape}")
    if cfg.dup_distance is not None and table.descriptors is None:
        raise ConfigError("dup_distance needs descriptors, but the score table has none")
    if cfg.dup_radius_m is not None and table.positions is None:
        raise ConfigError("dup_radius_m needs positions, but the score table has none")


def find_duplicates(
    table: ScoreTable, keep: ArrayLike, config: RedundancyConfig | None = None
) -> Duplicates:
    """Filter ``keep`` (bool[N]) so no kept frame near-duplicates an earlier kept frame."""
    cfg = config if config is not None else RedundancyConfig()
    mask = np.asarray(keep)
    _check_inputs(table, mask, cfg)
    n = table.n
    cand = np.flatnonzero(mask)
    m = cand.size
    out_keep = mask.copy()
    dup_of = np.full(n, -1, dtype=np.int64)
    dist_out = np.full(n, np.nan)
    if m == 0:
        return Duplicates(out_keep, dup_of, dist_out)

    kept = _KeptFrames(table, cand, cfg)
    b = int(min(256, max(16, math.isqrt(cfg.block_elements))))  # candidates per block
    chunk = max(1, cfg.block_elements // b)  # kept frames per distance block
    start = 0
    while start < m:
        stop = min(m, start + b)
        blk = slice(start, stop)
        # best match among the frames kept before this block, chunk by chunk
        best_old, best_old_v = kept.best_kept(blk, chunk)
        # within the block, sequentially (later frames may duplicate earlier block frames)
        c_in = kept.cost(blk, blk, False)  # column j set to inf once frame j is a duplicate
        new_in_block: list[int] = []
        for j in range(stop - start):
            ci = int(cand[start + j])
            bv = float(best_old_v[j])
            bref = int(kept.kept_rows[best_old[j]]) if best_old[j] >= 0 else -1
            if j:
                k = int(c_in[j, :j].argmin())
                if c_in[j, k] < bv:
                    bv, bref = float(c_in[j, k]), int(cand[start + k])
            if bref >= 0:
                out_keep[ci] = False
                dup_of[ci] = bref
                dist_out[ci] = bv
                c_in[j + 1 :, j] = np.inf
            else:
                new_in_block.append(j)
        kept.keep(np.asarray(new_in_block, dtype=np.int64) + start, cand)
        start = stop
    if not kept.use_d:
        dist_out = np.sqrt(dist_out)
    return Duplicates(out_keep, dup_of, dist_out)


def drop_duplicates(
    table: ScoreTable, selection: Selection, config: RedundancyConfig | None = None
) -> Selection:
    """A copy of ``selection`` with near-duplicate kept frames dropped (reason
    "duplicate"; ``duplicates`` maps their frame index to the kept frame index)."""
    cfg = config if config is not None else RedundancyConfig()
    if selection.n_frames != table.n or not np.array_equal(selection.index, table.index):
        raise SelectionError("selection and score table cover different frames")
    res = find_duplicates(table, selection.keep, cfg)
    reasons = list(selection.reason)
    duplicates = dict(selection.duplicates)
    for r in res.dropped_rows.tolist():
        reasons[r] = "duplicate"
        duplicates[int(table.index[r])] = int(table.index[res.duplicate_of[r]])
    info = dict(selection.info)
    info["dedup"] = {**cfg.to_dict(), "n_dropped": int(res.dropped_rows.size)}
    return Selection(
        mode=selection.mode,
        index=selection.index,
        keep=res.keep,
        reason=reasons,
        thresholds=dict(selection.thresholds),
        gaps=list(selection.gaps),
        duplicates=duplicates,
        info=info,
        segment_id=selection.segment_id,
    )

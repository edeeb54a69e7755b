"""Path scoring: the contrast-normalised similarities of a window's query frames to the map frames
along a path, for the constant-speed paths (SeqSLAM) and the dynamic-programming ones."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from memlog.descriptors.search import Database
from memlog.matching.config import BoolArray, CENTRE_STEPS, F32, F64, I64, MAX_SPEEDS, PAIR_ELEMS, RESCORE_SPEEDS, SCORE_ELEMS, STAT_SAMPLE, SequenceConfig
from memlog.matching.coordinates import _nearest

__all__: list[str] = []



def _stats(q: F32, db: Database) -> tuple[F64, F64]:
    """Mean and standard deviation of each query's similarities to a fixed sample of map rows
    (float64, one query at a time: no dependence on how many queries are given)."""
    n = q.shape[0]
    if db.rows.shape[0] < 2:
        return np.zeros(n), np.ones(n)
    sample = np.unique(np.linspace(0, db.rows.shape[0] - 1, min(STAT_SAMPLE, db.rows.shape[0])).astype(np.int64))
    s = db.rows[sample].astype(np.float64)
    mu = np.empty(n)
    sd = np.empty(n)
    step = 256
    for a in range(0, n, step):
        sims = np.einsum("qd,sd->qs", q[a : a + step].astype(np.float64), s)
        mu[a : a + step] = sims.mean(axis=1)
        sd[a : a + step] = sims.std(axis=1)
    sd = np.where(sd > 1e-12, sd, np.inf)  # a blank frame (all similarities equal) scores 0 everywhere
    return mu, sd


@dataclass
class _Problem:
    """Everything the matcher needs, validated: queries, the (masked) map sorted by coordinate."""

    q: F32
    qc: F64
    run_lo: I64  # first row of each query's run
    run_hi: I64  # one past its last row
    rows: F32  # map descriptors in coordinate order
    rc: F64  # map coordinates, sorted
    full_row: I64  # reference row of each sorted map row
    mu: F64
    sd: F64
    unit: float
    spacing: float  # median spacing of consecutive map coordinates
    excl: float  # exclusion half-width in coordinate units
    speeds: F64
    cfg: SequenceConfig
    pace: float  # the speed of a drive at the map's own pace (the speed prior's centre)

    def prior(self, v: F64) -> F64:
        """What the speed prior takes off a path's score at speeds ``v``: ``speed_prior`` per
        doubling or halving against :attr:`pace`."""
        if self.cfg.speed_prior <= 0:
            return np.zeros(np.shape(v))
        with np.errstate(divide="ignore"):
            out: F64 = self.cfg.speed_prior * np.abs(np.log2(np.asarray(v, dtype=np.float64) / self.pace))
        return out


def _run_bounds(labels: I64, qc: F64) -> tuple[I64, I64]:
    """First and one-past-last row of each row's run: consecutive rows with equal labels and
    non-decreasing coordinates."""
    n = len(labels)
    if n == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    cut = np.r_[True, (labels[1:] != labels[:-1]) | (np.diff(qc) < 0)]
    starts = np.flatnonzero(cut)
    run = np.cumsum(cut) - 1
    ends = np.r_[starts[1:], n]
    return starts[run].astype(np.int64), ends[run].astype(np.int64)


def _speed_grid(cfg: SequenceConfig, vmin: float, vmax: float, unit: float, qstep: float) -> tuple[F64, float]:
    """The speeds searched and their step (see :class:`SequenceConfig`)."""
    if vmax <= vmin:
        return np.array([vmin]), 0.0
    step = cfg.speed_step or unit / (max(1, cfg.length) * qstep)
    step = max(step, (vmax - vmin) / (MAX_SPEEDS - 1))
    n = math.floor((vmax - vmin) / step + 1e-9) + 1
    v = vmin + step * np.arange(n)
    if v[-1] < vmax - 1e-9:
        v = np.r_[v, vmax]
    return v.astype(np.float64), float(step)


def _offsets(cfg: SequenceConfig) -> I64:
    n = cfg.length
    return np.arange(-n, 1 if cfg.causal else n + 1, dtype=np.int64)


def window_rows(centres: I64, offs: I64, run_lo: I64, run_hi: I64, slide: bool) -> tuple[I64, BoolArray]:
    """Rows ``[B, W]`` of each centre's window (``centres + offs``, offset order) and which lie in
    the centre's run. With ``slide`` (offline matching, where the window reaches both ways), a
    window cut by its run's start or end slides along the run so that it keeps its length, all its
    extra frames on the one side there is (what proposes places for a drive's first and last frames:
    :func:`~memlog.matching.voting._with_end_votes`; the paths are scored along the cut window,
    whose frames are the nearest). The centre stays in its window; a run shorter than the window
    is the whole run."""
    centres = np.asarray(centres, dtype=np.int64)
    t = centres[:, None] + offs[None, :]
    lo, hi = run_lo[centres][:, None], run_hi[centres][:, None]
    if slide and len(offs):
        shift = np.maximum(lo[:, 0] - t[:, 0], 0) - np.maximum(t[:, -1] - (hi[:, 0] - 1), 0)
        t = t + shift[:, None]
    return t, (t >= lo) & (t < hi)


def _pair_dots(q: F32, rows: F32, t: I64, r: I64) -> F64:
    """``q[t] . rows[r]`` pair by pair (float32 products summed per pair: the value of a pair does
    not depend on which other pairs are computed with it), in chunks of bounded memory."""
    out = np.empty(len(t), dtype=np.float64)
    step = max(1, PAIR_ELEMS // max(1, q.shape[1]))
    for a in range(0, len(t), step):
        out[a : a + step] = np.einsum("ij,ij->i", q[t[a : a + step]], rows[r[a : a + step]])
    return out


def _z_of_pairs(p: _Problem, t: npt.NDArray[np.int64], r: npt.NDArray[np.int64]) -> F64:
    """Contrast-normalised similarity of query rows ``t`` and sorted map rows ``r`` (any equal
    shapes), each distinct pair computed once."""
    m = p.rc.shape[0]
    key = t.astype(np.int64).ravel() * m + r.astype(np.int64).ravel()
    uk, inv = np.unique(key, return_inverse=True)
    ut, ur = uk // m, uk % m
    z = (_pair_dots(p.q, p.rows, ut, ur) - p.mu[ut]) / p.sd[ut]
    out: F64 = z[inv].reshape(t.shape)
    return out


def _on_map(p: _Problem, x: npt.NDArray[np.float64]) -> BoolArray:
    """Coordinates within the map's extent (half a frame spacing beyond its first and last frame)."""
    half = 0.5 * p.spacing
    out: BoolArray = (x >= p.rc[0] - half) & (x <= p.rc[-1] + half)
    return out




def _windows(p: _Problem, centres: I64, offs: I64) -> tuple[I64, BoolArray, F64]:
    """Rows ``[B, W]`` of each centre's window (offset order; invalid slots hold the centre),
    which slots are inside the run, and their coordinate minus the centre's."""
    t, valid = window_rows(centres, offs, p.run_lo, p.run_hi, False)
    t = np.where(valid, t, centres[:, None])
    return t, valid, p.qc[t] - p.qc[centres][:, None]


def _centre_offsets(p: _Problem) -> F64:
    """Centre positions tried around a voted map frame, in coordinate units: every half
    reference frame (:data:`CENTRE_STEPS`) within half the map's spacing."""
    h = math.floor(p.spacing / (2 * p.unit) * CENTRE_STEPS + 1e-9)
    out: F64 = np.arange(-h, h + 1, dtype=np.float64) * p.unit / CENTRE_STEPS
    return out


def _closest_to_their_frame(p: _Problem, pred: F64, rk: I64, inside: BoolArray) -> BoolArray:
    """Along the last axis (a window's frames, in order, their predicted coordinates ``pred``
    non-decreasing): the frames whose prediction is the nearest, among the frames sharing their
    nearest map frame ``rk``, to that map frame (all of them on a tie: a stop). A map frame
    along the path is compared with the query frame(s) aligned with it, never with frames
    that fell into its gap only because the map has no frame nearer."""
    dist = np.abs(pred - p.rc[rk])
    inf = np.inf
    left_same = np.zeros(rk.shape, bool)
    right_same = np.zeros(rk.shape, bool)
    left_same[..., 1:] = (rk[..., 1:] == rk[..., :-1]) & inside[..., :-1]
    right_same[..., :-1] = (rk[..., :-1] == rk[..., 1:]) & inside[..., 1:]
    dl = np.full(rk.shape, inf)
    dr = np.full(rk.shape, inf)
    dl[..., 1:] = dist[..., :-1]
    dr[..., :-1] = dist[..., 1:]
    eps = 1e-9 * p.unit
    out: BoolArray = (~left_same | (dist <= dl + eps)) & (~right_same | (dist <= dr + eps))
    return out


def _score_constant(p: _Problem, centres: I64, offs: I64, places: I64, vbest: I64) -> tuple[F64, F64, F64]:
    """Exact constant-speed scores ``[B, P]`` of the voted places, with the best centre
    coordinate and speed of each: the centre is tried at :func:`_centre_offsets` around the map
    frame, the speed at the voted one and :data:`RESCORE_SPEEDS` steps either side. The centre
    offsets are taken in blocks of at most :data:`SCORE_ELEMS` path elements, so memory does not
    grow with the map's sparsity (a sparse map has many offsets)."""
    t, valid, d = _windows(p, centres, offs)
    nv = len(p.speeds)
    sidx = np.clip(vbest[:, :, None] + np.arange(-RESCORE_SPEEDS, RESCORE_SPEEDS + 1)[None, None, :], 0, nv - 1)
    ok = places >= 0
    v = p.speeds[sidx]  # [B, P, S]
    penalty = p.prior(v)
    dx_all = _centre_offsets(p)
    b, n_p, n_s, n_w = places.shape[0], places.shape[1], v.shape[2], d.shape[1]
    step = max(1, SCORE_ELEMS // max(1, b * n_p * n_s * n_w))
    best = np.full((b, n_p), -np.inf)
    centre = np.zeros((b, n_p))
    speed = np.full((b, n_p), np.nan)
    for a in range(0, len(dx_all), step):  # in offset order: the first best is the lowest offset, then speed
        dx = dx_all[a : a + step]
        x = p.rc[np.maximum(places, 0)][:, :, None] + dx[None, None, :]  # [B, P, D]
        pred = x[:, :, :, None, None] + v[:, :, None, :, None] * d[:, None, None, None, :]  # [B, P, D, S, W]
        rk = _nearest(p.rc, pred)
        tq = np.broadcast_to(t[:, None, None, None, :], rk.shape)
        inside = valid[:, None, None, None, :] & ok[:, :, None, None, None] & _on_map(p, pred)
        use = inside & _closest_to_their_frame(p, pred, rk, inside)
        z = np.zeros(rk.shape)
        z[use] = _z_of_pairs(p, tq[use], rk[use])
        total = np.zeros(rk.shape[:4])
        count = np.zeros(rk.shape[:4])
        for o in range(rk.shape[4]):  # a fixed summation order
            total += z[..., o]
            count += use[..., o]
        total /= np.sqrt(np.maximum(count, 1))
        total -= penalty[:, :, None, :]
        flat = total.reshape(b, n_p, -1)
        arg = np.argmax(flat, axis=2)
        score = np.take_along_axis(flat, arg[..., None], axis=2)[..., 0]
        di, si = np.divmod(arg, n_s)
        better = score > best
        best = np.where(better, score, best)
        centre = np.where(better, np.take_along_axis(x, di[..., None], axis=2)[..., 0], centre)
        speed = np.where(better, np.take_along_axis(v, si[..., None], axis=2)[..., 0], speed)
    return np.where(ok, best, -np.inf), centre, speed

"""Sequence matching of descriptor arrays (:func:`match_sequences`): the single-frame candidates, the
votes, the exact path scores and the fallback to single frames, row by row."""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from memlog.descriptors.search import Database, _as_2d, _rescore, _row_norms, match
from memlog.errors import DescriptorError
from memlog.matching.config import (
    EXACT_PLACES, FALLBACK_REASONS, MAX_LENGTH_SCALE, VOTE_ELEMS, BoolArray, F32, F64, I64, SequenceConfig, SequenceMatch,
)
from memlog.matching.paths import _Problem, _offsets, _run_bounds, _score_constant, _speed_grid, _stats, _windows
from memlog.matching.voting import _place, _votes, _with_end_votes

if TYPE_CHECKING:
    from memlog.descriptors.approx import IVFIndex

__all__ = ["match_sequences"]



def match_sequences(
    query: npt.ArrayLike,
    query_coord: npt.ArrayLike,
    reference: npt.ArrayLike | Database,
    reference_coord: npt.ArrayLike,
    config: SequenceConfig | None = None,
    *,
    k: int = 5,
    ref_mask: npt.ArrayLike | None = None,
    runs: npt.ArrayLike | None = None,
    ref_unit: float | None = None,
    coordinate: str = "frames",
    index: IVFIndex | None = None,
    nprobe: int | None = None,
    rerank: int | None = None,
    standing: npt.ArrayLike | None = None,
    pace: float = 1.0,
) -> SequenceMatch:
    """Match the query drive against the reference as sequences (``docs/method.md``, "Drives, not frames").

    ``query`` ``[Q, d]`` and ``reference`` ``[R, d]``: L2-normalised descriptors, rows in drive
    order; ``query_coord`` ``[Q]`` and ``reference_coord`` ``[R]``: their coordinates along the
    drives (frame index, seconds, metres: the unit of ``coordinate``, which also picks the
    default speeds). ``ref_mask`` (bool ``[R]``): the map is the rows where it is True (the
    others are not searched); returned rows are rows of the full ``reference``. ``runs``
    (``[Q]`` labels, default one run): consecutive rows with the same label form a run (a
    decreasing coordinate also starts one). ``ref_unit``: the reference drive's frame spacing in
    coordinate units (default: the median positive spacing of ``reference_coord`` over all
    rows). ``index``: an approximate index over the (masked) map for the candidates (default:
    exact search; ``nprobe``/``rerank`` its settings); ``reference`` is then its database.
    ``standing`` (bool ``[Q]``): query rows whose camera stood still since the previous row of
    their run; they take that stop's first row's result (the first row of a run never stands).
    ``pace``: the speed of a query driven at the map's own pace (frames: the query's frame interval
    over the map drive's, so a map recorded at twice the frame rate has pace 2): the default speed
    range is taken relative to it and the speed prior is centred on it.
    """
    cfg = config or SequenceConfig()
    if k < 1:
        raise DescriptorError(f"k must be >= 1, got {k}")
    q, db, qc, rc_all, labels, n_ref = _inputs(query, query_coord, reference, reference_coord, ref_mask, runs, index)
    n_q, n_m = q.shape[0], db.rows.shape[0]
    if standing is not None:
        stand = np.asarray(standing, dtype=bool)
        if stand.shape != (n_q,):
            raise DescriptorError(f"standing must have one flag per query row, got shape {stand.shape}")
        first = _run_bounds(labels, qc)[0] == np.arange(n_q)
        stand = stand & ~first
        if stand.any() and cfg.enabled:
            keep = ~stand
            sub = match_sequences(q[keep], qc[keep], reference, reference_coord, config, k=k, ref_mask=ref_mask,
                                  runs=labels[keep], ref_unit=ref_unit, coordinate=coordinate, index=index,
                                  nprobe=nprobe, rerank=rerank, pace=pace)
            lo, hi = _run_bounds(labels, qc)
            return _expand(sub, keep, q, db, n_ref, cfg, hi - lo)
    info: dict[str, Any] = {**cfg.to_dict(), "coordinate": coordinate, "k": k}
    m = _MapOrder.of(db, rc_all, n_ref, ref_unit, cfg)
    cfg = m.cfg
    info["length_used"] = cfg.length
    ci, z, mu, sd = _candidates(q, db, cfg, k, index, nprobe, rerank)
    out = _SingleFrames.of(ci, z, rc_all, cfg.exclude * m.unit, k, n_m)
    run_lo, run_hi = _run_bounds(labels, qc)
    info["runs"] = len(np.unique(run_lo)) if n_q else 0
    reason = _fallback_reasons(cfg, run_lo, run_hi, m, n_m)
    use = reason == ""
    if use.any() and n_m:
        p = _problem(q, qc, run_lo, run_hi, use, db, m, mu, sd, cfg, coordinate, pace, info)
        _match_windows(p, use, ci, z, m, k, out)
    # a row with a voted place none of whose paths scored stays a single frame: say why
    reason[use & ~out.seq] = "no-path"
    fallback = reason.astype(str)
    _summarise_fallback(info, cfg, fallback)
    db_rows = _db_rows(db, n_ref)
    sims = _similarities(q, db, out.indices, db_rows)
    ratio = _ratio(q, db, out.indices[:, 0], out.second_row, db_rows)
    return SequenceMatch(out.indices, out.scores, sims, out.margin, out.speed, out.window, out.seq, ratio, fallback,
                         info)


def _inputs(query: npt.ArrayLike, query_coord: npt.ArrayLike, reference: npt.ArrayLike | Database,
            reference_coord: npt.ArrayLike, ref_mask: npt.ArrayLike | None, runs: npt.ArrayLike | None,
            index: IVFIndex | None) -> tuple[F32, Database, F64, F64, I64, int]:
    """:func:`match_sequences`' arguments checked: the query descriptors, the map's database, both
    drives' coordinates, the query's run labels and the number of reference rows."""
    q = _as_2d(query, "query")
    _row_norms(q, "query")
    if index is not None:
        db = index.db
    elif isinstance(reference, Database):
        db = reference
    else:
        db = Database.of(reference, ref_mask, dim=q.shape[1])
    n_q, n_m = q.shape[0], db.rows.shape[0]
    if n_m and db.rows.shape[1] != q.shape[1]:
        raise DescriptorError(f"query descriptors are {q.shape[1]}-d but references are {db.rows.shape[1]}-d")
    qc = np.asarray(query_coord, dtype=np.float64)
    rc_all = np.asarray(reference_coord, dtype=np.float64)
    n_ref = rc_all.shape[0] if db.index is not None else n_m
    if qc.shape != (n_q,) or (db.index is None and rc_all.shape != (n_m,)) or rc_all.ndim != 1:
        raise DescriptorError(f"coordinates must be one per row: query {qc.shape} for {n_q}, reference "
                              f"{rc_all.shape} for {n_ref}")
    if not (np.all(np.isfinite(qc)) and np.all(np.isfinite(rc_all))):
        raise DescriptorError("coordinates must be finite")
    labels = np.zeros(n_q, np.int64) if runs is None else np.asarray(runs).astype(np.int64)
    if labels.shape != (n_q,):
        raise DescriptorError(f"runs must have one label per query row, got shape {labels.shape}")
    return q, db, qc, rc_all, labels, n_ref


@dataclass
class _MapOrder:
    """The map's frames in coordinate order: their coordinates ``rc`` (increasing), the reference
    drive's frame spacing ``unit`` and the map's own ``spacing``, the reference row of each sorted
    frame (``full_row``; ``order``: the database row of each) and the sorted position of each reference row (``sorted_of_full``, -1: not
    in the map); ``cfg`` with its window scaled to the map's spacing."""

    order: I64
    rc: F64
    unit: float
    spacing: float
    full_row: I64
    sorted_of_full: I64
    cfg: SequenceConfig

    @classmethod
    def of(cls, db: Database, rc_all: F64, n_ref: int, ref_unit: float | None, cfg: SequenceConfig) -> _MapOrder:
        rc_db = rc_all if db.index is None else rc_all[db.index]
        order = np.argsort(rc_db, kind="stable")
        rc = rc_db[order]
        unit = float(ref_unit) if ref_unit else _median_step(rc_all)  # the reference drive's frame spacing
        spacing = _median_step(rc)  # the map's (kept frames') spacing
        if cfg.enabled and cfg.scale_length and len(rc) > 1:
            # a sparse map (every 2nd, 4th... frame kept) has fewer frames along a window of query
            # frames: the window grows with the map's spacing so a sequence gathers as much evidence
            scale = min(MAX_LENGTH_SCALE, max(1.0, spacing / unit)) if unit > 0 else 1.0
            cfg = replace(cfg, length=int(round(cfg.length * scale)))
        full_row = (order if db.index is None else db.index[order]).astype(np.int64)
        sorted_of_full = np.full(max(n_ref, 1), -1, dtype=np.int64)
        sorted_of_full[full_row] = np.arange(len(rc))
        return cls(order.astype(np.int64), rc, unit, spacing, full_row, sorted_of_full, cfg)


def _candidates(q: F32, db: Database, cfg: SequenceConfig, k: int, index: IVFIndex | None, nprobe: int | None,
                rerank: int | None) -> tuple[I64, F64, F64, F64]:
    """Every query frame's single-frame candidates (reference rows, best first; one more than
    ``cfg.candidates``: the floor of the gains, and a second place), their contrast-normalised
    similarities ``z`` and the normalisation's mean and deviation per query."""
    n_q, n_m = q.shape[0], db.rows.shape[0]
    n_cand = max(cfg.candidates + 1, min(k, max(1, n_m)))
    if n_q and n_m:
        if index is not None:
            ci, cs = index.search(q, n_cand, nprobe, rerank)
        else:
            ci, cs = match(q, db, k=n_cand)  # rows of the full reference
    else:
        ci, cs = np.full((n_q, n_cand), -1, np.int64), np.full((n_q, n_cand), -np.inf, np.float32)
    mu, sd = _stats(q, db)
    with np.errstate(invalid="ignore"):
        z = np.where(ci >= 0, (cs.astype(np.float64) - mu[:, None]) / sd[:, None], -np.inf)
    return ci, z, mu, sd


@dataclass
class _SingleFrames:
    """The result rows being filled: every query starts as a single frame (a path of one pair,
    scored by ``z``, the margin taken to the best candidate of another place); sequence rows are
    overwritten by :func:`~memlog.matching.voting._place`."""

    indices: I64
    scores: F64
    margin: F64
    second_row: I64
    speed: F64
    window: I64
    seq: BoolArray

    @classmethod
    def of(cls, ci: I64, z: F64, rc_all: F64, excl: float, k: int, n_m: int) -> _SingleFrames:
        n_q = ci.shape[0]
        kk = min(k, max(1, n_m))
        indices = np.full((n_q, k), -1, dtype=np.int64)
        scores = np.full((n_q, k), -np.inf)
        indices[:, :kk] = ci[:, :kk]
        scores[:, :kk] = z[:, :kk]
        second = _second_place(ci, rc_all, excl)
        rows_q = np.arange(n_q)
        with np.errstate(invalid="ignore"):
            margin = np.where(second >= 0, z[:, 0] - z[rows_q, np.maximum(second, 0)], np.nan)
        second_row = np.where(second >= 0, ci[rows_q, np.maximum(second, 0)], -1)
        return cls(indices, scores, margin, second_row, np.full(n_q, np.nan), np.ones(n_q, dtype=np.int64),
                   np.zeros(n_q, dtype=bool))


def _fallback_reasons(cfg: SequenceConfig, run_lo: I64, run_hi: I64, m: _MapOrder, n_m: int) -> npt.NDArray[Any]:
    """Why each query row is matched frame by frame ("" where it can be a sequence): offline, a
    run shorter than the window; causal, fewer frames of its run before it than the window needs
    (decided from the past only: a live robot does not know how long a run will be); a map shorter
    than the window; single frames asked for."""
    n_q = len(run_lo)
    so_far = np.arange(n_q) - run_lo + 1
    reason = np.full(n_q, "", dtype=object)
    if not cfg.enabled:
        reason[:] = "single"
        return reason
    reason[(so_far if cfg.causal else run_hi - run_lo) < cfg.length + 1] = "causal-start" if cfg.causal else "short-run"
    # the map must cover at least as many reference frames as the window has frames
    if n_m == 0 or (m.rc[-1] - m.rc[0]) / max(m.unit, 1e-300) + 1 < len(_offsets(cfg)) - 1e-9:
        reason[:] = "small-map"
    return reason


def _problem(q: F32, qc: F64, run_lo: I64, run_hi: I64, use: BoolArray, db: Database, m: _MapOrder, mu: F64,
             sd: F64, cfg: SequenceConfig, coordinate: str, pace: float, info: dict[str, Any]) -> _Problem:
    """The windows' matching problem: the speeds searched (relative to ``pace`` unless given, in
    steps set by the query's median coordinate step) and the map in coordinate order; ``info``
    records the speeds."""
    qsteps = [np.abs(np.diff(qc[a : run_hi[a]])) for a in np.unique(run_lo[use])]
    qs = np.concatenate(qsteps) if qsteps else np.zeros(0)
    qstep = float(np.median(qs[qs > 0])) if np.any(qs > 0) else m.unit
    vmin, vmax = cfg.speed_range(coordinate)
    if cfg.speeds is None:
        vmin, vmax = vmin * pace, vmax * pace
    speeds, step = _speed_grid(cfg, vmin, vmax, m.unit, qstep)
    info.update({"speeds": [vmin, vmax], "speed_step": step, "n_speeds": len(speeds), "unit": m.unit,
                 "speed_prior": cfg.speed_prior, "pace": pace})
    return _Problem(q, qc, run_lo, run_hi, db.rows[m.order], m.rc, m.full_row, mu, sd, m.unit, m.spacing,
                    cfg.exclude * m.unit, speeds, cfg, pace)


def _match_windows(p: _Problem, use: BoolArray, ci: I64, z: F64, m: _MapOrder, k: int, out: _SingleFrames) -> None:
    """Match the windows of the rows in ``use`` as sequences, into ``out``: the candidates vote
    (weighted by how far each stands out of the frame's next candidate, the (K+1)-th), the
    best-voted places are scored exactly along their paths and ranked, block by block of centres."""
    cfg = p.cfg
    n_q = ci.shape[0]
    offs = _offsets(cfg)
    cand = np.where(ci >= 0, m.sorted_of_full[np.maximum(ci, 0)], -1)
    n_valid = (ci >= 0).sum(axis=1)
    floor = z[np.arange(n_q), np.clip(n_valid - 1, 0, cfg.candidates)]
    gain = np.where(ci[:, : cfg.candidates] >= 0, z[:, : cfg.candidates] - floor[:, None], 0.0)
    cand = cand[:, : cfg.candidates]
    n_places = max(k, EXACT_PLACES)
    centres_all = np.flatnonzero(use).astype(np.int64)
    # votes are [centres x window x candidates, speeds]: fewer centres a block when they are many
    block = max(1, min(cfg.block, VOTE_ELEMS // max(1, len(offs) * cfg.candidates * len(p.speeds))))
    for a in range(0, len(centres_all), block):
        centres = centres_all[a : a + block]
        places, vbest = _with_end_votes(p, centres, offs, cand, gain, *_votes(p, centres, offs, cand, gain, n_places))
        sc = np.full(places.shape, -np.inf)
        xc = np.zeros(places.shape)
        sp = np.full(places.shape, np.nan)
        # the centres with places proposed by their slid windows apart (the others' padding unscored)
        more = (places[:, n_places:] >= 0).any(axis=1)
        for rows, width in ((~more, n_places), (more, places.shape[1])):
            if rows.any():
                sc[rows, :width], xc[rows, :width], sp[rows, :width] = _score_constant(
                    p, centres[rows], offs, places[rows, :width], vbest[rows, :width])
        _, valid, _d = _windows(p, centres, offs)
        for j, i in enumerate(centres):
            _place(p, int(i), sc[j], xc[j], sp[j], int(valid[j].sum()), k, out.indices, out.scores, out.margin,
                   out.speed, out.window, out.seq)
    # a sequence row's second place is its rank 2 (a distinct place)
    out.second_row = np.where(out.seq, out.indices[:, 1] if k > 1 else -1, out.second_row)


def _second_place(ci: I64, rc_all: F64, excl: float) -> I64:
    """Per query, the column of ``ci`` (candidates, best first; rows of the reference whose
    coordinates are ``rc_all``) of the first candidate outside ``excl`` of the best: another
    place (-1: none among the candidates)."""
    out = np.full(ci.shape[0], -1, dtype=np.int64)
    if ci.shape[1] < 2 or not ci.shape[0]:
        return out
    c = np.where(ci >= 0, rc_all[np.maximum(ci, 0)], np.nan)
    with np.errstate(invalid="ignore"):
        far = (ci[:, 1:] >= 0) & (np.abs(c[:, 1:] - c[:, :1]) > excl) & (ci[:, :1] >= 0)
    has = far.any(axis=1)
    out[has] = np.argmax(far[has], axis=1) + 1
    return out


def _ratio(q: F32, db: Database, best: I64, second: I64, db_rows: I64) -> F64:
    """Lowe's ratio: the query frame's descriptor distance to ``best`` over its distance to
    ``second`` (reference rows; NaN where either is missing; 1 where both distances are 0)."""
    out = np.full(len(best), np.nan)
    ok = np.flatnonzero((best >= 0) & (second >= 0))
    if len(ok):
        s1 = _rescore(q, db.rows, ok.astype(np.int64), db_rows[best[ok]])
        s2 = _rescore(q, db.rows, ok.astype(np.int64), db_rows[second[ok]])
        d1 = np.sqrt(np.maximum(0.0, 2.0 - 2.0 * s1))
        d2 = np.sqrt(np.maximum(0.0, 2.0 - 2.0 * s2))
        out[ok] = np.where(d2 > 0, d1 / np.where(d2 > 0, d2, 1.0), 1.0)
    return out


def _summarise_fallback(info: dict[str, Any], cfg: SequenceConfig, fallback: npt.NDArray[np.str_]) -> None:
    """``info``'s counts of rows matched as sequences and frame by frame, by reason, and the
    summary line (None: every row by sequence)."""
    n_q = len(fallback)
    counts = {r: int(np.sum(fallback == r)) for r in dict.fromkeys(fallback.tolist()) if r}
    n_single = sum(counts.values())
    info["sequence_queries"] = n_q - n_single
    info["single_queries"] = n_single
    info["fallback_reasons"] = counts
    if not n_single:
        info["fallback"] = None
        return
    used = int(info.get("length_used", cfg.length))
    n = used + (0 if cfg.causal else used) + 1
    parts = [f"{c} frame(s): {FALLBACK_REASONS.get(r, r)}" for r, c in counts.items()]
    what = "every frame" if n_single == n_q else f"{n_single} of {n_q} frames"
    info["fallback"] = f"{what} matched frame by frame (window {n} frames) — " + "; ".join(parts)


def _expand(sub: SequenceMatch, keep: BoolArray, q: F32, db: Database, n_ref: int, cfg: SequenceConfig,
            run_len: I64) -> SequenceMatch:
    """The result of every query row from that of the rows matched (``keep``): a standing row
    takes the result of the last matched row before it, with its own similarities (and counts
    as matched the way that row was). A row whose run was long enough but whose moving frames
    were too few for the window falls back because the query stood still (``run_len``: each
    row's run length before the standing rows were left out)."""
    n_q = len(keep)
    last = np.maximum.accumulate(np.where(keep, np.arange(n_q), 0))
    src = (np.cumsum(keep) - 1)[last]
    out = sub.take(src)
    reason = out.fallback.astype(object)
    reason[(reason == "short-run") & (run_len >= int(sub.info.get("length_used", cfg.length)) + 1)] = "standing"
    fallback = reason.astype(str)
    info = {**sub.info, "standing_rows": int((~keep).sum())}
    _summarise_fallback(info, cfg, fallback)
    db_rows = _db_rows(db, n_ref)
    sims = _similarities(q, db, out.indices, db_rows)
    second = np.where(out.sequence, out.indices[:, 1] if out.indices.shape[1] > 1 else -1, -1)
    ratio = np.where(out.sequence, _ratio(q, db, out.indices[:, 0], second, db_rows), out.ratio)
    return SequenceMatch(out.indices, out.scores, sims, out.margin, out.speed, out.window, out.sequence, ratio,
                         fallback, info)


def _median_step(c: F64) -> float:
    s = np.diff(np.sort(c))
    s = s[s > 0]
    return float(np.median(s)) if s.size else 1.0


def _db_rows(db: Database, n_ref: int) -> I64:
    """The row of ``db`` holding each of the ``n_ref`` reference rows (-1: not in the map)."""
    if db.index is None:
        return np.arange(max(n_ref, 1), dtype=np.int64)
    out = np.full(max(n_ref, 1), -1, dtype=np.int64)
    out[db.index] = np.arange(len(db.index))
    return out


def _similarities(q: F32, db: Database, indices: I64, db_rows: I64) -> F32:
    """Cosine similarity of each query frame to each matched frame (``indices``: reference rows,
    ``db_rows``: :func:`_db_rows`; float64 products, pair by pair)."""
    out = np.full(indices.shape, -np.inf, dtype=np.float32)
    qr, kr = np.nonzero(indices >= 0)
    if len(qr):
        out[qr, kr] = _rescore(q, db.rows, qr.astype(np.int64), db_rows[indices[qr, kr]]).astype(np.float32)
    return out

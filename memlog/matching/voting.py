"""Voting: the single-frame candidates of a window's frames vote for the places (and speeds) its path may
take; the best-voted places are scored exactly and ranked into a query's result."""

from __future__ import annotations


import numpy as np

from memlog.matching.config import EXACT_PLACES, TOP_VOTES, BoolArray, F64, I64
from memlog.matching.coordinates import _nearest
from memlog.matching.paths import _Problem, _on_map, window_rows

__all__: list[str] = []



def _votes(p: _Problem, centres: I64, offs: I64, cand: I64, gain: F64, n_places: int,
           slide: bool = False) -> tuple[I64, I64]:
    """The best-voted places of each centre: ``(places [B, n_places], speed index [B, n_places])``,
    sorted map rows (-1 = none), distinct by ``p.excl`` (greedy non-maximum suppression, best
    first), each with the speed that voted for it most. ``slide``: a window cut by its run's end
    votes with the frames of the window slid along the run (:func:`~memlog.matching.paths.window_rows`)."""
    b = len(centres)
    m = p.rc.shape[0]
    nv = len(p.speeds)
    places = np.full((b, n_places), -1, dtype=np.int64)
    speeds = np.zeros((b, n_places), dtype=np.int64)
    t, valid = window_rows(centres, offs, p.run_lo, p.run_hi, slide)
    bi, oi = np.nonzero(valid)
    tv = t[bi, oi]
    dv = p.qc[tv] - p.qc[centres[bi]]
    cr = cand[tv]  # [n, K] sorted map rows, -1 = none
    g = gain[tv]
    rr, cc = np.nonzero((cr >= 0) & (g > 0))
    if not len(rr):
        return places, speeds
    vs = np.arange(nv, dtype=np.int64)
    x = p.rc[cr[rr, cc]][:, None] - p.speeds[vs][None, :] * dv[rr][:, None]  # [votes, V]: the centre they imply
    on_map = _on_map(p, x)  # a centre beyond the map's ends has no frame to vote for (never clipped onto one)
    key = (bi[rr][:, None].astype(np.int64) * m + _nearest(p.rc, x)) * nv + vs[None, :]
    key = key[on_map]
    wv = np.exp2(-p.prior(p.speeds))  # the speed prior weighs each speed's vote as it weighs its score
    val = (g[rr, cc][:, None] * wv[None, :])[on_map]
    if not len(key):
        return places, speeds
    order = np.argsort(key, kind="stable")
    key, val = key[order], val[order]
    starts = np.r_[0, np.flatnonzero(np.diff(key)) + 1]
    sums = np.add.reduceat(val, starts)  # per (centre, place, speed)
    place = key[starts] // nv
    vidx = key[starts] % nv
    pstarts = np.r_[0, np.flatnonzero(np.diff(place)) + 1]
    seg = np.repeat(np.arange(len(pstarts)), np.diff(np.r_[pstarts, len(place)]))
    best = np.maximum.reduceat(sums, pstarts)
    is_best = np.flatnonzero(sums == best[seg])
    _u, first_best = np.unique(seg[is_best], return_index=True)
    best_v = vidx[is_best[first_best]]
    place = place[pstarts]
    cb, row = place // m, place % m
    order = np.lexsort((row, -best, cb))
    cb, row, best_v = cb[order], row[order], best_v[order]
    first = np.searchsorted(cb, np.arange(b))
    last = np.searchsorted(cb, np.arange(b), side="right")
    for j in range(b):
        top = slice(first[j], min(last[j], first[j] + TOP_VOTES))
        for n, (r, v) in enumerate(_distinct(p, row[top], best_v[top], [], n_places)):
            places[j, n], speeds[j, n] = r, v
    return places, speeds


def _distinct(p: _Problem, rows: I64, speeds: I64, have: list[float], limit: int) -> list[tuple[int, int]]:
    """``rows`` (sorted map rows, with their speed indices), in order, each taken when it lies further
    than ``p.excl`` from every row taken before it and from the coordinates ``have``: greedy
    non-maximum suppression, at most ``limit`` rows."""
    taken: list[tuple[int, int]] = []
    xs = list(have)
    for r, v in zip(rows, speeds):
        x = float(p.rc[r])
        if all(abs(x - y) > p.excl for y in xs):
            taken.append((int(r), int(v)))
            xs.append(x)
            if len(taken) == limit:
                break
    return taken




def _with_end_votes(p: _Problem, centres: I64, offs: I64, cand: I64, gain: F64, places: I64, vbest: I64
                    ) -> tuple[I64, I64]:
    """``places`` / ``vbest`` with, for each centre whose window its run's start or end cuts
    (offline matching only), the places its window slid along the run votes for appended (those
    not within ``p.excl`` of one it has; -1 padded). At a drive's end the window has frames on one
    side only, and where their single-frame candidates rarely hold the right places the cut
    window's votes miss them (the drive HMM then has no place to continue the path into and
    relocalises for the last frames); the slid window has as many frames as any other, so more
    chances to propose them. Each place is still scored along the cut window: only the proposals
    grow."""
    if p.cfg.causal or not len(centres):
        return places, vbest
    t0, _ = window_rows(centres, offs, p.run_lo, p.run_hi, False)
    t1, _ = window_rows(centres, offs, p.run_lo, p.run_hi, True)
    cut = np.flatnonzero((t0 != t1).any(axis=1))
    if not len(cut):
        return places, vbest
    n_places = places.shape[1]
    more, more_v = _votes(p, centres[cut], offs, cand, gain, n_places, slide=True)
    extra = np.full(places.shape, -1, dtype=np.int64)
    extra_v = np.zeros(places.shape, dtype=np.int64)
    for j, c in enumerate(cut):
        have = [float(p.rc[r]) for r in places[c] if r >= 0]
        found = more[j] >= 0
        for n, (r, v) in enumerate(_distinct(p, more[j][found], more_v[j][found], have, n_places)):
            extra[c, n], extra_v[c, n] = r, v
    return np.concatenate([places, extra], axis=1), np.concatenate([vbest, extra_v], axis=1)


def _place(p: _Problem, i: int, sc: F64, xc: F64, sp: F64, w: int, k: int, indices: I64, scores: F64,
           margin: F64, speed: F64, window: I64, seq: BoolArray) -> None:
    """Write query ``i``'s result from its scored centres (in vote order): the first
    ``places`` (:data:`EXACT_PLACES` by default) ranked by score, then the others ranked by score (so the best match does
    not depend on ``k``), each reported as the map frame nearest it; a centre, or its reported
    frame, within ``p.excl`` of a better one's is the same place (left out); the margin is the best
    score minus the next place's."""
    good = np.flatnonzero(np.isfinite(sc))
    if not len(good):
        return
    late = (good >= EXACT_PLACES).astype(np.int64)
    order = good[np.lexsort((xc[good], -sc[good], late))]
    kept: list[int] = []
    rows: list[int] = []
    for e in order:
        r = int(_nearest(p.rc, np.array([xc[e]]))[0])
        if any(abs(xc[e] - xc[f]) <= p.excl or abs(p.rc[r] - p.rc[g]) <= p.excl for f, g in zip(kept, rows)):
            continue
        kept.append(int(e))
        rows.append(r)
    n = min(k, len(kept))
    indices[i] = -1
    scores[i] = -np.inf
    indices[i, :n] = p.full_row[rows[:n]]
    scores[i, :n] = sc[kept[:n]]
    margin[i] = sc[kept[0]] - sc[kept[1]] if len(kept) > 1 else np.nan
    speed[i] = sp[kept[0]]
    window[i] = w
    seq[i] = True

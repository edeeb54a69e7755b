"""Staged segment selection: the memorability CNN only for frames that can still win their segment.

Segment selection keeps, per place segment, the frame with the best geometric score
(MS^a SS^b ES^c)^(1/(a+b+c)) among the frames passing the minimum scores. SS and ES are cheap;
MS needs ResMem. The score is increasing in MS, and MS is bounded before any crop is scored:
MS = sum_k w_k M_k with crop weights summing to SS and ResMem outputs in 0..1, so MS lies in
[0, SS] (in [0, 1] with ``normalize="static"``). :func:`choose_in_segment` therefore scores the
candidates in order of their upper bound; each one only until it is known not to beat the
current leader (the crop loop stops as soon as MS is below the MS that would be needed), a new
leader to its exact MS; and it stops when the leader's score is above every remaining
candidate's upper bound. The frame it returns is the frame full scoring would keep (ties go to
the earlier frame, as in :func:`~memlog.selection.segment.select_segments`): the tests compare
both on real logs.

``shortlist=K`` (approximate, ``--candidates K``): only K candidates per segment are scored,
the best by their upper bound, spread over the segment (the best of each of K equal parts; with
a centre tolerance the one nearest the part's middle among those within it of the best).

Staticity is staged the same way, one step earlier (:func:`detect_in_segment`): before the
detector runs, a frame's ES is bounded by ``es_static``, its ES were every pixel static (S <= 1
only removes entropy), and SS <= 1, MS <= SS, so its score, and the shortlist's upper bound, are
at most ``geometric_score(1, 1, es_static)``. The detector runs on a segment's frames in order of
that bound until the best upper bound of the segment is known and, with the centre rule, until
the frame nearest the segment's middle within the tolerance of it is known; the frames it never
reached cannot be their segment's candidate, whatever their SS. Their SS and ES stay unknown
(NaN in the table), and selection from such a table keeps the frames selection from every score
keeps (:func:`~memlog.selection.segment.select_segments` drops a frame with unknown scores, and
calls it dropped for its segment).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from memlog.selection.segment import MS_DIGITS, geometric_score, shortlist_rows, upper_bounds

__all__ = ["MSResult", "MSState", "choose_in_segment", "shortlist_rows", "ms_to_beat", "StaticityMode",
           "staticity_mode", "detect_in_segment"]

#: Slack on the MS a candidate needs: decisions are verified on the score itself anyway.
_SLACK = 1e-9


@dataclass
class MSResult:
    """What scoring one frame's memorability produced: exact MS, or bounds [low, high]; the crop
    scores so far (5 x 5, NaN = not scored) and the number of crops run by this call."""

    low: float
    high: float
    exact: bool
    m: NDArray[Any] | None = None
    crops_run: int = 0

    @property
    def ms(self) -> float | None:
        return self.low if self.exact else None


@dataclass
class MSState:
    """The MS bounds of one row as the staged selection leaves them."""

    low: float
    high: float
    exact: bool = False
    m: NDArray[Any] | None = None
    crops_run: int = 0
    scored: bool = False  # the CNN looked at this frame at all


#: ``score(row, threshold, known)``: score row's MS, stopping once MS >= threshold is decided
#: (threshold None: exact), continuing from the crop scores ``known`` when given.
ScoreFn = Callable[[int, float | None, NDArray[Any] | None], MSResult]


def _value(ms: float, ss: float, es: float, weights: tuple[float, float, float]) -> float:
    return float(geometric_score(ms, ss, es, weights)[0])


def ms_to_beat(value: float, ss: float, es: float, weights: tuple[float, float, float]) -> float:
    """The MS at which a frame with these SS and ES reaches the score ``value`` (a hint for the
    crop loop; decisions are checked on the score itself)."""
    w = np.asarray(weights, dtype=np.float64)
    used = [i for i in range(3) if w[i] > 0]
    tot = float(w[used].sum())
    if w[0] <= 0:
        return 0.0
    if value <= 0:
        return 0.0
    rest = 0.0
    for i, v in ((1, ss), (2, es)):
        if w[i] > 0:
            if v <= 0:
                return math.inf
            rest += w[i] / tot * math.log(v)
    return math.exp((math.log(value) - rest) / (w[0] / tot))


def _beats(value: float, row: int, lead_value: float, lead_row: int) -> bool:
    """Whether ``row`` with ``value`` wins over the leader (ties to the earlier frame)."""
    return value > lead_value or (value == lead_value and row < lead_row)


def choose_in_segment(
    rows: Sequence[int],
    ss: NDArray[np.float64],
    es: NDArray[np.float64],
    score: ScoreFn,
    *,
    weights: tuple[float, float, float] = (1.0, 1.0, 1.0),
    min_ms: float = 0.0,
    ms_max: NDArray[np.float64] | None = None,
    shortlist: int | None = None,
    digits: int | None = MS_DIGITS,
    prepare: Callable[[list[int]], None] | None = None,
    score_alone: bool = True,
    coord: Sequence[float] | None = None,
    centre_tolerance: float = 0.0,
) -> tuple[int | None, dict[int, MSState]]:
    """The winning row of one segment, and the MS state of every candidate row.

    ``rows``: the segment's candidates (rows passing the SS/ES minimums), ``ss``/``es``: scores
    indexed by row; ``ms_max``: an upper bound on each row's MS (default SS, capped at 1);
    ``min_ms``: the MS minimum a kept frame must reach. Returns (None, ...) when no candidate
    passes ``min_ms`` (a gap). ``digits``: MS is compared as the score records store it (rounded
    to this many decimals; rounding keeps bounds bounds), so the choice is the one full scoring
    makes from its records. ``prepare`` is told the order in which candidates may be scored
    (so frames can be read ahead in that order). ``score_alone=False``: a segment left with one
    candidate (``shortlist=1``, or one passing frame) and no MS minimum keeps it without ResMem
    (its MS would choose nothing; it stays unknown). ``coord``/``centre_tolerance``: each row's
    segment coordinate and the shortlist's preference for the middle of each part
    (:func:`~memlog.selection.segment.shortlist_rows`).
    """
    def q(v: float) -> float:
        return v if digits is None or not math.isfinite(v) else round(v, digits)

    states: dict[int, MSState] = {}
    hi_ms = {r: float(min(1.0, ss[r] + _SLACK) if ms_max is None else ms_max[r]) for r in rows}
    for r in rows:
        states[r] = MSState(0.0, hi_ms[r])
    if weights[0] <= 0 and min_ms <= 0:
        # MS does not count: the best by SS and ES, no CNN at all
        vals = {r: _value(0.0, float(ss[r]), float(es[r]), weights) for r in rows}
        best = min(rows, key=lambda r: (-vals[r], r)) if rows else None
        return best, states
    upper = {r: _value(q(hi_ms[r]), float(ss[r]), float(es[r]), weights) for r in rows}
    todo = list(rows)
    if shortlist is not None:
        todo = shortlist_rows(todo, [upper[r] for r in todo], shortlist,
                              None if coord is None else [coord[r] for r in todo], centre_tolerance)
    order = sorted(todo, key=lambda r: (-upper[r], r))
    if not score_alone and len(order) == 1 and min_ms <= 0:
        return order[0], states
    if prepare is not None:
        prepare(order)
    lead: int | None = None
    lead_value = -math.inf
    for r in order:
        if lead is not None and not _beats(upper[r], r, lead_value, lead):
            break  # sorted by upper bound: no later candidate can win either
        need = min_ms
        if lead is not None:
            to_beat = ms_to_beat(lead_value, float(ss[r]), float(es[r]), weights)
            if math.isfinite(to_beat):  # (infinite: its score is 0 whatever MS; a tie decides by row)
                need = max(need, to_beat)
        st = states[r]
        res = score(r, need if need > 0 else None, None)
        st.scored = True
        st.crops_run += res.crops_run
        st.m = res.m
        if not res.exact:
            st.low, st.high = res.low, res.high
            if q(st.high) < min_ms or (lead is not None and
                                    not _beats(_value(q(st.high), float(ss[r]), float(es[r]), weights), r,
                                               lead_value, lead)):
                continue  # provably below the minimum or the leader
            res = score(r, None, res.m)  # it may win: its exact MS decides
            st.crops_run += res.crops_run
            st.m = res.m
        st.low = st.high = float(res.low)
        st.exact = True
        if q(st.low) < min_ms:
            continue
        v = _value(q(st.low), float(ss[r]), float(es[r]), weights)
        if lead is None or _beats(v, r, lead_value, lead):
            lead, lead_value = r, v
    return lead, states


# -- staticity, staged -------------------------------------------------------------------------------
#: How :func:`detect_in_segment` stages the detector: ``"best"`` (MS does not count: the segment keeps
#: its best frame by SS and ES), ``"shortlist"`` (``--candidates 1``: the one candidate of the
#: shortlist rule), ``"every"`` (the detector on every frame: more candidates, or ES not bounded).
StaticityMode = Literal["best", "shortlist", "every"]

#: Relative slack on the bound and on the decisions: the bound and the upper bounds are computed by
#: the same float functions, this only keeps a last-ulp difference from ever saving a detector run.
_STAGE_SLACK = 1e-9


def staticity_mode(weights: tuple[float, float, float], min_ms: float, shortlist: int | None,
                   es_bounded: bool) -> StaticityMode:
    """Which frames of a segment need the detector (see :data:`StaticityMode`). ``es_bounded``: ES
    is divided by all pixels (``normalize="all"``), so masking can only lower it; with ES divided
    by the static pixels it can rise, and every frame is detected."""
    if not es_bounded:
        return "every"
    if weights[0] <= 0 and min_ms <= 0:
        return "best"
    return "shortlist" if shortlist == 1 else "every"


def detect_in_segment(
    n: int,
    es_static: Sequence[float],
    detect: Callable[[int], tuple[float, float]],
    *,
    mode: StaticityMode,
    weights: tuple[float, float, float] = (1.0, 1.0, 1.0),
    min_ss: float = 0.0,
    min_es: float = 0.0,
    coord: Sequence[float] | None = None,
    centre_tolerance: float = 0.0,
) -> dict[int, tuple[float, float]]:
    """Run the detector (``detect(row) -> (ss, es)``, both as the table holds them: 6 decimals) on
    the rows 0..n-1 of one segment that can still be its candidate; returns the rows it ran on.

    ``es_static[row]``: the row's ES were every pixel static (rounded as ES is), which bounds its
    ES. ``mode`` (:func:`staticity_mode`): ``"best"``, the segment keeps the best frame by the
    geometric score of SS and ES (MS has weight 0): rows in order of their bound until the best
    passing row's score is above every remaining bound; ``"shortlist"``, the candidate of
    :func:`~memlog.selection.segment.shortlist_rows` with ``k=1``: the same for the best upper
    bound (:func:`~memlog.selection.segment.upper_bounds`), then, with ``coord`` and a
    ``centre_tolerance``, the rows within the tolerance by their bound in order of their distance
    to the segment's middle until one is within it by its upper bound (rows as near as each other,
    the frames of a stop, in order of their bound until the best of them is known); ``"every"``:
    every row. A row passes with ``ss >= min_ss`` and ``es >= min_es``; a
    segment without a passing row has every row detected (its gap's reasons are exact).
    """
    got: dict[int, tuple[float, float]] = {}

    def run(r: int) -> tuple[float, float]:
        if r not in got:
            got[r] = detect(r)
        return got[r]

    def passes(r: int) -> bool:
        ss, es = got[r]
        return bool(ss >= min_ss and es >= min_es)

    if mode == "every" or n <= 1:
        for r in range(n):
            run(r)
        return got
    es_b = np.asarray(es_static, dtype=np.float64)
    ms_top = 0.0 if mode == "best" else 1.0  # (with MS weight 0 the MS column is not used)
    bound = geometric_score(np.full(n, ms_top), np.ones(n), es_b, weights) * (1.0 + _STAGE_SLACK)

    def value(r: int) -> float:
        ss, es = got[r]
        if mode == "best":
            return float(geometric_score(np.array([0.0]), np.array([ss]), np.array([es]), weights)[0])
        return float(upper_bounds(np.array([ss]), np.array([es]), weights)[0])

    lead: int | None = None
    lead_value = -math.inf
    for r in sorted(range(n), key=lambda r: (-bound[r], r)):
        if lead is not None and bound[r] < lead_value * (1.0 - _STAGE_SLACK):
            break  # in order of the bound: no later row can reach the leader, or tie with it
        run(r)
        if not passes(r):
            continue
        v = value(r)
        if lead is None or v > lead_value or (v == lead_value and r < lead):
            lead, lead_value = r, v
    if lead is None or mode == "best" or coord is None or centre_tolerance <= 0:
        return got
    # the centre rule: the row nearest the middle among the passing rows within the tolerance
    floor = (1.0 - centre_tolerance) * lead_value
    base = float(np.floor(coord[0]))
    if any(float(np.floor(coord[r])) != base for r in range(n)):  # (one segment lies in one bin)
        for r in range(n):
            run(r)
        return got
    mid = base + 0.5
    dist = [abs(float(coord[r]) - mid) for r in range(n)]  # (as shortlist_rows computes it)
    near = sorted((r for r in range(n) if bound[r] >= floor * (1.0 - _STAGE_SLACK)), key=lambda r: (dist[r], r))
    i = 0
    while i < len(near):
        group = [r for r in near[i:] if dist[r] == dist[near[i]]]  # as near as each other (a stop: many)
        i += len(group)
        # within the group the higher upper bound wins (ties: the earlier row): in order of the bound
        # until no other row can reach the best one within the tolerance
        best: int | None = None
        best_value = -math.inf
        for r in sorted(group, key=lambda r: (-bound[r], r)):
            if best is not None and bound[r] < best_value * (1.0 - _STAGE_SLACK):
                break
            run(r)
            if not passes(r):
                continue
            v = value(r)
            if v >= floor * (1.0 - _STAGE_SLACK) and (best is None or v > best_value or (v == best_value and r < best)):
                best, best_value = r, v
        if best is not None and best_value >= floor * (1.0 + _STAGE_SLACK):
            break  # a row surely within the tolerance: no farther row is the candidate
    return got

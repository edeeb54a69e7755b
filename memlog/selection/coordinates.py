"""Coordinates along the drive that :mod:`memlog.selection.segment` cuts place segments by.

* :func:`distance_coordinate`: metres travelled through the known positions, a position gap's
  frames spread over its estimated length by time (the rule: the segment module's docstring,
  "Position gaps"; :data:`GAP_FACTOR`, :data:`GAP_SPEED_WINDOW_S`);
* :func:`moving_view_steps` and :func:`view_step_length`: how far each step of view change moves
  along the drive (capped at :data:`VIEW_STEP_CAP`); :func:`anchored_view_segments`: segments that
  end where the view left the segment's first frame's by ``view_distance``;
* :func:`without_stops`: a coordinate with the steps into still rows removed (a stop lies at one
  place); :func:`bin_along`: equal bins of a coordinate, as many of them holding a row as asked
  (:func:`count_cut`).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from memlog.scoring.scorer import view_steps
from memlog.selection.table import ScoreTable

__all__ = ["GAP_FACTOR", "GAP_SPEED_WINDOW_S", "VIEW_STEP_CAP", "distance_coordinate", "bin_along",
           "view_step_length", "moving_view_steps", "without_stops", "anchored_view_segments", "count_cut"]


#: A pair of consecutive known positions further apart in time than this many typical fix intervals
#: (the median over the drive) is a position gap; see :mod:`memlog.selection.segment`'s docstring.
GAP_FACTOR = 3.0
#: Seconds of known positions on each side of a gap whose median speed gives the gap's length.
GAP_SPEED_WINDOW_S = 60.0


def _weighted_median(x: NDArray[np.float64], w: NDArray[np.float64]) -> float:
    """The lower weighted median of ``x`` (weights ``w`` > 0, at least one value)."""
    order = np.argsort(x, kind="stable")
    cw = np.cumsum(w[order])
    return float(x[order][int(np.searchsorted(cw, 0.5 * cw[-1]))])


def distance_coordinate(table: ScoreTable) -> tuple[NDArray[np.float64], NDArray[np.bool_], dict[str, Any]]:
    """Position of each row along the drive (metres from 0, non-decreasing; see the docstring of
    :mod:`memlog.selection.segment`), the rows inside position gaps, and facts about the gaps for ``info``."""
    assert table.positions is not None
    n = table.n
    t = (table.t_ns - table.t_ns[0]).astype(np.float64) / 1e9
    rows = np.flatnonzero(table.known_positions())
    s = np.zeros(n)
    in_gap = np.zeros(n, dtype=bool)
    if rows.size < 2:  # no travelled distance can be measured
        return s, in_gap, {"position_gaps": 0}
    a, b = rows[:-1], rows[1:]
    dur = t[b] - t[a]
    length = np.linalg.norm(np.diff(table.positions[rows], axis=0), axis=1)
    limit = GAP_FACTOR * float(np.median(dur))  # 0: most fixes share a time, no rate to go by
    gap = dur > limit if limit > 0 else np.zeros(dur.size, dtype=bool)
    step = ~gap & (dur > 0)  # measured speeds: pairs at the fixes' rate
    st_a, st_b = t[a[step]], t[b[step]]
    speed, weight = length[step] / dur[step], dur[step]

    def speed_around(before: float | None, after: float | None) -> float:
        """Median speed (by time) of the steps within the window before ``before`` and after
        ``after``; the whole drive's when there are none there; 0 without any step."""
        parts = []
        if before is not None:
            parts.append(np.arange(int(np.searchsorted(st_a, before - GAP_SPEED_WINDOW_S, "left")),
                                   int(np.searchsorted(st_b, before, "right"))))
        if after is not None:
            parts.append(np.arange(int(np.searchsorted(st_a, after, "left")),
                                   int(np.searchsorted(st_b, after + GAP_SPEED_WINDOW_S, "right"))))
        sel = np.concatenate(parts) if parts else np.zeros(0, dtype=np.int64)
        if sel.size:
            return _weighted_median(speed[sel], weight[sel])
        if "drive" not in drive_speed:
            drive_speed["drive"] = _weighted_median(speed, weight) if speed.size else 0.0
        return drive_speed["drive"]

    drive_speed: dict[str, float] = {}

    estimated = 0.0
    pair_len = length.copy()
    for g in np.flatnonzero(gap).tolist():
        pair_len[g] = max(float(length[g]), speed_around(float(t[a[g]]), float(t[b[g]])) * float(dur[g]))
        estimated += float(pair_len[g])
        in_gap[a[g] + 1 : b[g]] = True
    lead_s, trail_s = float(t[rows[0]]), float(t[-1] - t[rows[-1]])
    lead_gap, trail_gap = limit > 0 and lead_s > limit, limit > 0 and trail_s > limit
    v_lead = speed_around(None, float(t[rows[0]])) if lead_gap else 0.0
    v_trail = speed_around(float(t[rows[-1]]), None) if trail_gap else 0.0
    s_known = v_lead * lead_s + np.concatenate([[0.0], np.cumsum(pair_len)])
    # rows from the first to the last fix: along their pair in proportion to time
    mid = np.arange(rows[0], rows[-1] + 1)
    k = np.minimum(np.searchsorted(rows, mid, side="right") - 1, a.size - 1)
    frac = np.divide(t[mid] - t[a[k]], dur[k], out=np.zeros(mid.size), where=dur[k] > 0)
    s[mid] = s_known[k] + pair_len[k] * np.clip(frac, 0.0, 1.0)
    s[rows] = s_known
    # before the first fix and after the last one: by time at the speed next to them when they are
    # gaps, else they carry the nearest fix's place
    s[: rows[0]] = v_lead * t[: rows[0]]
    s[rows[-1] + 1 :] = s_known[-1] + v_trail * (t[rows[-1] + 1 :] - t[rows[-1]])
    in_gap[: rows[0]] = lead_gap
    in_gap[rows[-1] + 1 :] = trail_gap
    n_gaps = int(np.count_nonzero(gap)) + int(lead_gap) + int(trail_gap)
    facts: dict[str, Any] = {"position_gaps": n_gaps}
    if n_gaps:
        facts["gap_s"] = float(dur[gap].sum()) + lead_s * lead_gap + trail_s * trail_gap
        facts["gap_length_m"] = estimated + v_lead * lead_s + v_trail * trail_s
    return s, in_gap, facts


def bin_along(value: NDArray[np.float64], spacing: float | None, n_bins: int | None) -> tuple[NDArray[np.int64], float]:
    """Bins of a non-decreasing coordinate (time or path length from 0) and their width: every
    ``spacing``; else ``n_bins`` segments (:func:`count_cut`); one bin, width 0, when the span is 0."""
    span = float(value[-1])
    if spacing is not None:
        return np.floor(value / spacing).astype(np.int64), float(spacing)
    if span > 0:
        assert n_bins is not None
        parts = count_cut(value, n_bins)
        return _equal_parts(value, parts), span / parts
    return np.zeros(len(value), dtype=np.int64), 0.0


def _equal_parts(value: NDArray[np.float64], parts: int) -> NDArray[np.int64]:
    """Each row's part when the span of ``value`` is cut into ``parts`` equal parts (the end in the last)."""
    return np.clip(np.floor(value * parts / float(value[-1])).astype(np.int64), 0, parts - 1)


def _held(value: NDArray[np.float64], parts: int) -> int:
    """How many of ``parts`` equal parts of the span hold a row (``value`` non-decreasing)."""
    ids = _equal_parts(value, parts)
    return 1 + int(np.count_nonzero(np.diff(ids)))


#: The finest cut :func:`count_cut` makes (parts of a 2**-40 share of the drive).
MAX_PARTS = 2**40


def count_cut(value: NDArray[np.float64], n: int) -> int:
    """How many equal parts the span of a non-decreasing coordinate is cut into so that ``n`` of
    them hold a row: ``n`` itself unless a step of the coordinate is longer than a part (the robot
    covered two parts between frames: a fast stretch by distance, a sudden change of view, a
    position gap), which leaves a part without a row; then, by doubling and bisection, a number of
    parts of which at least ``n`` hold a row while one part fewer leaves fewer than ``n`` (a few
    more than ``n`` where one more part gains several), or, when the coordinate has fewer than ``n``
    distinct values, as many as it has (at most :data:`MAX_PARTS` parts: values closer than a
    part of that many are one place). So a map asked for ``n`` frames (``--keep-fraction``) gets
    them: its frames go to the rest of the drive, not missing where it moved fast (on the Stromovka
    drive pair with odometry, half the frames: 64 instead of 70 kept before this rule)."""
    target = min(n, 1 + int(np.count_nonzero(np.diff(value))))
    if _held(value, n) >= target:
        return n
    lo, hi = n, 2 * n
    while _held(value, hi) < target and hi < MAX_PARTS:
        lo, hi = hi, 2 * hi
    while hi - lo > 1:  # _held(lo) < target <= _held(hi)
        mid = (lo + hi) // 2
        lo, hi = (lo, mid) if _held(value, mid) >= target else (mid, hi)
    return hi


#: A step of view change counts at most this chord (cosine similarity 0.875 of consecutive view
#: vectors): a sudden change of the whole view, a tunnel's mouth or a flash of light, is not a long
#: way. Chosen on the Nordland drive variants (``benchmarks/drive_maps.py``: mean map-only R@1 of
#: eight maps 0.551 uncapped, 0.578 capped at 0.5; a cap relative to the drive's median step did as
#: well there but counts every step alike once more than half the drive crawls).
VIEW_STEP_CAP = 0.5


def view_step_length(d: NDArray[np.float64]) -> NDArray[np.float64]:
    """How far each step of view change ``d`` (cosine distance of consecutive view vectors) moves
    along the drive: its chord ``sqrt(2 d)``, at most :data:`VIEW_STEP_CAP`."""
    chord = np.sqrt(2.0 * np.clip(d, 0.0, None))
    return np.asarray(np.minimum(chord, VIEW_STEP_CAP), dtype=np.float64)


def moving_view_steps(view: ArrayLike, still: NDArray[np.bool_]) -> NDArray[np.float64]:
    """How much the view changed at each row that moved since the previous row that moved (cosine
    distance, :func:`~memlog.scoring.scorer.view_steps` of the moving rows; 0 at still rows). A
    row that ends a standing run is measured from the run's first frame, so a crawl whose every
    step is below the noise counts the whole drift it made, as the same stretch driven faster does
    (not only its last step)."""
    v = np.asarray(view, dtype=np.float64)
    out = np.zeros(len(v))
    moving = np.flatnonzero(~np.asarray(still, dtype=bool))
    if len(moving) > 1:
        out[moving[1:]] = view_steps(v[moving])[1:]
    return out


def without_stops(coord: NDArray[np.float64], still: NDArray[np.bool_]) -> NDArray[np.float64]:
    """``coord`` with the steps into still rows removed (a stop lies at one place)."""
    if not still.any():
        return coord
    step = np.diff(coord, prepend=coord[:1])
    return np.asarray(np.cumsum(np.where(still, 0.0, step)), dtype=np.float64)


def anchored_view_segments(table: ScoreTable, view_distance: float) -> NDArray[np.int64]:
    """Segment ids by view change: new segment when 1 - <d_i, d_anchor> > view_distance, with
    ``d`` the view vectors (else the descriptors; blank rows unknown)."""
    n = table.n
    if table.view is not None:
        d = table.view
        known = ~table.blank_view()
    else:
        assert table.descriptors is not None
        d = table.descriptors
        known = table.known_descriptors()
    seg = np.zeros(n, dtype=np.int64)
    sid = 0
    anchor = -1  # row of the segment's first frame with a known descriptor
    start = 0
    while start < n:
        if anchor < 0:
            if known[start]:
                anchor = start
            seg[start] = sid
            start += 1
            continue
        block = 32
        found = -1
        i = start
        while i < n and found < 0:
            j = min(n, i + block)
            with np.errstate(invalid="ignore"):
                dist = 1.0 - d[i:j].astype(np.float64) @ d[anchor].astype(np.float64)
            over = np.flatnonzero(known[i:j] & (dist > view_distance))
            if over.size:
                found = i + int(over[0])
                j = found
            seg[i:j] = sid
            i = j
            block *= 2
        if found < 0:
            break
        sid += 1
        seg[found] = sid
        anchor = found
        start = found + 1
    return seg

"""Coverage-keeping selection: one best frame per place segment of the drive.

The drive is cut into consecutive place segments, by one of

* ``"distance"``: travelled distance along the known positions, a new segment every
  ``spacing_m`` metres; across a gap in the positions the segments are cut by time (below);
* ``"time"``: log time, a new segment every ``spacing_s`` seconds;
* ``"count"``: frame count, ``spacing_frames`` frames per segment;
* ``"view"``: how much the view changed along the drive: the table's view vectors
  (``ScoreTable.view``, a 32 x 16 zero-mean thumbnail of every frame) give each step from one
  frame to the next its chord length ``sqrt(2 * cosine distance)`` (about proportional to how far
  the camera moved for small steps), capped at :data:`VIEW_STEP_CAP` (a sudden change of the
  whole view is not a long way; a step that ends a standing run is measured from the run's first
  frame, so a crawl below the noise counts its whole drift), and the drive's total view change is split into
  equal parts like a path length; without a size (``keep_fraction``) and with ``view_distance``, a new
  segment starts instead when the cosine distance to the segment's first frame's view vector (its
  descriptor in a table without view vectors) exceeds ``view_distance``.

With ``keep_fraction=F`` instead of a spacing, the number of segments is
``S = max(1, floor(F*N + 0.5))`` and the drive's total length (metres, view change, seconds or
frames) is split into S equal parts; ``by="auto"`` then uses distance when positions exist and
the robot moved, else the view change when the table has view vectors, else time when the
timestamps span > 0, else frame count. Bins that hold no frame (the robot jumped, a time gap)
are not segments.

Stops. A frame that stood still (:func:`memlog.scoring.motion.find_stops`, the rule matching uses
too: by the log's own motion when it knows every frame of the drive (odometry, poses, twists,
GNSS: the table's ``motion``), else by the images: its view within ``still_distance`` of its
stop's first frame, a standing camera's sensor noise only; both measure from the stop's first
frame, so a crawl is not a stop) adds nothing to the coordinate, whichever it is (distance, view
change or time): the frames of a stop lie at one place of the drive and fall in one segment, so a
stop never gets more than one map frame (``info["still_frames"]`` counts the frames that stood
still; ``info["stops_from"]`` names the motion topic when the log's motion decided). GNSS jitter
of a standing robot, or the seconds it stood, do not make segments.

Position gaps (``"distance"``). The coordinate is the path length through the known positions
(rows with a NaN or infinite coordinate are unknown); a row between two consecutive fixes is placed between
them in proportion to its time. A pair of consecutive fixes is a *gap* when they are more than
``GAP_FACTOR = 3`` typical fix intervals apart in time (the median interval between consecutive
fixes over the drive: one or two missed fixes are not a gap, a tunnel is), whether or not frames lie
between them; so are the rows before the first fix and after the last one when they last that long.
A gap's length is the larger of the straight line between its fixes and ``v * duration``, where
``v`` is the median speed (weighted by time) of the fix-to-fix steps within
``GAP_SPEED_WINDOW_S = 60`` s before and after it (the whole drive's median speed when there are
none; 0 without any step); its frames are spread over that length in proportion to time. So a gap
is cut by time, one segment every ``spacing / v`` seconds (``spacing`` being ``spacing_m``, or the
segment length ``path_length_m / S`` with ``keep_fraction``): it gets as many segments per second as
the drive around it, not one for minutes of driving. ``info`` then says ``position_gaps`` (how
many), ``gap_s`` and ``gap_length_m`` (their duration and estimated length, which
``path_length_m`` includes) and ``time_segments`` (segments holding a row inside a gap). A time jump
between two consecutive frames that both have a fix holds no frame to cut; only its length (and so
the later rows' coordinate) is the gap rule's.

Each segment keeps its best frame by a combined score among the frames that pass the
minimum thresholds ``min_ms``/``min_ss``/``min_es`` (NaN fails); a segment none of whose
frames passes is dropped and reported as a :class:`~memlog.selection.table.Gap`. A frame whose SS
and ES are both unknown (the staged map ran no detector on it because it could not be its
segment's candidate, :func:`memlog.selection.staged.detect_in_segment`) is dropped for its
segment ("segment") when the segment keeps a frame.

Candidates (``shortlist=K``, ``memlog map --candidates K``, default 1): before MS is known each of
K parts of a segment gives one candidate, by its upper bound; with ``centre_tolerance`` (default
0.03) the one nearest the middle of the part's share of the segment along the coordinate the
segments were cut by (:func:`cut_segments`), among the frames within that fraction of the part's
best bound. On the Nordland drive variants (``benchmarks/drive_maps.py``, sequences) this beat the
best bound alone on all eight maps (+0.004 to +0.054 R@1, mean +0.026): sequence matching pays
for irregular gaps between map frames, and within 3 % the cheap scores say little. The exact
selection (no shortlist) keeps the best frame by the score.

Distinctiveness (``distinct_weight`` > 0; the table's ``ds`` column, see
:mod:`memlog.selection.distinctiveness`) enters the combined score as a fourth criterion with
that weight (``weights=(0, 0, 0)`` with a positive ``distinct_weight``: distinctiveness alone).

Combined score. The default ``combine="geometric"`` is the weighted geometric mean of the raw
scores, (MS^a SS^b ES^c)^(1/(a+b+c)); its per-segment argmax does not change when one criterion
is rescaled by a constant (so ES being low everywhere on small frames does not matter), and a
zero in any criterion (a fully dynamic view, a black frame) zeroes the frame. ``combine="rank"``
is the weighted mean of the three per-criterion percentile ranks within the drive (mid-rank of
ties, in (0, 1)), invariant to any increasing transform; a criterion that is constant over the
drive (SS == 1.0 everywhere) ranks 0.5 everywhere and drops out. Ties go to the earliest frame
of the segment.

Defaults (:data:`SEGMENT_DEFAULTS`, the one source every entry point reads; chosen on the shared
Nordland slice, summer -> winter, thumbnail descriptor; the grid is
``benchmarks/selection_table.py --tune``): geometric beat rank at 25 % of the frames (R@1
0.104 vs 0.092 map-only) and matched it at 50/75 %; equal weights were as good as any other
weighting tried; minimum scores only for staticity (``min_ss=0.1``: a view almost fully covered
by vehicles or people is no place), because dropping dark frames (``min_es=0.05``) left tunnel
stretches without a frame and cost recall.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import asdict, dataclass
from collections.abc import Sequence
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from memlog.errors import ConfigError
from memlog.scoring.motion import MOTION_KINDS, STILL_DISTANCE, find_stops
from memlog.scoring.scorer import view_steps
from memlog.selection._checks import finite_number, fraction, positive_int, positive_number
from memlog.selection.paper import codes_to_reasons, first_failing
from memlog.selection.table import CRITERIA, Gap, ScoreTable, Selection

__all__ = ["SegmentConfig", "SegmentDefaults", "SEGMENT_DEFAULTS", "select_segments", "segment_ids", "cut_segments",
           "shortlist_rows", "upper_bounds", "MS_DIGITS", "combined_score", "geometric_score", "percentile_ranks"]

SegmentBy = Literal["auto", "distance", "time", "count", "view"]
Combine = Literal["rank", "geometric"]
_BY = ("auto", "distance", "time", "count", "view")
_COMBINE = ("rank", "geometric")


@dataclass(frozen=True)
class SegmentDefaults:
    """The segment selector's defaults (chosen on the shared Nordland slice: module docstring).

    The one source: :class:`SegmentConfig`, :func:`combined_score`, :func:`select_segments` without
    a config, ``SELECTORS["segment"]`` (:mod:`memlog.selection.selectors`) and
    :class:`~memlog.selection.config.SelectionConfig` all read :data:`SEGMENT_DEFAULTS`.
    ``keep_fraction`` is the size used when no spacing is given.
    """

    by: SegmentBy = "auto"
    keep_fraction: float = 0.25
    view_distance: float = 0.3
    still_distance: float = STILL_DISTANCE
    min_ms: float = 0.0
    min_ss: float = 0.1
    min_es: float = 0.0
    weights: tuple[float, float, float] = (1.0, 1.0, 1.0)  # (ms, ss, es)
    combine: Combine = "geometric"
    distinct_weight: float = 0.0
    centre_tolerance: float = 0.03

    def to_dict(self) -> dict[str, Any]:
        """The defaults as a plain dict (``weights`` a tuple), in field order."""
        return asdict(self)


#: The segment defaults every entry point reads (see :class:`SegmentDefaults`).
SEGMENT_DEFAULTS = SegmentDefaults()


@dataclass(frozen=True)
class SegmentConfig:
    """Settings of :func:`select_segments` (set exactly one of ``keep_fraction``,
    ``spacing_m``, ``spacing_s``, ``spacing_frames``; ``by="view"``: ``keep_fraction``, or
    none and ``view_distance``).

    ``shortlist=K`` (``memlog map --candidates K``): a segment keeps the best of only K
    candidates, the best of each of K equal parts of it by the score's upper bound before MS is
    known (MS at most SS, or 1 with ``ms_bound="one"``: MS normalised by the static area), so the
    choice is the one the staged selection makes while running ResMem on those K frames only
    (:mod:`memlog.selection.staged`); None: every frame is a candidate. ``centre_tolerance``: a
    part's candidate is, among its rows whose upper bound is within this fraction of the part's
    best, the one nearest the middle of the part along the segment coordinate (see
    :func:`shortlist_rows`); 0: the best by the bound alone. ``still_distance``: the image rule's
    stop threshold (:func:`memlog.scoring.motion.find_stops`, default
    :data:`memlog.scoring.motion.STILL_DISTANCE`; the log's motion decides instead when it knows
    every frame); 0: no stops, whatever the source."""

    by: SegmentBy = SEGMENT_DEFAULTS.by
    keep_fraction: float | None = None
    spacing_m: float | None = None
    spacing_s: float | None = None
    spacing_frames: int | None = None
    view_distance: float = SEGMENT_DEFAULTS.view_distance
    still_distance: float = SEGMENT_DEFAULTS.still_distance
    min_ms: float = SEGMENT_DEFAULTS.min_ms
    min_ss: float = SEGMENT_DEFAULTS.min_ss
    min_es: float = SEGMENT_DEFAULTS.min_es
    weights: tuple[float, float, float] = SEGMENT_DEFAULTS.weights  # (ms, ss, es)
    combine: Combine = SEGMENT_DEFAULTS.combine
    distinct_weight: float = SEGMENT_DEFAULTS.distinct_weight
    centre_tolerance: float = SEGMENT_DEFAULTS.centre_tolerance
    shortlist: int | None = None
    ms_bound: Literal["ss", "one"] = "ss"

    def __post_init__(self) -> None:
        if self.shortlist is not None:
            positive_int("shortlist", self.shortlist)
        if self.ms_bound not in ("ss", "one"):
            raise ConfigError(f"ms_bound must be 'ss' or 'one', got {self.ms_bound!r}")
        if self.by not in _BY:
            raise ConfigError(f"segment by must be one of {_BY}, got {self.by!r}")
        if self.combine not in _COMBINE:
            raise ConfigError(f"segment combine must be one of {_COMBINE}, got {self.combine!r}")
        sizes = {
            k: getattr(self, k)
            for k in ("keep_fraction", "spacing_m", "spacing_s", "spacing_frames")
            if getattr(self, k) is not None
        }
        v = finite_number("still_distance", self.still_distance)
        if not 0.0 <= v < 2.0:
            raise ConfigError(f"still_distance must be in [0, 2), got {self.still_distance!r}")
        if self.by == "view" and set(sizes) - {"keep_fraction"}:
            raise ConfigError(f"segment by='view' is sized by keep_fraction (or view_distance); unset "
                              f"{sorted(set(sizes) - {'keep_fraction'})}")
        if self.by == "view" and not sizes:
            v = finite_number("view_distance", self.view_distance)
            if not 0.0 < v <= 2.0:
                raise ConfigError(f"view_distance must be in (0, 2], got {self.view_distance!r}")
        elif len(sizes) != 1:
            raise ConfigError(
                "segment selection needs exactly one of keep_fraction, spacing_m, spacing_s, "
                f"spacing_frames; got {sorted(sizes) or 'none'}"
            )
        if self.keep_fraction is not None:
            fraction("keep_fraction", self.keep_fraction)
        implied = {"spacing_m": "distance", "spacing_s": "time", "spacing_frames": "count"}
        for key, by in implied.items():
            if getattr(self, key) is None:
                continue
            if key == "spacing_frames":
                positive_int(key, self.spacing_frames)
            else:
                positive_number(key, getattr(self, key))
            if self.by not in ("auto", by):
                raise ConfigError(f"{key} segments by {by}, but by={self.by!r}")
        for key in ("min_ms", "min_ss", "min_es"):
            finite_number(key, getattr(self, key))
        tol = finite_number("centre_tolerance", self.centre_tolerance)
        if not 0.0 <= tol <= 1.0:
            raise ConfigError(f"centre_tolerance must be in [0, 1], got {self.centre_tolerance!r}")
        w = tuple(self.weights)
        if len(w) != 3:
            raise ConfigError(f"weights must be three numbers (ms, ss, es), got {self.weights!r}")
        wf = [finite_number("weight", x) for x in w]
        dw = finite_number("distinct_weight", self.distinct_weight)
        if min(wf) < 0 or dw < 0 or sum(wf) + dw <= 0:
            raise ConfigError(f"weights must be >= 0 with a positive sum (distinct_weight included), got "
                              f"{self.weights!r} and distinct_weight {self.distinct_weight!r}")

    def to_dict(self) -> dict[str, Any]:
        """Settings as a plain dict."""
        d = asdict(self)
        d["weights"] = list(self.weights)
        return d


def percentile_ranks(x: NDArray[np.float64]) -> NDArray[np.float64]:
    """Mid-rank percentile of each value among the finite values: (#less + #equal/2) / n.

    In (0, 1); ties share a rank; NaN stays NaN.
    """
    out = np.full(x.shape, np.nan)
    ok = np.isfinite(x)
    v = np.sort(x[ok])
    if v.size:
        left = np.searchsorted(v, x[ok], side="left")
        right = np.searchsorted(v, x[ok], side="right")
        out[ok] = (left + right) / (2.0 * v.size)
    return out


def combined_score(
    table: ScoreTable,
    weights: tuple[float, float, float] = SEGMENT_DEFAULTS.weights,
    combine: Combine = SEGMENT_DEFAULTS.combine,
    distinct_weight: float = SEGMENT_DEFAULTS.distinct_weight,
) -> NDArray[np.float64]:
    """Per-frame combined score of (MS, SS, ES) with weights (ms, ss, es), and of the
    distinctiveness DS with ``distinct_weight``; NaN if any used score is NaN. Defaults: those of
    :data:`SEGMENT_DEFAULTS` (the geometric mean); see the module docstring for the choice."""
    if distinct_weight > 0 and table.ds is None:
        raise ConfigError("distinct_weight needs the table's distinctiveness (ds) column")
    if combine == "geometric":
        return geometric_score(table.ms, table.ss, table.es, weights, table.ds, distinct_weight)
    if combine == "rank":
        w = np.asarray(tuple(weights) + (distinct_weight,), dtype=np.float64)
        nan = np.full(table.n, np.nan)
        sources = (table.ms, table.ss, table.es, table.ds if table.ds is not None else nan)
        used = [i for i in range(4) if w[i] > 0]
        wu = w[used][:, None] / w[used].sum()
        ranks = np.stack([percentile_ranks(sources[i]) for i in used])
        return np.asarray((wu * ranks).sum(axis=0), dtype=np.float64)
    raise ConfigError(f"combine must be one of {_COMBINE}, got {combine!r}")


def geometric_score(ms: ArrayLike, ss: ArrayLike, es: ArrayLike,
                    weights: tuple[float, float, float] = (1.0, 1.0, 1.0),
                    ds: ArrayLike | None = None, distinct_weight: float = 0.0) -> NDArray[np.float64]:
    """The weighted geometric mean (MS^a SS^b ES^c DS^d)^(1/(a+b+c+d)), element-wise; increasing
    in each score, so bounds on MS give bounds on it (the staged selection relies on this)."""
    w = np.asarray(tuple(weights) + (distinct_weight,), dtype=np.float64)
    used = [i for i in range(4) if w[i] > 0]
    wu = w[used][:, None] / w[used].sum()
    sources = (ms, ss, es, ds if ds is not None else np.nan)
    cols = np.stack([np.atleast_1d(np.asarray(sources[i], dtype=np.float64)) for i in used])
    with np.errstate(divide="ignore", invalid="ignore"):
        logs = np.log(np.clip(cols, 0.0, None))
        return np.asarray(np.exp((wu * logs).sum(axis=0)), dtype=np.float64)


#: A pair of consecutive known positions further apart in time than this many typical fix intervals
#: (the median over the drive) is a position gap; see the module docstring.
GAP_FACTOR = 3.0
#: Seconds of known positions on each side of a gap whose median speed gives the gap's length.
GAP_SPEED_WINDOW_S = 60.0


def _weighted_median(x: NDArray[np.float64], w: NDArray[np.float64]) -> float:
    """The lower weighted median of ``x`` (weights ``w`` > 0, at least one value)."""
    order = np.argsort(x, kind="stable")
    cw = np.cumsum(w[order])
    return float(x[order][int(np.searchsorted(cw, 0.5 * cw[-1]))])


def _distance_coordinate(table: ScoreTable) -> tuple[NDArray[np.float64], NDArray[np.bool_], dict[str, Any]]:
    """Position of each row along the drive (metres from 0, non-decreasing; see the module
    docstring), the rows inside position gaps, and facts about the gaps for ``info``."""
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


def _bin_along(value: NDArray[np.float64], spacing: float | None, n_bins: int | None) -> tuple[NDArray[np.int64], float]:
    """Bins of a non-decreasing coordinate (time or path length from 0) and their width: every
    ``spacing``, else ``n_bins`` equal parts of its span (clipped to n_bins - 1); one bin, width
    0, when the span is 0."""
    span = float(value[-1])
    if spacing is not None:
        return np.floor(value / spacing).astype(np.int64), float(spacing)
    if span > 0:
        assert n_bins is not None
        return np.clip(np.floor(value * n_bins / span).astype(np.int64), 0, n_bins - 1), span / n_bins
    return np.zeros(len(value), dtype=np.int64), 0.0


#: A step of view change counts at most this chord (cosine similarity 0.875 of consecutive view
#: vectors): a sudden change of the whole view, a tunnel's mouth or a flash of light, is not a long
#: way. Chosen on the Nordland drive variants (``benchmarks/drive_maps.py``: mean map-only R@1 of
#: eight maps 0.551 uncapped, 0.578 capped at 0.5; a cap relative to the drive's median step did as
#: well there but counts every step alike once more than half the drive crawls).
VIEW_STEP_CAP = 0.5


def _view_step(d: NDArray[np.float64]) -> NDArray[np.float64]:
    """How far each step of view change ``d`` (cosine distance of consecutive view vectors) moves
    along the drive: its chord ``sqrt(2 d)``, at most :data:`VIEW_STEP_CAP`."""
    chord = np.sqrt(2.0 * np.clip(d, 0.0, None))
    return np.asarray(np.minimum(chord, VIEW_STEP_CAP), dtype=np.float64)


def _moving_steps(view: ArrayLike, still: NDArray[np.bool_]) -> NDArray[np.float64]:
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


def _without_stops(coord: NDArray[np.float64], still: NDArray[np.bool_]) -> NDArray[np.float64]:
    """``coord`` with the steps into still rows removed (a stop lies at one place)."""
    if not still.any():
        return coord
    step = np.diff(coord, prepend=coord[:1])
    return np.asarray(np.cumsum(np.where(still, 0.0, step)), dtype=np.float64)


def _view_segments(table: ScoreTable, view_distance: float) -> NDArray[np.int64]:
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


def segment_ids(table: ScoreTable, config: SegmentConfig) -> tuple[NDArray[np.int64], dict[str, Any]]:
    """Place segment of each row (0..S-1, non-decreasing) and a description of the cut."""
    seg, _coord, info = cut_segments(table, config)
    return seg, info


def cut_segments(table: ScoreTable, config: SegmentConfig
                 ) -> tuple[NDArray[np.int64], NDArray[np.float64] | None, dict[str, Any]]:
    """:func:`segment_ids` and where each row lies in its segment's stretch of the drive: the
    coordinate the segments were cut along (metres, view change, time or rows, stops left out) in
    units of the segment length, so the segment of bin ``b`` covers ``[b, b + 1)`` and its middle
    is ``b + 0.5`` (non-decreasing); None for anchored view segments (not cut along a coordinate)."""
    n = table.n
    info: dict[str, Any] = {}
    coord: NDArray[np.float64] | None = None
    if n == 0:
        return np.zeros(0, dtype=np.int64), None, {"by": config.by, "n_segments": 0}
    by = config.by
    if by == "auto":
        if config.spacing_m is not None:
            by = "distance"
        elif config.spacing_s is not None:
            by = "time"
        elif config.spacing_frames is not None:
            by = "count"
        else:
            moved = table.positions is not None and float(_distance_coordinate(table)[0][-1]) > 0.0
            by = "distance" if moved else "view" if table.view is not None else (
                "time" if table.t_ns[-1] > table.t_ns[0] else "count")
    if by == "distance" and table.positions is None:
        raise ConfigError("segment by='distance' needs positions, but the score table has none")
    anchored = by == "view" and config.keep_fraction is None
    if anchored and table.descriptors is None and table.view is None:
        raise ConfigError("segment by='view' with view_distance needs view vectors or descriptors, but the score "
                          "table has neither")
    if by == "view" and not anchored and table.view is None:
        raise ConfigError("segment by='view' needs the frames' view vectors, but the score table has none")
    stops = find_stops(n, table.view, table.motion, config.still_distance)
    still = stops.still
    if table.view is not None or stops.source in MOTION_KINDS:
        info["still_frames"] = int(still.sum())
    if stops.source in MOTION_KINDS:
        info["stops_from"] = {"source": stops.source, "topic": stops.topic}
    n_seg = (
        max(1, int(np.floor(config.keep_fraction * n + 0.5)))
        if config.keep_fraction is not None
        else None
    )
    raw: NDArray[np.int64]
    width = 0.0
    if by == "count":
        along = np.arange(n, dtype=np.float64) + 0.5  # row i covers [i, i + 1)
        if config.spacing_frames is not None:
            raw = np.arange(n, dtype=np.int64) // config.spacing_frames
            width = float(config.spacing_frames)
            info["spacing_frames"] = config.spacing_frames
        else:
            assert n_seg is not None
            raw = (np.arange(n, dtype=np.int64) * n_seg) // n
            width = n / n_seg
            info["spacing_frames"] = n / n_seg
    elif by == "time":
        dt = _without_stops((table.t_ns - table.t_ns[0]).astype(np.float64), still)
        spacing = None if config.spacing_s is None else config.spacing_s * 1e9
        raw, width = _bin_along(dt, spacing, n_seg)
        along = dt
        if width == 0.0:
            info["note"] = "timestamps span 0 s: one segment"
        info["spacing_s"] = width / 1e9
    elif by == "distance":
        s, in_gap, facts = _distance_coordinate(table)
        s = _without_stops(s, still)
        info["path_length_m"] = float(s[-1])
        info.update(facts)
        raw, width = _bin_along(s, config.spacing_m, n_seg)
        along = s
        if width == 0.0:
            info["note"] = "the robot did not move (path length 0 m): one segment"
        info["spacing_m"] = width
    elif anchored:
        raw = _view_segments(table, config.view_distance)
        info["view_distance"] = config.view_distance
    else:  # view change
        assert table.view is not None
        c = np.cumsum(_view_step(np.nan_to_num(_moving_steps(table.view, still), nan=0.0)))
        raw, width = _bin_along(c, None, n_seg)
        along = c
        info["view_change"] = float(c[-1])
        if width == 0.0:
            info["note"] = "the view never changed: one segment"
    if not anchored:
        # in segment lengths, within the row's own bin (the last bin holds the end of the drive);
        # a drive of length 0 is one segment, every row at its middle
        coord = np.asarray(np.clip(along / width, raw, raw + 1.0 - 1e-9) if width > 0 else raw + 0.5, np.float64)
    # relabel to consecutive ids (bins without frames are not segments)
    change = np.concatenate([[0], (np.diff(raw) != 0).astype(np.int64)])
    seg = np.cumsum(change).astype(np.int64)
    info["by"] = by
    info["n_segments"] = int(seg[-1]) + 1
    if by == "distance":
        info["time_segments"] = int(np.unique(seg[in_gap]).size)
    if n_seg is not None:
        info["n_bins"] = n_seg
    return seg, coord, info


#: MS as score records store it (decimals): the staged choice compares it so, and so does the shortlist.
MS_DIGITS = 6


def shortlist_rows(rows: Sequence[int], upper: Sequence[float], k: int,
                   coord: Sequence[float] | None = None, tolerance: float = 0.0) -> list[int]:
    """``k`` rows by ``upper``, spread over the segment: the rows are cut into ``k`` consecutive
    parts and each part gives one row, its best by ``upper`` (ties: earlier row). With ``coord``
    (each row's place in its segment, in segment lengths as :func:`cut_segments` gives it: the
    segment covers ``[b, b + 1)``) and ``tolerance`` > 0, part ``j`` of ``k`` gives the row nearest
    its share's middle ``b + (j + 0.5) / k`` among its rows whose ``upper`` is at least
    ``(1 - tolerance)`` times the part's best (ties: the higher ``upper``, then the earlier row).
    So a map keeps evenly spaced frames where the cheap scores hardly differ, and a clearly better
    frame where they do."""
    rows = list(rows)
    if k >= len(rows):
        return rows
    parts = np.array_split(np.arange(len(rows)), k)
    base = float(np.floor(coord[0])) if coord is not None and rows else 0.0
    out = []
    for j, p in enumerate(parts):
        idx = p.tolist()
        best = min(idx, key=lambda i: (-upper[i], rows[i]))
        if coord is not None and tolerance > 0:
            floor = (1.0 - tolerance) * upper[best]
            mid = base + (j + 0.5) / k
            best = min((i for i in idx if upper[i] >= floor),
                       key=lambda i: (abs(coord[i] - mid), -upper[i], rows[i]))
        out.append(rows[best])
    return sorted(out)


def upper_bounds(ss: ArrayLike, es: ArrayLike, weights: tuple[float, float, float],
                 ms_bound: str = "ss") -> NDArray[np.float64]:
    """The largest geometric score each frame can reach before its MS is known (MS <= SS, or 1)."""
    ssa = np.asarray(ss, dtype=np.float64)
    hi = np.ones_like(ssa) if ms_bound == "one" else np.minimum(1.0, ssa + 1e-9)
    return geometric_score(np.round(hi, MS_DIGITS), ssa, es, weights)


def _shortlisted(table: ScoreTable, seg: NDArray[np.int64], coord: NDArray[np.float64] | None,
                 cfg: SegmentConfig) -> NDArray[np.bool_]:
    """The rows that are candidates of their segment under ``cfg.shortlist`` (all when None, or when
    MS does not count at all)."""
    n = table.n
    if cfg.shortlist is None or (cfg.weights[0] <= 0 and cfg.min_ms <= 0):
        return np.ones(n, dtype=bool)
    with np.errstate(invalid="ignore"):
        cheap_ok = (table.ss >= cfg.min_ss) & (table.es >= cfg.min_es)
    upper = upper_bounds(table.ss, table.es, cfg.weights, cfg.ms_bound)
    out = np.zeros(n, dtype=bool)
    starts = np.flatnonzero(np.concatenate([[True], seg[1:] != seg[:-1]])) if n else np.zeros(0, np.int64)
    ends = np.concatenate([starts[1:], [n]])
    for a, e in zip(starts.tolist(), ends.tolist()):
        rows = [r for r in range(a, e) if cheap_ok[r]]
        out[shortlist_rows(rows, [float(upper[r]) for r in rows], cfg.shortlist,
                           None if coord is None else [float(coord[r]) for r in rows], cfg.centre_tolerance)] = True
    return out


def select_segments(table: ScoreTable, config: SegmentConfig | None = None) -> Selection:
    """Keep the best frame (by :func:`combined_score`) of each place segment among those
    passing the minimum thresholds; segments with no passing frame become gaps. Without a
    config: :data:`SEGMENT_DEFAULTS` (``keep_fraction`` 0.25)."""
    cfg = config if config is not None else SegmentConfig(keep_fraction=SEGMENT_DEFAULTS.keep_fraction)
    n = table.n
    seg, coord, info = cut_segments(table, cfg)
    code = first_failing(table, cfg.min_ms, cfg.min_ss, cfg.min_es)
    score = combined_score(table, cfg.weights, cfg.combine, cfg.distinct_weight)
    short = np.ones(n, dtype=bool)
    if cfg.shortlist is not None:
        short = _shortlisted(table, seg, coord, cfg)
        if cfg.min_ms <= 0 and n:
            # a segment's only candidate is kept whatever its MS: an unknown MS (ResMem not run
            # because it would not choose anything, see staged.choose_in_segment) does not fail it
            alone = short & (np.bincount(seg[short], minlength=int(seg.max()) + 1)[seg] == 1)
            code = np.where(alone & np.isnan(table.ms) & (code == 3), 0, code).astype(np.int8)
        info["shortlist"] = cfg.shortlist
    passing = (code == 0) & short  # a frame that was not a candidate is dropped for its "segment"
    keep = np.zeros(n, dtype=bool)
    gaps: list[Gap] = []
    if n:
        # a passing frame whose score is unknown (its segment's only candidate, MS not run) still
        # ranks above every frame that does not pass
        eff = np.where(passing, np.where(np.isfinite(score), score, -np.finfo(np.float64).max), -np.inf)
        rows = np.arange(n)
        order = np.lexsort((rows, -eff, seg))  # by segment, best score first, earliest first
        first_in_seg = np.concatenate([[True], seg[order][1:] != seg[order][:-1]])
        best = order[first_in_seg]
        keep[best[passing[best]]] = True
        starts = np.flatnonzero(np.concatenate([[True], seg[1:] != seg[:-1]]))
        ends = np.concatenate([starts[1:], [n]]) - 1
        for sid, b in enumerate(best.tolist()):
            if passing[b]:
                continue
            a, e = int(starts[sid]), int(ends[sid])
            counts = Counter(CRITERIA[c - 1] for c in code[a : e + 1].tolist() if 0 < c <= len(CRITERIA))
            reason = max(CRITERIA, key=lambda c: (counts.get(c, 0), -CRITERIA.index(c)))
            gaps.append(
                Gap(
                    segment=sid,
                    start_index=int(table.index[a]),
                    end_index=int(table.index[e]),
                    start_t_ns=int(table.t_ns[a]),
                    end_t_ns=int(table.t_ns[e]),
                    n_frames=e - a + 1,
                    reason=reason,
                    counts={c: counts[c] for c in CRITERIA if counts.get(c)},
                )
            )
    failed = codes_to_reasons(code)
    # a frame whose SS and ES were not computed (the staged map ran no detector on it: it could not
    # be its segment's candidate, memlog.selection.staged.detect_in_segment) is dropped for its segment
    unknown = np.isnan(table.ss) & np.isnan(table.es)
    seg_kept = np.zeros(int(seg.max()) + 1 if n else 0, dtype=bool)
    seg_kept[seg[keep]] = True
    reasons: list[str | None] = [
        None if k else ("segment" if r is None or (u and seg_kept[s]) else r)
        for k, r, u, s in zip(keep.tolist(), failed, unknown.tolist(), seg.tolist())
    ]
    info.update({"combine": cfg.combine, "weights": list(cfg.weights), "n_gaps": len(gaps)})
    if cfg.distinct_weight > 0:
        info["distinct_weight"] = cfg.distinct_weight
    return Selection(
        mode="segment",
        index=table.index,
        keep=keep,
        reason=reasons,
        thresholds={"mt": float(cfg.min_ms), "st": float(cfg.min_ss), "et": float(cfg.min_es)},
        gaps=gaps,
        info=info,
        segment_id=seg,
    )

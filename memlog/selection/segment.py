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
timestamps span > 0, else frame count. A part that holds no frame (the robot covered more than a
part between two frames: a fast stretch, a time gap) is no segment; so that the map still gets its
S frames, the length is then cut into the fewest equal parts of which S hold a frame
(:func:`memlog.selection.coordinates.count_cut`; as many as the drive has distinct places when it
has fewer), and a fast stretch keeps every frame while the rest of the drive gets the frames the
empty parts would have lost.

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

import math
from collections import Counter
from dataclasses import asdict, dataclass
from collections.abc import Sequence
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from memlog.errors import ConfigError
from memlog.scoring.motion import MOTION_KINDS, STILL_DISTANCE, find_stops
from memlog.selection._checks import finite_number, fraction, positive_int, positive_number
from memlog.selection.coordinates import GAP_FACTOR as GAP_FACTOR
from memlog.selection.coordinates import GAP_SPEED_WINDOW_S as GAP_SPEED_WINDOW_S
from memlog.selection.coordinates import VIEW_STEP_CAP as VIEW_STEP_CAP
from memlog.selection.coordinates import (
    anchored_view_segments,
    bin_along,
    distance_coordinate,
    moving_view_steps,
    view_step_length,
    without_stops,
)
from memlog.selection.paper import codes_to_reasons, first_failing
from memlog.selection.table import CRITERIA, Gap, ScoreTable, Selection

__all__ = ["SegmentConfig", "SegmentDefaults", "SEGMENT_DEFAULTS", "SIZE_KEYS", "select_segments", "segment_ids", "cut_segments",
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
    ``view_spacing`` is the size used when no size is given (one segment per this much view
    change, :data:`VIEW_STEP_CAP`: a step of the drive that changed the whole view), and
    ``keep_fraction`` the size then when the table has no view vectors.
    """

    by: SegmentBy = "auto"
    view_spacing: float = VIEW_STEP_CAP
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

    def config_dict(self) -> dict[str, Any]:
        """The defaults as :class:`SegmentConfig`'s keywords: sized by view change (``spacing_view``)."""
        d = self.to_dict()
        d["spacing_view"] = d.pop("view_spacing")
        d.pop("keep_fraction")
        return d


#: The segment defaults every entry point reads (see :class:`SegmentDefaults`).
SEGMENT_DEFAULTS = SegmentDefaults()
#: The settings that size a segment selection (exactly one is given to :class:`SegmentConfig`).
SIZE_KEYS = ("keep_fraction", "spacing_view", "spacing_m", "spacing_s", "spacing_frames")


@dataclass(frozen=True)
class SegmentConfig:
    """Settings of :func:`select_segments` (set exactly one of ``keep_fraction``,
    ``spacing_view``, ``spacing_m``, ``spacing_s``, ``spacing_frames``; ``by="view"``:
    ``keep_fraction`` or ``spacing_view``, or none and ``view_distance``).

    ``spacing_view``: as many segments as the drive's view change (stops left out, each step's
    chord capped at :data:`VIEW_STEP_CAP`) holds this spacing, ``S = ceil(view change /
    spacing_view)`` (at most one per frame), cut along ``by`` like ``keep_fraction``'s ``S``: the
    map's size follows how much the drive saw, not how many frames it recorded. A table without
    view vectors falls back to ``SEGMENT_DEFAULTS.keep_fraction`` (``info["size_note"]``).

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
    spacing_view: float | None = None
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
            for k in SIZE_KEYS
            if getattr(self, k) is not None
        }
        v = finite_number("still_distance", self.still_distance)
        if not 0.0 <= v < 2.0:
            raise ConfigError(f"still_distance must be in [0, 2), got {self.still_distance!r}")
        if self.by == "view" and set(sizes) - {"keep_fraction", "spacing_view"}:
            raise ConfigError(f"segment by='view' is sized by keep_fraction or spacing_view (or view_distance); "
                              f"unset {sorted(set(sizes) - {'keep_fraction', 'spacing_view'})}")
        if self.by == "view" and not sizes:
            v = finite_number("view_distance", self.view_distance)
            if not 0.0 < v <= 2.0:
                raise ConfigError(f"view_distance must be in (0, 2], got {self.view_distance!r}")
        elif len(sizes) != 1:
            raise ConfigError(
                "segment selection needs exactly one of keep_fraction, spacing_view, spacing_m, spacing_s, "
                f"spacing_frames; got {sorted(sizes) or 'none'}"
            )
        if self.keep_fraction is not None:
            fraction("keep_fraction", self.keep_fraction)
        if self.spacing_view is not None:
            positive_number("spacing_view", self.spacing_view)
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


def segment_ids(table: ScoreTable, config: SegmentConfig) -> tuple[NDArray[np.int64], dict[str, Any]]:
    """Place segment of each row (0..S-1, non-decreasing) and a description of the cut."""
    seg, _coord, info = cut_segments(table, config)
    return seg, info


def _segment_by(table: ScoreTable, config: SegmentConfig) -> str:
    """What the segments of a non-empty ``table`` are cut by: ``config.by``, or for "auto" the one
    its spacing names, else distance when the robot moved, else view change when the table has
    view vectors, else time when the timestamps span > 0, else frame count. Raises
    :class:`ConfigError` when the table lacks the columns that takes."""
    by = config.by
    if by == "auto":
        if config.spacing_m is not None:
            by = "distance"
        elif config.spacing_s is not None:
            by = "time"
        elif config.spacing_frames is not None:
            by = "count"
        else:
            moved = table.positions is not None and float(distance_coordinate(table)[0][-1]) > 0.0
            by = "distance" if moved else "view" if table.view is not None else (
                "time" if table.t_ns[-1] > table.t_ns[0] else "count")
    if by == "distance" and table.positions is None:
        raise ConfigError("segment by='distance' needs positions, but the score table has none")
    anchored = by == "view" and config.keep_fraction is None and config.spacing_view is None
    if anchored and table.descriptors is None and table.view is None:
        raise ConfigError("segment by='view' with view_distance needs view vectors or descriptors, but the score "
                          "table has neither")
    if by == "view" and not anchored and table.view is None:
        raise ConfigError("segment by='view' needs the frames' view vectors, but the score table has none")
    return by


def _bins(table: ScoreTable, config: SegmentConfig, by: str, still: NDArray[np.bool_], n_seg: int | None,
          view_change: NDArray[np.float64] | None, info: dict[str, Any]
          ) -> tuple[NDArray[np.int64], NDArray[np.float64] | None, float, NDArray[np.bool_] | None]:
    """Each row's bin along the coordinate ``by`` (stops left out), the coordinate itself (None for
    anchored view segments), the bin width and, by distance, the rows inside position gaps; what
    the cut found goes into ``info``. ``view_change``: :func:`_view_change` where the table has
    view vectors."""
    n = table.n
    raw: NDArray[np.int64]
    along: NDArray[np.float64] | None = None
    in_gap: NDArray[np.bool_] | None = None
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
        dt = without_stops((table.t_ns - table.t_ns[0]).astype(np.float64), still)
        spacing = None if config.spacing_s is None else config.spacing_s * 1e9
        raw, width = bin_along(dt, spacing, n_seg)
        along = dt
        if width == 0.0:
            info["note"] = "timestamps span 0 s: one segment"
        info["spacing_s"] = width / 1e9
    elif by == "distance":
        s, in_gap, facts = distance_coordinate(table)
        s = without_stops(s, still)
        info["path_length_m"] = float(s[-1])
        info.update(facts)
        raw, width = bin_along(s, config.spacing_m, n_seg)
        along = s
        if width == 0.0:
            info["note"] = "the robot did not move (path length 0 m): one segment"
        info["spacing_m"] = width
    elif n_seg is None:  # anchored view segments
        raw = anchored_view_segments(table, config.view_distance)
        info["view_distance"] = config.view_distance
    else:  # view change
        assert view_change is not None
        c = view_change
        raw, width = bin_along(c, None, n_seg)
        along = c
        info["view_change"] = float(c[-1])
        if width == 0.0:
            info["note"] = "the view never changed: one segment"
    return raw, along, width, in_gap


def _view_change(table: ScoreTable, still: NDArray[np.bool_]) -> NDArray[np.float64]:
    """The drive's view change up to each row (capped chords, stops left out)."""
    assert table.view is not None
    out: NDArray[np.float64] = np.cumsum(view_step_length(np.nan_to_num(moving_view_steps(table.view, still),
                                                                          nan=0.0)))
    return out


def _n_segments(table: ScoreTable, config: SegmentConfig, view_change: NDArray[np.float64] | None,
                info: dict[str, Any]) -> int | None:
    """How many segments the drive is cut into when its size is a count (``keep_fraction``, or
    ``spacing_view``: from the drive's view change, :func:`_view_change`; a table without view
    vectors has none); None when a spacing along ``by`` sizes it."""
    n = table.n
    frac = config.keep_fraction
    if config.spacing_view is not None:
        if view_change is not None:
            total = float(view_change[-1])
            info["spacing_view"] = config.spacing_view
            info["view_change"] = total
            return max(1, min(n, math.ceil(total / config.spacing_view - 1e-9)))
        frac = SEGMENT_DEFAULTS.keep_fraction
        info["size_note"] = (f"the table has no view vectors: {frac:g} of the frames instead of one per "
                             f"{config.spacing_view:g} of view change")
    return max(1, int(np.floor(frac * n + 0.5))) if frac is not None else None


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
    by = _segment_by(table, config)
    stops = find_stops(n, table.view, table.motion, config.still_distance)
    still = stops.still
    if table.view is not None or stops.source in MOTION_KINDS:
        info["still_frames"] = int(still.sum())
    if stops.source in MOTION_KINDS:
        info["stops_from"] = {"source": stops.source, "topic": stops.topic}
    wanted = config.spacing_view is not None or by == "view"  # (the size, or the coordinate)
    view_change = _view_change(table, still) if wanted and table.view is not None else None
    n_seg = _n_segments(table, config, view_change, info)
    raw, along, width, in_gap = _bins(table, config, by, still, n_seg, view_change, info)
    if along is not None:
        # in segment lengths, within the row's own bin (the last bin holds the end of the drive);
        # a drive of length 0 is one segment, every row at its middle
        coord = np.asarray(np.clip(along / width, raw, raw + 1.0 - 1e-9) if width > 0 else raw + 0.5, np.float64)
    # relabel to consecutive ids (bins without frames are not segments)
    change = np.concatenate([[0], (np.diff(raw) != 0).astype(np.int64)])
    seg = np.cumsum(change).astype(np.int64)
    info["by"] = by
    info["n_segments"] = int(seg[-1]) + 1
    if in_gap is not None:
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
    cfg = config if config is not None else SegmentConfig(spacing_view=SEGMENT_DEFAULTS.view_spacing)
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

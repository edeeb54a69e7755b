"""Sequence matching: localize a drive against a map as sequences of frames, not frame by frame.

Both the map and the query are drives, so a query frame is matched together with its neighbours:
the frames ``t`` of a window around query frame ``i`` (``length`` frames before and after, or,
``causal``, the ``length`` frames before and ``i`` itself) are assumed to follow a path along
the reference drive, and the path whose frames are most similar to the window wins (SeqSLAM,
Milford & Wyeth 2012). What is matched is a *coordinate* along each drive (``coordinate``):

* ``frames``: the frame index on the topic (the map's rows carry their frame index in the
  reference drive, so a sparse map keeps the reference drive's numbering);
* ``time``: the header stamp, in seconds (a map recorded at another frame rate has the same
  speed 1);
* ``positions``: the distance travelled along the drive's positions, in metres (a stop adds
  nothing, so the speed is about 1 whatever the vehicle did);
* ``auto``: ``positions`` when both drives have positions for every frame, else ``frames``.

**The score of a path.** Every similarity is contrast-normalised per query frame:
``z = (s - mean) / std`` with the mean and standard deviation of the frame's similarities to a
fixed sample of :data:`STAT_SAMPLE` map frames spread evenly over the map (so no full row of
similarities is needed, and the value does not depend on which other queries are matched). A
path predicts a reference coordinate for each window frame, and each *map frame along the path*
is compared with the query frame(s) predicted nearest to it (all of them on a tie: a stop). On
a full map at the right speed that is every window frame against its own place; on a half or
quarter map (gaps: the map holds only the kept frames, with their frame indices in the reference
drive) each kept frame meets the query frame aligned with it, never the frames that fall in a gap
only because no kept frame is nearer (on Nordland a frame two places away is another view).
The measurements behind this and every default below: ``docs/defaults.md``. Predictions beyond the
map's ends meet nothing. The path's score is ``sum(z) / sqrt(pairs)``: standard normal when
nothing matches, whatever the number of pairs, so paths with fewer pairs do not win by noise
(the plain mean lost on half maps). Two path models (``path``):

* ``constant`` (SeqSLAM): a straight line, coordinate ``x + v (c_t - c_i)`` with the relative
  speed ``v`` (map coordinate per query coordinate) searched over ``speeds`` in steps of
  ``speed_step`` (default: the step that moves the window's far end by one reference frame).
  The default range is a third to three times the drives' *pace* (the speed of a query driven
  at the map's pace: 1 at one frame rate, the ratio of the frame intervals otherwise), with a
  *speed prior*: a path's score (and its vote) loses ``speed_prior`` per doubling or halving of
  its speed against the pace. There is no standing hypothesis (speed 0): stops are left out of
  both drives ("Stops" below), so a standing path could only fit noise;
* ``dp``: a monotone path found by dynamic programming on a grid of one reference frame, each
  step between consecutive window frames moving ``round(vmin d / u)`` to ``round(vmax d / u)``
  grid units (``d``: the query's coordinate step, ``u``: the reference's frame spacing), so the
  speed may change inside the window (a stop half-way through it). Each window frame is scored
  against the map frame nearest its grid position. Measured on the Nordland variants it loses to
  ``constant`` (its freedom fits wrong places too), so ``constant`` is the default.

**Any map size.** Only hypotheses supported by the single-frame search are considered: the top
``candidates`` map frames of every query frame (exact search, or an approximate FAISS index)
vote, for every speed, for the place they imply for the window's centre, weighted by how much
they stand out of that frame's next candidate (``z`` minus the ``z`` of candidate ``K + 1``);
votes for a centre beyond the map's ends are dropped. The :data:`EXACT_PLACES` best-voted places
(distinct places: non-maximum suppression with ``exclude``) compete for the best match: each is
scored exactly with the chosen path model at its voted speed and :data:`RESCORE_SPEEDS` steps
either side, with its centre refined in steps of half a reference frame within half the map's
spacing (a sparse map's place, or a query frame of a map at a lower frame rate, may lie between
map frames), and reported as the map frame nearest its centre. More places competing gave more
false maxima;
ranks beyond come from the next voted places. The cost per query does not depend on the map's
size beyond the candidate search.

**Confidence, one scale for every row.** The margin: the best place's score minus the second
best's, the second best being outside ``exclude`` reference frames of the best (a different
place, for ``exclude`` the truth window's half-width). A frame matched alone is a path of one
pair: its score is its ``z`` and its margin is taken over the best candidate of another place,
so sequence and single-frame rows rank on one scale.

**Stops.** A camera standing still (at a station, a junction, a red light) sees one place
for many frames. Along the frame index such a stop stretches one place over as many frames as it
lasted, and a window of frames around it covers little drive. With ``stops`` (the default), each
drive runs along its *moving index* in the ``frames`` coordinate
(:attr:`DescriptorTable.moving_index`: the frame index minus the frames spent standing; tables
without it keep the frame index) and along its moving time in the ``time`` coordinate (the time
spent standing left out); ``positions`` add nothing while standing anyway. A query frame that
stood still since its run's previous frame is not matched on its own: it takes the result of its
stop's first frame (``standing``; ``info["standing_rows"]``). ``docs/defaults.md``
(``benchmarks/matcher_defaults.py``) gives what this and the other defaults were measured on.

**Runs and the fallback.** Both drives are cut into runs (:func:`drive_runs`: recording gaps,
frames out of order, cameras); a map's runs lie far apart in coordinate, so no path crosses from
one to the next. A query is cut into runs of rows whose coordinates do not decrease
(and, for logs, whose stamps increase with gaps below a limit: :func:`drive_runs`); windows never
cross a run boundary and are cut at its ends. Offline, a run shorter than ``length + 1`` frames
(a single image, a log of unordered frames) is matched frame by frame; causal, a frame is matched
as a sequence once ``length`` frames of its run precede it (decided from the past alone), so the
first ``length`` frames of every run are single frames. A map spanning fewer reference frames
than the window, and a query that stood still throughout its run, are matched frame by frame
too. The result says so, row by row (``SequenceMatch.sequence``, ``SequenceMatch.fallback``: a
key of :data:`FALLBACK_REASONS`) and in total (``info["fallback"]``, ``info["fallback_reasons"]``).
``length = 0`` is single-frame matching.

**Batching.** Candidates come from :func:`memlog.descriptors.search.match` (independent of its
blocking), the statistics and the final scores are computed per query from its own window, and
the votes are summed in an order fixed by the query: matching the queries in blocks of any size
(``block``) gives identical results.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, replace
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from memlog.configfile import check_ints
from memlog.descriptors.drive_hmm import place_probabilities
from memlog.descriptors.search import Database, _as_2d, _rescore, _row_norms, match
from memlog.descriptors.table import POSITION_COLUMNS, DescriptorTable
from memlog.errors import ConfigError, DescriptorError
from memlog.io.positions import geo_origin, geo_to_local

if TYPE_CHECKING:
    from memlog.descriptors.approx import IVFIndex

__all__ = [
    "SequenceConfig", "SequenceMatch", "match_sequences", "match_tables", "drive_coordinates", "drive_runs",
    "resolve_coordinate", "has_positions", "reference_unit", "standing_rows", "uses_stops", "COORDINATES", "PATHS",
    "STAT_SAMPLE",
]


F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]
BoolArray = npt.NDArray[np.bool_]

COORDINATES = ("auto", "frames", "time", "positions")
PATHS = ("constant", "dp")
DEFAULT_SPEEDS = (1 / 3, 3.0)  # frames and time: a third to three times the map's speed (stops are left out)
POSITION_SPEEDS = (0.8, 1.25)  # positions: metres against metres; the range allows for odometry scale
STAT_SAMPLE = 256  # map frames the contrast normalisation's statistics are taken from
MAX_SPEEDS = 128  # at most this many speeds are searched (speed_step is raised to fit)
EXACT_PLACES = 3  # the best-voted places that compete for the best match (more: more false maxima)
TOP_VOTES = 64  # best-voted places per query looked at by the non-maximum suppression
CENTRE_STEPS = 2  # centres are tried every half reference frame (a map sparser than the query: between its frames)
RESCORE_SPEEDS = 3  # exact scores are taken at the voted speed and this many steps either side
PAIRINGS = ("mutual", "all")  # mutual: map frames along the path meet their nearest query frames; all: every frame
SCORE_NORMS = ("sqrt", "mean")  # sqrt: sum of z over sqrt(pairs), N(0, 1) without a match; mean: the mean z
VOTE_ELEMS = 1 << 21  # votes of one block of centres (memory bound whatever the window, candidates and speeds)
SCORE_ELEMS = 1 << 20  # elements of one [B, P, D, S, W] block of exact scores (memory bound whatever the sparsity)
PAIR_ELEMS = 1 << 21  # float32 elements per chunk of pair products (8 MiB)
GAP_FACTOR = 10.0  # default run boundary: a stamp gap above this many median frame intervals
MAX_LENGTH_SCALE = 2.0  # scale_length: a window grows at most 2x on a sparse map
#: why a query row was matched frame by frame (``SequenceMatch.fallback``; "" for sequence rows)
FALLBACK_REASONS = {
    "single": "single frames asked for (sequence length 0)",
    "small-map": "the map spans fewer reference frames than the window",
    "standing": "the query stood still: fewer moving frames in its run than the window needs",
    "short-run": "its run of ordered frames is shorter than the window (a single image, or frames whose stamps "
                 "do not increase)",
    "causal-start": "fewer frames of its run before it than the causal window needs",
    "no-path": "no place stood out of its window's single-frame candidates",
}


@dataclass(frozen=True)
class SequenceConfig:
    """How query frames are matched as sequences (see the module doc).

    ``length``: frames before (and, unless ``causal``, after) each query frame; 0 = single
    frames. ``speeds``: (min, max) relative speed, map coordinate per query coordinate (None:
    1/3..3 times the drives' pace for frames and time, 0.8..1.25 for positions); ``speed_step``
    (None: the step that moves the window's far end by one reference frame). ``candidates``: map
    frames per query frame from the single-frame search that vote. ``coordinate``: auto | frames | time |
    positions. ``path``: constant | dp. ``max_gap_s``: a stamp gap above this cuts the query
    into runs (None: :data:`GAP_FACTOR` times the median frame interval). ``exclude``:
    half-width, in reference frames, of the window around the best place inside which no
    second-best place is taken (the margin's "different place"). ``normalize``: contrast
    normalisation of the similarities. ``block``: query frames per block of votes, at most (fewer when a block's votes would pass
    :data:`VOTE_ELEMS`; speed and
    memory only; never the result). ``scale_length``: on a sparse map (the kept frames' median
    spacing ``s`` reference frames, a half map ``s = 2``) the window is ``length * s`` frames
    (at most :data:`MAX_LENGTH_SCALE` times), so a sequence meets as many map frames as on the
    full map (measured on Nordland's half and quarter maps; windows of 4x were worse on drives
    that change speed; ``info["length_used"]``).
    ``stops``: in the ``frames`` coordinate, drives run along their moving index and a standing
    query frame takes its stop's match (the module doc's "Stops"). ``speed_prior``: a path's
    score loses this much per doubling (or halving) of its speed against 1, ``|log2 v|`` (0: every
    speed in the range alike). Experimental settings (benchmarks compare them; the defaults are
    what was measured best): ``pairing`` (``mutual`` | ``all``), ``score_norm`` (``sqrt`` |
    ``mean``) and ``places`` (the best-voted places scored exactly). ``rerank``: re-rank each
    query's best places by patch features when both tables carry them under one PCA
    (:func:`rerank_by_patches`; ``--no-rerank`` turns it off). ``hmm``: after the re-rank, decide
    each frame's place with its neighbours', as the drive's most likely path through every
    frame's candidate places (:mod:`memlog.descriptors.drive_hmm`; ``--no-hmm`` turns it off).
    """

    length: int = 10
    causal: bool = False
    speeds: tuple[float, float] | None = None
    speed_step: float | None = None
    candidates: int = 10
    coordinate: str = "auto"
    path: str = "constant"
    max_gap_s: float | None = None
    exclude: float = 1.0
    normalize: bool = True
    block: int = 128
    scale_length: bool = True
    stops: bool = True
    speed_prior: float = 1.0
    pairing: str = "mutual"
    score_norm: str = "sqrt"
    places: int = EXACT_PLACES
    rerank: bool = True
    hmm: bool = True

    def __post_init__(self) -> None:
        check_ints(self, {"length": 0, "candidates": 1, "block": 1, "places": 1})
        if self.pairing not in PAIRINGS or self.score_norm not in SCORE_NORMS:
            raise ConfigError(f"pairing must be one of {', '.join(PAIRINGS)} and score_norm one of "
                              f"{', '.join(SCORE_NORMS)}, got {self.pairing!r} and {self.score_norm!r}")
        if not isinstance(self.causal, bool) or not isinstance(self.normalize, bool):
            raise ConfigError("causal and normalize must be true or false")
        if self.coordinate not in COORDINATES:
            raise ConfigError(f"coordinate must be one of {', '.join(COORDINATES)}, got {self.coordinate!r}")
        if self.path not in PATHS:
            raise ConfigError(f"path must be one of {', '.join(PATHS)}, got {self.path!r}")
        if self.speeds is not None:
            sp = tuple(self.speeds)
            if len(sp) != 2 or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
                                       for v in sp):
                raise ConfigError(f"speeds must be two finite numbers (min, max), got {self.speeds!r}")
            if sp[0] < 0 or sp[1] < sp[0]:
                raise ConfigError(f"speeds must satisfy 0 <= min <= max, got {sp[0]:g}:{sp[1]:g}")
            object.__setattr__(self, "speeds", (float(sp[0]), float(sp[1])))
        if isinstance(self.speed_prior, bool) or not isinstance(self.speed_prior, (int, float)) or not (
                math.isfinite(self.speed_prior) and self.speed_prior >= 0):
            raise ConfigError(f"speed_prior must be a number >= 0, got {self.speed_prior!r}")
        for name in ("speed_step", "max_gap_s"):
            v = getattr(self, name)
            if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v)
                                  or v <= 0):
                raise ConfigError(f"{name} must be a number > 0, got {v!r}")
        if isinstance(self.exclude, bool) or not isinstance(self.exclude, (int, float)) or not (
                math.isfinite(self.exclude) and self.exclude >= 0):
            raise ConfigError(f"exclude must be a number >= 0, got {self.exclude!r}")
        if not all(isinstance(v, bool) for v in (self.scale_length, self.stops, self.rerank, self.hmm)):
            raise ConfigError("scale_length, stops, rerank and hmm must be true or false")
        if self.length == 0 and self.causal:
            raise ConfigError("causal needs a sequence: length (--sequence) must be >= 1")

    @property
    def enabled(self) -> bool:
        """Sequences are matched (``length >= 1``)."""
        return self.length > 0

    def speed_range(self, coordinate: str) -> tuple[float, float]:
        """``speeds``, or the default for ``coordinate``."""
        if self.speeds is not None:
            return self.speeds
        return POSITION_SPEEDS if coordinate == "positions" else DEFAULT_SPEEDS

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict."""
        d = asdict(self)
        d["speeds"] = list(self.speeds) if self.speeds is not None else None
        return d


@dataclass
class SequenceMatch:
    """Best map places of every query frame.

    ``indices`` ``[Q, k]``: rows of the reference (the full reference, also when a mask was
    given), best first, -1 = none; for a sequence-matched query the ranks are distinct places
    (outside ``exclude`` of each other), for a single-frame one the ``k`` most similar frames.
    ``scores`` ``[Q, k]``: the sequence score (mean contrast-normalised similarity along the
    path), or the similarity for single-frame queries; ``similarities`` ``[Q, k]``: the cosine
    similarity of the query frame itself to each matched frame. ``margin`` ``[Q]``: best minus
    second-best *place*'s score (NaN without a second), in the score's unit for every row: a
    single frame is a path of one pair, its score the contrast-normalised similarity ``z`` and its
    second place the best candidate outside ``exclude`` of the best; after the re-rank, the best
    place's patch score minus the other place's; after the drive HMM, the best place's probability
    minus the other place's (``posterior`` ``[Q, k]``: each place's probability along the drive). ``ratio`` ``[Q]``: the query
    frame's descriptor distance to the best match over its distance to the second-best place
    (Lowe's ratio; lower is more distinct). ``speed`` ``[Q]``: relative speed of the best path
    (NaN for single frames). ``window`` ``[Q]``: frames the score was taken over (1 = single
    frame). ``sequence`` ``[Q]``: matched as a sequence. ``fallback`` ``[Q]``: why a row was
    matched frame by frame ("" for sequence rows; :data:`FALLBACK_REASONS`). ``info``: the
    settings used and what happened (``length_used``, ``sequence_queries``, ``single_queries``,
    ``fallback``: a summary, ``fallback_reasons``: rows per reason).
    """

    indices: I64
    scores: F64
    similarities: F32
    margin: F64
    speed: F64
    window: I64
    sequence: BoolArray
    ratio: F64 = field(default_factory=lambda: np.zeros(0))
    fallback: npt.NDArray[np.str_] = field(default_factory=lambda: np.zeros(0, dtype=str))
    info: dict[str, Any] = field(default_factory=dict)
    rerank: F64 | None = None
    posterior: F64 | None = None

    @property
    def confidence(self) -> F64:
        """Per-query confidence, one scale for every row: the margin of the best place over the
        second-best in score units (0 without a second place); -inf without a match."""
        found = self.indices[:, 0] >= 0
        m = np.where(np.isnan(self.margin), 0.0, self.margin)
        out: F64 = np.where(found, m, -np.inf).astype(np.float64)
        return out

    def take(self, rows: npt.ArrayLike) -> SequenceMatch:
        """The result of query ``rows`` (in that order), same info."""
        r = np.asarray(rows, dtype=np.int64)
        return SequenceMatch(self.indices[r], self.scores[r], self.similarities[r], self.margin[r], self.speed[r],
                             self.window[r], self.sequence[r], self.ratio[r], self.fallback[r], self.info,
                             None if self.rerank is None else self.rerank[r],
                             None if self.posterior is None else self.posterior[r])

    def top(self, k: int) -> SequenceMatch:
        """The ``k`` best places of every row (the others dropped)."""
        return replace(self, indices=self.indices[:, :k], scores=self.scores[:, :k],
                       similarities=self.similarities[:, :k],
                       rerank=None if self.rerank is None else self.rerank[:, :k],
                       posterior=None if self.posterior is None else self.posterior[:, :k])


# -- coordinates and runs of descriptor tables -------------------------------------------------------
def _stamps_s(table: DescriptorTable) -> F64:
    """Header stamps in seconds from the table's first (log time where a stamp is 0)."""
    ns = np.where(table.stamp_ns != 0, table.stamp_ns, table.log_time_ns).astype(np.int64)
    if not len(ns):
        return np.zeros(0)
    out: F64 = (ns - ns.min()).astype(np.float64) / 1e9
    return out


def has_positions(table: DescriptorTable) -> bool:
    """Every frame of ``table`` has a finite position."""
    cols = [c for cols in POSITION_COLUMNS.values() for c in cols[:2] if c in table.positions]
    return len(table) > 0 and len(cols) == 2 and all(np.all(np.isfinite(table.positions[c])) for c in cols)


def _topic_groups(table: DescriptorTable) -> list[I64]:
    """Rows of each topic, in table order, topics in order of first appearance."""
    topics = list(dict.fromkeys(table.topic))
    arr = np.array(table.topic, dtype=object)
    return [np.flatnonzero(arr == t).astype(np.int64) for t in topics]


def uses_stops(config: SequenceConfig, coordinate: str) -> bool:
    """Stops are left out of the match (``config.stops`` and the ``frames`` or ``time`` coordinate;
    positions add nothing while standing anyway)."""
    return config.enabled and config.stops and coordinate in ("frames", "time")


def drive_coordinates(table: DescriptorTable, coordinate: str, stops: bool = False) -> F64:
    """The along-drive coordinate of every row: ``frames`` (frame index; with ``stops`` the
    moving index where the table has one), ``time`` (stamp, s; with ``stops`` the time spent
    standing left out) or ``positions`` (distance travelled along the topic's frames in frame
    order, m)."""
    if coordinate == "frames":
        if stops and table.moving_index is not None:
            return table.moving_index.astype(np.float64)
        return table.frame_index.astype(np.float64)
    if coordinate == "time":
        t = _stamps_s(table)
        if stops and table.moving_index is not None:  # the moving time: time spent standing left out
            for rows in _topic_groups(table):
                dt = np.diff(t[rows])
                still = table.moving_index[rows][1:] == table.moving_index[rows][:-1]
                t[rows] = t[rows][0] + np.r_[0.0, np.cumsum(np.where(still, 0.0, dt))]
        return t
    if coordinate != "positions":
        raise DescriptorError(f"unknown coordinate {coordinate!r}")
    if not has_positions(table):
        raise DescriptorError("positions were asked for, but not every frame has a position")
    if "lat" in table.positions:
        ll = np.stack([table.positions["lat"], table.positions["lon"]], axis=1)
        xy = geo_to_local(ll, geo_origin(ll))
    else:
        xy = np.stack([table.positions["x"], table.positions["y"]], axis=1)
    out = np.zeros(len(table))
    for rows in _topic_groups(table):
        order = rows[np.argsort(table.frame_index[rows], kind="stable")]
        step = np.r_[0.0, np.linalg.norm(np.diff(xy[order], axis=0), axis=1)]
        out[order] = np.cumsum(step)
    return out


def standing_rows(table: DescriptorTable, runs: npt.ArrayLike | None = None) -> BoolArray:
    """Rows whose camera stood still since the previous row of their topic (and run, ``runs``:
    labels as :func:`drive_runs` gives): the same moving index; none without one."""
    out = np.zeros(len(table), dtype=bool)
    if table.moving_index is None:
        return out
    mi = table.moving_index
    lab = np.zeros(len(table), np.int64) if runs is None else np.asarray(runs, dtype=np.int64)
    for rows in _topic_groups(table):
        a, b = rows[:-1], rows[1:]
        out[b] = (mi[b] == mi[a]) & (lab[b] == lab[a])
    return out


def reference_unit(table: DescriptorTable, coord: npt.ArrayLike) -> float:
    """The reference drive's frame spacing in coordinate units: the median, over consecutive
    rows of a topic (by frame index), of coordinate step per frame-index step (1 for frames).
    A sparse map's rows keep their frame index in the drive, so this is the drive's spacing."""
    c = np.asarray(coord, dtype=np.float64)
    ratios = []
    for rows in _topic_groups(table):
        order = rows[np.argsort(table.frame_index[rows], kind="stable")]
        df = np.diff(table.frame_index[order]).astype(np.float64)
        dc = np.diff(c[order])
        ok = (df > 0) & (dc > 0)
        ratios.append(dc[ok] / df[ok])
    r = np.concatenate(ratios) if ratios else np.zeros(0)
    return float(np.median(r)) if r.size else 1.0


def frame_interval(table: DescriptorTable) -> float | None:
    """The drive's time per frame-index step (s): the median over consecutive rows of a topic of
    stamp step over frame-index step (a map's rows keep their frame index in the drive, so this is
    the drive's frame interval); None without increasing stamps."""
    stamps = _stamps_s(table)
    ratios = []
    for rows in _topic_groups(table):
        df = np.diff(table.frame_index[rows]).astype(np.float64)
        dt = np.diff(stamps[rows])
        ok = (df > 0) & (dt > 0)
        ratios.append(dt[ok] / df[ok])
    r = np.concatenate(ratios) if ratios else np.zeros(0)
    return float(np.median(r)) if r.size else None


def drive_pace(query: DescriptorTable, reference: DescriptorTable) -> float:
    """The speed, in map frames per query frame, of a query driven at the map drive's pace: the
    ratio of their frame intervals (1 when either is unknown or they are within 5 %)."""
    fq, fr = frame_interval(query), frame_interval(reference)
    if not fq or not fr:
        return 1.0
    ratio = fq / fr
    return 1.0 if abs(ratio - 1.0) <= 0.05 else ratio


def resolve_coordinate(asked: str, query: DescriptorTable, reference: DescriptorTable) -> tuple[str, str | None]:
    """The coordinate to match in, and a note when ``auto`` could not use positions.
    ``positions`` asked for without positions in both drives is a :class:`DescriptorError`."""
    both = has_positions(query) and has_positions(reference)
    if asked == "positions" and not both:
        which = [n for n, t in (("the map", reference), ("the query", query)) if not has_positions(t)]
        raise DescriptorError(f"--coordinate positions: {' and '.join(which)} has no position for every frame "
                          "(use --coordinate frames or time)")
    if asked != "auto":
        return asked, None
    if both:
        return "positions", None
    return "frames", "no positions in both drives: matched in frames"


def drive_runs(table: DescriptorTable, max_gap_s: float | None = None) -> tuple[I64, float | None]:
    """Run label of every row and the gap limit used: a run is a stretch of one topic's frames
    (in table order) whose stamps and frame indices increase, the stamps by at most ``max_gap_s``
    per frame-index step (None: :data:`GAP_FACTOR` times the topic's median frame interval). A
    query log (every frame, or every n-th) and a map (the kept frames of a drive, with their frame
    indices in it) are cut alike: at a recording gap, and where frames are out of order."""
    labels = np.zeros(len(table), dtype=np.int64)
    stamps = _stamps_s(table)
    run = 0
    limit_used: float | None = max_gap_s
    for rows in _topic_groups(table):
        df = np.diff(table.frame_index[rows])
        dt = np.diff(stamps[rows]) / np.maximum(df, 1)
        pos = dt[(dt > 0) & (df > 0)]
        limit = max_gap_s if max_gap_s is not None else (GAP_FACTOR * float(np.median(pos)) if pos.size else 0.0)
        if max_gap_s is None and pos.size:
            limit_used = limit if limit_used is None else max(limit_used, limit)
        cut = np.r_[True, (dt <= 0) | (df <= 0) | (dt > limit)]
        labels[rows] = run + np.cumsum(cut) - 1
        run += int(cut.sum())
    return labels, limit_used


# -- the matcher ----------------------------------------------------------------------------------
def _nearest(sorted_c: F64, x: npt.NDArray[np.float64]) -> I64:
    """Index of the value of ``sorted_c`` nearest each ``x`` (the lower one on a tie)."""
    n = sorted_c.shape[0]
    if n == 1:
        return np.zeros(np.shape(x), dtype=np.int64)
    i = np.clip(np.searchsorted(sorted_c, x), 1, n - 1)
    left = sorted_c[i - 1]
    right = sorted_c[i]
    out: I64 = np.where(x - left <= right - x, i - 1, i).astype(np.int64)
    return out


def _stats(q: F32, db: Database, normalize: bool) -> tuple[F64, F64]:
    """Mean and standard deviation of each query's similarities to a fixed sample of map rows
    (float64, one query at a time: no dependence on how many queries are given)."""
    n = q.shape[0]
    if not normalize or db.rows.shape[0] < 2:
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
    vmin: float
    vmax: float
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


def _window(p: _Problem, i: int, offs: I64) -> tuple[I64, F64]:
    """Rows of query ``i``'s window (offset order) and their coordinate minus ``i``'s."""
    t = i + offs
    t = t[(t >= p.run_lo[i]) & (t < p.run_hi[i])]
    return t, p.qc[t] - p.qc[i]


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


def _votes(p: _Problem, centres: I64, offs: I64, cand: I64, gain: F64, n_places: int) -> tuple[I64, I64]:
    """The best-voted places of each centre: ``(places [B, n_places], speed index [B, n_places])``,
    sorted map rows (-1 = none), distinct by ``p.excl`` (greedy non-maximum suppression, best
    first), each with the speed that voted for it most."""
    b = len(centres)
    m = p.rc.shape[0]
    nv = len(p.speeds)
    places = np.full((b, n_places), -1, dtype=np.int64)
    speeds = np.zeros((b, n_places), dtype=np.int64)
    t = centres[:, None] + offs[None, :]
    valid = (t >= p.run_lo[centres][:, None]) & (t < p.run_hi[centres][:, None])
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
        top = range(first[j], min(last[j], first[j] + TOP_VOTES))
        n = 0
        for e in top:
            x0 = p.rc[row[e]]
            if all(abs(x0 - p.rc[places[j, s]]) > p.excl for s in range(n)):
                places[j, n] = row[e]
                speeds[j, n] = best_v[e]
                n += 1
                if n == n_places:
                    break
    return places, speeds


def _windows(p: _Problem, centres: I64, offs: I64) -> tuple[I64, BoolArray, F64]:
    """Rows ``[B, W]`` of each centre's window (offset order; invalid slots hold the centre),
    which slots are inside the run, and their coordinate minus the centre's."""
    t = centres[:, None] + offs[None, :]
    valid = (t >= p.run_lo[centres][:, None]) & (t < p.run_hi[centres][:, None])
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
        use = inside & _closest_to_their_frame(p, pred, rk, inside) if p.cfg.pairing == "mutual" else inside
        z = np.zeros(rk.shape)
        z[use] = _z_of_pairs(p, tq[use], rk[use])
        total = np.zeros(rk.shape[:4])
        count = np.zeros(rk.shape[:4])
        for o in range(rk.shape[4]):  # a fixed summation order
            total += z[..., o]
            count += use[..., o]
        total /= np.sqrt(np.maximum(count, 1)) if p.cfg.score_norm == "sqrt" else np.maximum(count, 1)
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


def _dp_steps(d: F64, unit: float, vmin: float, vmax: float) -> tuple[I64, I64]:
    """Grid steps allowed between consecutive window frames ``d`` apart in query coordinate."""
    lo = np.round(vmin * np.abs(d) / unit).astype(np.int64)
    hi = np.maximum(lo, np.round(vmax * np.abs(d) / unit).astype(np.int64))
    return lo, hi


def _score_dp(p: _Problem, i: int, offs: I64, places: I64) -> tuple[F64, F64, F64]:
    """Exact DP-path scores of query ``i`` at the sorted map rows ``places``, with the best centre
    (tried at :func:`_centre_offsets` around each) and the path's mean speed."""
    t, d = _window(p, i, offs)
    w = len(t)
    dx = _centre_offsets(p)
    x = (p.rc[places][:, None] + dx[None, :]).ravel()  # [P * D]
    centre = int(np.flatnonzero(t == i)[0])
    reach = float(np.max(np.abs(d))) * p.vmax if w > 1 else 0.0
    g = math.ceil(reach / p.unit - 1e-9) + 1
    grid = np.arange(-g, g + 1, dtype=np.float64) * p.unit
    rk = _nearest(p.rc, x[:, None] + grid[None, :])  # [P, G]
    emis = _z_of_pairs(p, np.broadcast_to(t[:, None, None], (w,) + rk.shape), np.broadcast_to(rk, (w,) + rk.shape))
    emis = np.where(_on_map(p, x[:, None] + grid[None, :])[None], emis, 0.0)  # off the map: no evidence
    n_g = rk.shape[1]
    mid = n_g // 2
    total = np.zeros(len(x))
    ends = np.zeros((2, len(x)))
    for side, seq in ((0, range(centre + 1, w)), (1, range(centre - 1, -1, -1))):
        cur = np.full((len(x), n_g), -np.inf)
        cur[:, mid] = 0.0
        prev = centre
        for o in seq:
            lo, hi = _dp_steps(np.array([d[o] - d[prev]]), p.unit, p.vmin, p.vmax)
            nxt = np.full_like(cur, -np.inf)
            for s in range(int(lo[0]), min(int(hi[0]), n_g - 1) + 1):
                if side == 0:
                    nxt[:, s:] = np.maximum(nxt[:, s:], cur[:, : n_g - s])
                else:
                    nxt[:, : n_g - s] = np.maximum(nxt[:, : n_g - s], cur[:, s:])
            cur = nxt + emis[o]
            prev = o
        arg = np.argmax(cur, axis=1)
        total = total + cur[np.arange(len(x)), arg]
        ends[side] = (arg - mid) * p.unit
    score = ((total + emis[centre, :, mid]) / math.sqrt(w)).reshape(len(places), len(dx))
    span = (d[-1] - d[0]) if w > 1 else 0.0
    speed = ((ends[0] - ends[1]) / span if span > 0 else np.full(len(x), np.nan)).reshape(score.shape)
    arg = np.argmax(score, axis=1)
    rows = np.arange(len(places))
    return score[rows, arg], x.reshape(score.shape)[rows, arg], speed[rows, arg]


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
    late = (good >= p.cfg.places).astype(np.int64)
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
    """Match the query drive against the reference as sequences (see the module doc).

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
    kk = min(k, max(1, n_m))
    info: dict[str, Any] = {**cfg.to_dict(), "coordinate": coordinate, "k": k}

    rc_db = rc_all if db.index is None else rc_all[db.index]
    order = np.argsort(rc_db, kind="stable")
    rc = rc_db[order]  # the map frames' coordinates, increasing
    unit = float(ref_unit) if ref_unit else _median_step(rc_all)  # the reference drive's frame spacing
    spacing = _median_step(rc)  # the map's (kept frames') spacing
    if cfg.enabled and cfg.scale_length and n_m > 1:
        # a sparse map (every 2nd, 4th... frame kept) has fewer frames along a window of query
        # frames: the window grows with the map's spacing so a sequence gathers as much evidence
        scale = min(MAX_LENGTH_SCALE, max(1.0, spacing / unit)) if unit > 0 else 1.0
        cfg = replace(cfg, length=int(round(cfg.length * scale)))
    info["length_used"] = cfg.length
    full_row = order if db.index is None else db.index[order]
    full_row = full_row.astype(np.int64)
    sorted_of_full = np.full(max(n_ref, 1), -1, dtype=np.int64)
    sorted_of_full[full_row] = np.arange(n_m)

    n_cand = max(cfg.candidates + 1, kk)  # one more: the floor of the gains (and a second place)
    if n_q and n_m:
        if index is not None:
            ci, cs = index.search(q, n_cand, nprobe, rerank)
        else:
            ci, cs = match(q, db, k=n_cand)  # rows of the full reference
    else:
        ci, cs = np.full((n_q, n_cand), -1, np.int64), np.full((n_q, n_cand), -np.inf, np.float32)
    mu, sd = _stats(q, db, cfg.normalize)
    with np.errstate(invalid="ignore"):
        z = np.where(ci >= 0, (cs.astype(np.float64) - mu[:, None]) / sd[:, None], -np.inf)

    # single-frame results (every query has them; sequence queries are overwritten below): a
    # path of one pair, scored by z, the margin taken to the best candidate of another place
    indices = np.full((n_q, k), -1, dtype=np.int64)
    scores = np.full((n_q, k), -np.inf)
    indices[:, :kk] = ci[:, :kk]
    scores[:, :kk] = z[:, :kk]
    second = _second_place(ci, rc_all, cfg.exclude * unit)
    rows_q = np.arange(n_q)
    with np.errstate(invalid="ignore"):
        margin = np.where(second >= 0, z[:, 0] - z[rows_q, np.maximum(second, 0)], np.nan)
    second_row = np.where(second >= 0, ci[rows_q, np.maximum(second, 0)], -1)
    speed = np.full(n_q, np.nan)
    window = np.ones(n_q, dtype=np.int64)
    seq = np.zeros(n_q, dtype=bool)

    run_lo, run_hi = _run_bounds(labels, qc)
    run_len = run_hi - run_lo
    info["runs"] = len(np.unique(run_lo)) if n_q else 0
    # offline: a run of length + 1 frames or more; causal: a frame with length frames of its run
    # before it (decided from the past only: a live robot does not know how long a run will be)
    so_far = np.arange(n_q) - run_lo + 1
    reason = np.full(n_q, "", dtype=object)
    offs = _offsets(cfg)
    if not cfg.enabled:
        reason[:] = "single"
    else:
        reason[(so_far if cfg.causal else run_len) < cfg.length + 1] = "causal-start" if cfg.causal else "short-run"
        # the map must cover at least as many reference frames as the window has frames
        if n_m == 0 or (rc[-1] - rc[0]) / max(unit, 1e-300) + 1 < len(offs) - 1e-9:
            reason[:] = "small-map"
    use = reason == ""

    if use.any() and n_m:
        qsteps = []
        for a in np.unique(run_lo[use]):
            qsteps.append(np.abs(np.diff(qc[a : run_hi[a]])))
        qs = np.concatenate(qsteps) if qsteps else np.zeros(0)
        qstep = float(np.median(qs[qs > 0])) if np.any(qs > 0) else unit
        vmin, vmax = cfg.speed_range(coordinate)
        if cfg.speeds is None:
            vmin, vmax = vmin * pace, vmax * pace
        speeds, step = _speed_grid(cfg, vmin, vmax, unit, qstep)
        p = _Problem(q, qc, run_lo, run_hi, db.rows[order], rc, full_row, mu, sd, unit, spacing,
                     cfg.exclude * unit, speeds, vmin, vmax, cfg, pace)
        info.update({"speeds": [vmin, vmax], "speed_step": step, "n_speeds": len(speeds), "unit": unit,
                     "speed_prior": cfg.speed_prior, "pace": pace})
        cand = np.where(ci >= 0, sorted_of_full[np.maximum(ci, 0)], -1)
        # a candidate's vote: how far it stands out of the frame's next candidate (the (K+1)-th)
        n_valid = (ci >= 0).sum(axis=1)
        floor = z[np.arange(n_q), np.clip(n_valid - 1, 0, cfg.candidates)]
        gain = np.where(ci[:, : cfg.candidates] >= 0, z[:, : cfg.candidates] - floor[:, None], 0.0)
        cand = cand[:, : cfg.candidates]
        n_places = max(k, cfg.places)
        centres_all = np.flatnonzero(use).astype(np.int64)
        # votes are [centres x window x candidates, speeds]: fewer centres a block when they are many
        block = max(1, min(cfg.block, VOTE_ELEMS // max(1, len(offs) * cfg.candidates * len(speeds))))
        for a in range(0, len(centres_all), block):
            centres = centres_all[a : a + block]
            places, vbest = _votes(p, centres, offs, cand, gain, n_places)
            if cfg.path == "constant":
                sc, xc, sp = _score_constant(p, centres, offs, places, vbest)
            else:
                sc = np.full(places.shape, -np.inf)
                xc = np.zeros(places.shape)
                sp = np.full(places.shape, np.nan)
                for j, i in enumerate(centres):
                    ok = places[j] >= 0
                    if ok.any():
                        sc[j, ok], xc[j, ok], sp[j, ok] = _score_dp(p, int(i), offs, places[j, ok])
            _, valid, _d = _windows(p, centres, offs)
            for j, i in enumerate(centres):
                _place(p, int(i), sc[j], xc[j], sp[j], int(valid[j].sum()), k, indices, scores, margin, speed,
                       window, seq)
        # a sequence row's second place is its rank 2 (a distinct place)
        second_row = np.where(seq, indices[:, 1] if k > 1 else -1, second_row)
    # a row with a voted place none of whose paths scored stays a single frame: say why
    reason[use & ~seq] = "no-path"
    fallback = reason.astype(str)
    _summarise_fallback(info, cfg, fallback)
    db_rows = _db_rows(db, n_ref)
    sims = _similarities(q, db, indices, db_rows)
    ratio = _ratio(q, db, indices[:, 0], second_row, db_rows)
    return SequenceMatch(indices, scores, sims, margin, speed, window, seq, ratio, fallback, info)


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


def match_tables(
    query: DescriptorTable,
    reference: DescriptorTable,
    config: SequenceConfig | None = None,
    *,
    k: int = 5,
    index: IVFIndex | None = None,
    nprobe: int | None = None,
    rerank: int | None = None,
    ref_mask: npt.ArrayLike | None = None,
) -> SequenceMatch:
    """The drive matcher: :func:`match_sequences` for two descriptor tables (a query log and a
    map), what ``memlog localize``, ``memlog evaluate`` and the benchmarks all call. The
    coordinate is resolved (:func:`resolve_coordinate`), the query is cut into runs
    (:func:`drive_runs`) and put in drive order per topic; the map is cut into runs the same way
    (its topics, recording gaps and frames out of order), each run's coordinates far from the
    others' so no path crosses from one to the next; the reference frame spacing comes from the
    map's frame indices (so a sparse map's gaps are known). ``ref_mask``: the map is these rows of
    ``reference`` (returned rows are rows of the whole table). Results are in the query table's
    row order."""
    cfg = config or SequenceConfig()
    coordinate, note = resolve_coordinate(cfg.coordinate, query, reference)
    stops = uses_stops(cfg, coordinate)
    qc = drive_coordinates(query, coordinate, stops)
    labels, gap = drive_runs(query, cfg.max_gap_s)
    standing = standing_rows(query, labels) if stops else None
    # query rows topic by topic (a run never mixes topics), each in table order
    perm = np.concatenate(_topic_groups(query)) if len(query) else np.zeros(0, np.int64)
    rc = drive_coordinates(reference, coordinate, stops)
    unit = reference_unit(reference, rc)
    ref_runs, _gap = drive_runs(reference, cfg.max_gap_s)
    if len(rc) and ref_runs.max() > 0:  # several runs (cameras, recording gaps): far apart
        span = float(rc.max() - rc.min()) + 1.0
        rc = rc + ref_runs * 4.0 * span
    pace = drive_pace(query, reference) if coordinate == "frames" else 1.0
    query, why_not = _patch_plan(cfg, query, reference)
    places = max(k, RERANK_PLACES) if why_not is None else k
    res = match_sequences(query.descriptors[perm], qc[perm], index.db if index is not None else reference.descriptors,
                          rc, cfg, k=places, runs=labels[perm], ref_unit=unit, coordinate=coordinate, index=index,
                          nprobe=nprobe, rerank=rerank, standing=None if standing is None else standing[perm],
                          ref_mask=None if index is not None else ref_mask, pace=pace)
    if why_not is None:
        assert query.patches is not None and reference.patches is not None and reference.patch_pca is not None
        map_rows = (np.flatnonzero(np.asarray(ref_mask, dtype=bool)) if ref_mask is not None
                    else np.arange(len(reference), dtype=np.int64))
        res = rerank_by_patches(res, query.descriptors[perm], reference.descriptors, query.patches[perm],
                                reference.patches, qc[perm], rc, map_rows, labels[perm], cfg, places, unit)
        res.info["rerank"] = {"by": "patches", "places": places, "patch_pca": reference.patch_pca.sha256}
        if cfg.hmm and cfg.enabled:
            res = _along_drive(res, query.descriptors[perm], reference.descriptors, qc[perm], rc, labels[perm],
                               _median_step(np.sort(rc[map_rows])), unit, cfg)
        else:
            res.info["hmm"] = {"off": "turned off (--no-hmm)" if cfg.enabled else "single frames"}
        res = res.top(k)
    else:
        res.info["rerank"] = {"off": why_not}
        res.info["hmm"] = {"off": "no re-rank: the drive HMM decides between re-ranked places"}
    inv = np.empty_like(perm)
    inv[perm] = np.arange(len(perm))
    res = res.take(inv)
    res.info["coordinate_note"] = note
    res.info["max_gap_s"] = gap
    res.info["stops"] = stops
    res.info["map_runs"] = int(ref_runs.max()) + 1 if len(ref_runs) else 0
    res.info.setdefault("standing_rows", 0)
    return res


RERANK_BLOCK = 64  # query rows re-ranked per block (their pairs scored once each)
RERANK_PLACES = 20  # places per query the patch re-rank orders (the best of the descriptor match)


def _patch_plan(cfg: SequenceConfig, query: DescriptorTable, reference: DescriptorTable
                ) -> tuple[DescriptorTable, str | None]:
    """The query (its raw patches projected by the map's PCA) and why the patch re-rank does not
    run (None: it runs)."""
    if not cfg.rerank:
        return query, "turned off (--no-rerank)"
    if reference.patches is None or reference.patch_pca is None:
        return query, (f"the map stores no patch features ({reference.meta.kind} descriptors give none, or the map "
                       "was written before memlog stored them)")
    query = query.projected(reference.patch_pca)
    if query.patches is None:
        return query, "the query has no patch features in the map's PCA space (described with another descriptor " \
                      "or another map's PCA)"
    return query, None


def rerank_by_patches(res: SequenceMatch, q_desc: F32, r_desc: F32, q_patches: npt.NDArray[Any],
                      r_patches: npt.NDArray[Any], qc: F64, rc: F64, map_rows: I64, labels: I64,
                      cfg: SequenceConfig, k: int, unit: float) -> SequenceMatch:
    """Re-rank each query's places by patch features (:mod:`memlog.descriptors.patches`).

    A place's patch score is the mean :func:`~memlog.descriptors.patches.pair_scores` of the
    window's query frames against the map frames aligned with them along the place's path (the
    query's best speed; a frame matched alone: itself against the place). The places are ranked
    by it (ties keep their order), the ``k`` best kept; ``margin`` and the confidence become the
    best patch score minus the best of another place (one scale for every row), ``ratio`` is
    taken to the new second place. ``rc``: every reference row's coordinate; ``map_rows``: the
    rows that make the map; ``labels``: the query's runs.
    """
    from memlog.descriptors.patches import pair_scores

    n_q, n_c = res.indices.shape
    n_ref = max(1, len(rc))
    mr = map_rows[np.argsort(rc[map_rows], kind="stable")]
    mc = rc[mr]
    if not n_q or not len(mr):
        return res
    spacing = _median_step(mc)
    lo, hi = _run_bounds(labels, qc)
    length = int(res.info.get("length_used", cfg.length))
    offs = np.arange(-length, 1 if cfg.causal else length + 1, dtype=np.int64)
    cand = res.indices
    patch = np.full((n_q, n_c), np.nan)
    for a in range(0, n_q, RERANK_BLOCK):
        rows = np.arange(a, min(n_q, a + RERANK_BLOCK))
        t = rows[:, None] + offs[None, :]
        seq = res.sequence[rows][:, None]
        valid = ((t >= lo[rows][:, None]) & (t < hi[rows][:, None]) & seq) | (offs[None, :] == 0)
        t = np.where(valid, t, rows[:, None])
        c = cand[rows]
        v = np.where(res.sequence[rows], res.speed[rows], 0.0)
        pred = rc[np.maximum(c, 0)][:, :, None] + v[:, None, None] * (qc[t] - qc[rows][:, None])[:, None, :]
        near = mr[_nearest(mc, pred)]
        use = (valid[:, None, :] & (c >= 0)[:, :, None] & (pred >= mc[0] - spacing / 2)
               & (pred <= mc[-1] + spacing / 2))
        tq = np.broadcast_to(t[:, None, :], pred.shape)[use]
        key = tq * n_ref + near[use]
        uk, inv = np.unique(key, return_inverse=True)
        total = np.zeros(pred.shape)
        total[use] = pair_scores(q_patches, r_patches, uk // n_ref, uk % n_ref)[inv]
        count = use.sum(axis=2)
        patch[rows] = np.where(c >= 0, total.sum(axis=2) / np.maximum(count, 1), np.nan)
    res = replace(res, rerank=patch, info={**res.info, "patch_rerank": n_c})  # the places re-ranked
    return _ranked_by(res, np.where(cand >= 0, np.nan_to_num(patch, nan=0.0), -np.inf), q_desc, r_desc, rc,
                      cfg.exclude * unit, nan_without_second=True).top(min(k, n_c))


def _ranked_by(res: SequenceMatch, key: F64, q_desc: F32, r_desc: F32, rc: F64, excl: float,
               nan_without_second: bool = False) -> SequenceMatch:
    """``res`` with each row's places ordered by ``key`` ``[Q, K]`` (highest first, ties in their
    order; -inf: no place), the margin the best key minus the best of another place (outside
    ``excl`` coordinate units; NaN, or the best key alone with ``nan_without_second`` false, when
    there is none) and Lowe's ratio taken to that place."""
    n_q = res.indices.shape[0]
    order = np.argsort(-key, axis=1, kind="stable")
    idx = np.take_along_axis(res.indices, order, axis=1)
    ks = np.take_along_axis(key, order, axis=1)
    other = (idx[:, 1:] >= 0) & (np.abs(rc[np.maximum(idx[:, 1:], 0)] - rc[np.maximum(idx[:, :1], 0)]) > excl)
    has = other.any(axis=1)
    col = np.where(has, np.argmax(other, axis=1) + 1, 0)
    rows_q = np.arange(n_q)
    alone = np.full(n_q, np.nan) if nan_without_second else np.zeros(n_q)
    margin = np.where(idx[:, 0] >= 0, np.where(has, ks[:, 0] - ks[rows_q, col], alone + ks[:, 0]), np.nan)
    second = np.where(has, idx[rows_q, col], -1)
    ratio = _ratio(q_desc, Database.of(r_desc), idx[:, 0], second, np.arange(len(r_desc), dtype=np.int64))

    def by(a: F64 | None) -> F64 | None:
        return None if a is None else np.take_along_axis(a, order, axis=1)

    return replace(res, indices=idx, scores=np.take_along_axis(res.scores, order, axis=1),
                   similarities=np.take_along_axis(res.similarities, order, axis=1), margin=margin, ratio=ratio,
                   rerank=by(res.rerank), posterior=by(res.posterior))


def _along_drive(res: SequenceMatch, q_desc: F32, r_desc: F32, qc: F64, rc: F64, labels: I64, spacing: float,
                 unit: float, cfg: SequenceConfig) -> SequenceMatch:
    """``res`` (query rows in drive order, each with its re-ranked places) with every row's places
    ranked by their probability along the drive (:mod:`memlog.descriptors.drive_hmm`): the margin
    becomes the best place's probability minus the best other place's; a standing row takes its
    stop's first row's places."""
    assert res.rerank is not None
    score = np.where(res.indices >= 0, np.nan_to_num(res.rerank, nan=0.0), -np.inf)
    x = np.where(res.indices >= 0, rc[np.maximum(res.indices, 0)], 0.0)
    speeds = res.info.get("speeds")
    pace = float(res.info.get("pace") or 1.0)
    lo, hi = _run_bounds(labels, qc)
    post, owner = place_probabilities(score, x, qc, lo, hi, pace=pace, spacing=spacing,
                                      vmax=float(speeds[1]) if speeds else 3.0 * pace, causal=cfg.causal)
    res = res.take(owner)
    res.posterior = post[owner]
    res.info = {**res.info, "hmm": {"posterior": "filtered" if cfg.causal else "forward-backward",
                                    "standing_rows": int((owner != np.arange(len(owner))).sum())}}
    return _ranked_by(res, np.where(res.indices >= 0, res.posterior, -np.inf), q_desc, r_desc, rc,
                      cfg.exclude * unit)

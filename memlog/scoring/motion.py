"""Where a drive stood still: from the log's own motion when it has any, else from its images.

The one rule that selection (the map's place segments: a stop adds nothing to any coordinate,
:func:`memlog.selection.segment.cut_segments`) and matching (every descriptor table's moving index,
what sequences run along) use: :func:`find_stops`. A drive is one camera topic's frames in drive
order.

**The log's motion** (:func:`memlog.io.positions.read_motion`): odometry (``nav_msgs/Odometry``),
other poses, measured velocities (``TwistStamped``, ``TwistWithCovarianceStamped``: wheel speed, a
GNSS receiver's velocity) and GNSS fixes, preferred in that order (:data:`MOTION_KINDS`). The
first topic that knows the motion at *every* frame of the drive decides
(:func:`frame_motion`: interpolated at the frame times, held within :data:`MOTION_MAX_GAP_S` of
its first and last message, unknown inside a longer gap between its messages); when none does,
the images decide. So a car standing at a red light with traffic passing in front stands (the
images change, the odometry does not), and a featureless stretch driven at speed is drive (the
images barely change, the odometry moves).

**The motion rule** (:func:`motion_still_rows`). A frame stands when, since its stop's first frame
(the last frame that moved; the first frame of the drive moves),

* positions (odometry, poses): it moved less than :data:`STILL_M` = 0.25 m;
* GNSS positions: less than :data:`GNSS_STILL_M` = 0.5 m (east/north);
* speeds (twists; an odometry whose pose never left its first frame's :data:`STILL_M` while its
  twist moved, i.e. a pose left unfilled): its speed is below :data:`STILL_SPEED_MPS` = 0.1 m/s,
  or the distance travelled (speed integrated over the frame times, speeds below the threshold
  counting 0) is below :data:`STILL_M`.

Measured from the stop's first frame as the image rule is, so a crawl is drive: it moves a frame
every :data:`STILL_M`. An odometry whose twist is zero while its pose moves (a twist left
unfilled, as ``benchmarks/drives.py`` writes it) is decided by its pose.

Thresholds (physical, not tuned: no log among the shared data has odometry). Odometry is not
always wheel odometry, which does not move while the vehicle stands: ``nav_msgs/Odometry`` also
carries fused and GNSS-derived positions (``robot_localization``, ``navsat_transform``) that jitter
by centimetres; the drive variants of ``benchmarks/drives.py`` put 5 cm of noise on each
``/odom`` message. Two such samples lie more than 0.25 m apart once in about 500 (Rayleigh,
sigma 7 cm), more than 0.05 m apart four times in five, so 0.05 m would break every stop of those
into frames that move. 0.25 m is still far below the metres that tell places apart; what it
costs is that a camera moving slower than 0.25 m per frame (2.5 m/s at 10 Hz) moves only every
few frames, its moving index then counting quarter metres, as the image rule counts a crawl by its
drift. A standing receiver's GNSS fix wanders more (centimetres with RTK, decimetres without over
a minute): 0.5 m; GNSS positions are the last resort (odometry, poses and twists decide first).
A twist of a standing vehicle is noise of a few cm/s (wheel-speed quantisation, GNSS Doppler):
below 0.1 m/s (0.36 km/h) it stands.

**The image rule** (:func:`still_rows`, today's rule when the log has no motion): a frame's view
vector lies within ``still_distance`` (cosine, default :data:`STILL_DISTANCE` = 0.001) of its stop's
first frame. ``still_distance`` <= 0 turns stops off whatever the source (``"none"``).

**The record** (:func:`stop_rule`, :func:`stops_record`): every descriptor table records how its
stops were found beside its moving index (``extra["stops"]``): the rule, ``still_distance``, the
motion rule's thresholds (:func:`motion_rule`), the ``source`` that decided (``"images"``, a kind
of :data:`MOTION_KINDS`, ``"none"``) and the ``motion_topic``. ``localize`` finds the query's stops
with the map's ``still_distance`` and the same rule; the source is each log's own (a query
without odometry is decided by its images). A cached table whose stops were found otherwise is
not reused (:func:`stops_found_otherwise`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from memlog.errors import SelectionError
from memlog.io.positions import MOTION_KINDS, MotionTrack
from memlog.scoring.scorer import blank_views, view_steps

__all__ = ["STILL_DISTANCE", "STILL_M", "GNSS_STILL_M", "STILL_SPEED_MPS", "MOTION_MAX_GAP_S", "MOTION_KINDS",
           "STOP_RULE", "FrameMotion", "frame_motion", "Stops", "find_stops", "still_rows", "motion_still_rows",
           "moving_index", "motion_rule", "stop_rule", "stops_record", "recorded_still_distance",
           "stops_found_otherwise"]

#: The image rule's default: a view within this cosine distance of its stop's first frame stands
#: (EuRoC 376x240, a standing drone: all 188 pairs <= 0.0002; a moving train: median 0.15).
STILL_DISTANCE = 0.001
#: Odometry and poses: a frame less than this many metres from its stop's first frame stands
#: (speeds: travelled since it; see the module docstring for the choice).
STILL_M = 0.25
#: GNSS positions (east/north): less than this many metres from the stop's first frame stands.
GNSS_STILL_M = 0.5
#: Speeds (twists): a frame whose speed is below this (m/s) stands.
STILL_SPEED_MPS = 0.1
#: A motion topic knows a frame's motion within this many seconds of its first and last message,
#: and not inside a longer gap between two of its messages (one missed fix of a 1 Hz GNSS is not one).
MOTION_MAX_GAP_S = 2.5

#: How a stop is found (both rules measure from the stop's first frame), as a descriptor table
#: records it beside its moving index (``extra["stops"]``, :func:`stop_rule`). Tables written before
#: it was recorded found stops frame to frame (a slow crawl was one stop).
STOP_RULE = "within still_distance of the stop's first frame"


@dataclass(frozen=True, eq=False)
class FrameMotion:
    """The log's motion at a drive's frames (rows in drive order): which topic (``topic``, of
    kind ``source``, one of :data:`MOTION_KINDS`) says it, the frames' times ``t_ns``, and per
    frame its position ``xyz`` ([N, 3] metres) and/or speed ``speed`` ([N] m/s), NaN where unknown."""

    source: str
    topic: str
    t_ns: NDArray[np.int64]
    xyz: NDArray[np.float64] | None = None
    speed: NDArray[np.float64] | None = None

    def __len__(self) -> int:
        return len(self.t_ns)

    def _known_xyz(self) -> bool:
        return self.xyz is not None and bool(np.isfinite(self.xyz).all())

    def _known_speed(self) -> bool:
        return self.speed is not None and bool(np.isfinite(self.speed).all())

    @property
    def complete(self) -> bool:
        """Whether it knows every frame's position, or every frame's speed."""
        return self._known_xyz() or self._known_speed()

    def take(self, rows: ArrayLike) -> FrameMotion:
        """The motion of the given rows (increasing row positions)."""
        r = np.asarray(rows)
        return FrameMotion(self.source, self.topic, self.t_ns[r], None if self.xyz is None else self.xyz[r],
                           None if self.speed is None else self.speed[r])


def frame_motion(tracks: Sequence[MotionTrack], t_ns: ArrayLike) -> FrameMotion | None:
    """The log's motion at the frames at ``t_ns`` (one drive, in drive order): that of the first of
    ``tracks`` (:func:`memlog.io.positions.read_motion`, in :data:`MOTION_KINDS` order) that knows
    every frame; None when none does (the images decide)."""
    t = np.asarray(t_ns, dtype=np.int64)
    for track in tracks:
        xyz, speed = track.at(t.tolist(), MOTION_MAX_GAP_S)
        m = FrameMotion(track.kind, track.topic, t, xyz, speed)
        if m.complete:
            return m
    return None


@dataclass(frozen=True, eq=False)
class Stops:
    """Where a drive stood still (``still``, one flag per row: the row stood since the previous
    one) and what decided: ``source`` ``"images"``, a kind of :data:`MOTION_KINDS` (its topic
    ``topic``) or ``"none"`` (stops turned off, or nothing to find them from)."""

    still: NDArray[np.bool_]
    source: str
    topic: str | None = None


def find_stops(n: int, view: ArrayLike | None = None, motion: FrameMotion | None = None,
               still_distance: float = STILL_DISTANCE) -> Stops:
    """The stops of a drive of ``n`` rows (see the module docstring): from ``motion`` when it knows
    every row (:func:`motion_still_rows`), else from the view vectors ``view`` (:func:`still_rows`
    with ``still_distance``); none when ``still_distance`` <= 0 or there is neither."""
    if still_distance <= 0:
        return Stops(np.zeros(n, dtype=bool), "none")
    if motion is not None:
        if len(motion) != n:
            raise SelectionError(f"find_stops: {n} rows but the motion of {len(motion)}")
        if motion.complete:
            return Stops(motion_still_rows(motion), motion.source, motion.topic)
    if view is not None:
        return Stops(still_rows(view, still_distance), "images")
    return Stops(np.zeros(n, dtype=bool), "none")


def _speed_decides(m: FrameMotion) -> bool:
    """Whether the speeds decide rather than the positions: there are no positions for every frame,
    or the pose never left the first frame's :data:`STILL_M` while the speed moved (unfilled)."""
    if not m._known_xyz():
        return True
    if not m._known_speed():
        return False
    assert m.xyz is not None and m.speed is not None
    pose_moved = bool((np.linalg.norm(m.xyz - m.xyz[0], axis=1) >= STILL_M).any())
    return not pose_moved and bool((m.speed >= STILL_SPEED_MPS).any())


def motion_still_rows(motion: FrameMotion) -> NDArray[np.bool_]:
    """Rows that stood still by the log's motion (which must know every row: ``motion.complete``):
    within :data:`STILL_M` (GNSS: :data:`GNSS_STILL_M`) of the stop's first frame, the last row
    that moved; by speeds, below :data:`STILL_SPEED_MPS` or less than :data:`STILL_M` travelled since
    the stop's first frame. The first row never stands."""
    n = len(motion)
    still = np.zeros(n, dtype=bool)
    if n < 2:
        return still
    if _speed_decides(motion):
        assert motion.speed is not None
        v = motion.speed
        slow = v < STILL_SPEED_MPS
        counted = np.where(slow, 0.0, v)
        dt = np.diff(motion.t_ns).astype(np.float64) / 1e9
        travelled = np.r_[0.0, np.cumsum(0.5 * (counted[1:] + counted[:-1]) * dt)].tolist()
        anchor = 0
        for i in range(1, n):
            if slow[i] or travelled[i] - travelled[anchor] < STILL_M:
                still[i] = True
            else:
                anchor = i
        return still
    assert motion.xyz is not None
    limit = GNSS_STILL_M if motion.source == "gnss" else STILL_M
    p = motion.xyz
    anchor = 0
    for i in range(1, n):
        if float(np.linalg.norm(p[i] - p[anchor])) < limit:
            still[i] = True
        else:
            anchor = i
    return still


def still_rows(view: ArrayLike, still_distance: float = STILL_DISTANCE) -> NDArray[np.bool_]:
    """Rows that stood still by the images: their view vector (``view``: [N, v], rows in drive order,
    :func:`memlog.scoring.scorer.view_vector`) lies within ``still_distance`` (cosine) of the
    stop's first frame, the last row that moved (the first row never stands still; two blank
    views are the same view, a blank and a non-blank one differ by 1; a row with an unknown
    vector moves; ``still_distance <= 0``: none). Measured from the stop's first frame, not the
    predecessor, so a camera that crawls (a fraction of a pixel per frame, each step below sensor
    noise) stands only until its view has drifted by ``still_distance``: a crawl is drive, a stop
    is not."""
    v = np.asarray(view, dtype=np.float64)
    n = len(v)
    still = np.zeros(n, dtype=bool)
    if still_distance <= 0 or n < 2:
        return still
    steps = np.nan_to_num(view_steps(v), nan=np.inf)
    blank = blank_views(v)
    # a row whose step from its predecessor is 4x the threshold or more is out of reach of any
    # anchor its predecessor stood within (chord lengths: sqrt(2 * 4t) - sqrt(2t) = sqrt(2t)), so
    # only rows below that are compared with the anchor
    near = steps < 4 * still_distance
    anchor = 0
    for i in range(1, n):
        if near[i]:
            if anchor == i - 1:
                d = steps[i]
            elif blank[i] or blank[anchor]:
                d = 0.0 if blank[i] and blank[anchor] else 1.0
            else:
                d = 1.0 - float(np.dot(v[i], v[anchor]))  # NaN (unknown) compares False: moves
            if d < still_distance:
                still[i] = True
                continue
        anchor = i
    return still


def moving_index(index: ArrayLike, still: ArrayLike) -> NDArray[np.int64]:
    """The frame index with the stops left out: ``index`` (frame indices of one topic's rows in
    drive order) minus the frames spent standing still up to each row, where a row that stood
    still (``still``) stood for all the frames since the previous row. A standing camera's frames
    share one value, so a drive matched along it does not stretch a stop over many places."""
    idx = np.asarray(index, dtype=np.int64)
    st = np.asarray(still, dtype=bool)
    if idx.shape != st.shape:
        raise SelectionError(f"moving_index: {idx.shape[0]} frame indices but {st.shape[0]} still flags")
    gap = np.diff(idx, prepend=idx[:1])
    return np.asarray(idx - np.cumsum(np.where(st, gap, 0)), dtype=np.int64)


def motion_rule() -> dict[str, Any]:
    """The motion rule's settings as a table records them (``extra["stops"]["motion"]``)."""
    return {"still_m": STILL_M, "gnss_still_m": GNSS_STILL_M, "still_speed_mps": STILL_SPEED_MPS,
            "max_gap_s": MOTION_MAX_GAP_S, "order": list(MOTION_KINDS)}


def stop_rule(still_distance: float = STILL_DISTANCE, source: str | None = None,
              topic: str | None = None) -> dict[str, Any]:
    """The record of how a drive's stops were found (:func:`find_stops` with ``still_distance``;
    ``source``: what decided, default ``"images"``, ``"none"`` when ``still_distance`` <= 0;
    ``topic``: the motion topic that decided), kept with its moving index: two drives are matched
    along their moving indices only when their stops were found by the same rule."""
    rec: dict[str, Any] = {"rule": STOP_RULE, "still_distance": float(still_distance),
                           "source": source if source is not None else "images" if still_distance > 0 else "none",
                           "motion": motion_rule()}
    if topic is not None:
        rec["motion_topic"] = topic
    return rec


def stops_record(still_distance: float, found: Mapping[str, Stops]) -> dict[str, Any]:
    """:func:`stop_rule` of a table whose camera topics' stops are ``found`` (by topic): their
    source when all topics agree, else ``source`` (and ``motion_topic``) by camera topic."""
    decided = {(s.source, s.topic) for s in found.values()}
    if len(decided) <= 1:
        source, topic = next(iter(decided), (None, None))
        return stop_rule(still_distance, source, topic)
    rec = stop_rule(still_distance)
    rec["source"] = {cam: s.source for cam, s in found.items()}
    rec["motion_topic"] = {cam: s.topic for cam, s in found.items() if s.topic is not None}
    return rec


def recorded_still_distance(extra: Mapping[str, Any]) -> float | None:
    """The ``still_distance`` a descriptor table's stops were found with under today's rule (its
    ``extra["stops"]``, as :func:`stop_rule` wrote it); None when the table does not say, or
    found them by another rule."""
    rule = extra.get("stops")
    if isinstance(rule, Mapping) and rule.get("rule") == STOP_RULE:
        return float(rule["still_distance"])
    return None


def stops_found_otherwise(extra: Mapping[str, Any], still_distance: float) -> str | None:
    """How a descriptor table's stops (``extra["stops"]``) were found when not as they are now with
    ``still_distance`` (words that follow "its stops were found"); None when they were."""
    found = recorded_still_distance(extra)
    if found is None:
        return "by an older memlog (frame to frame)"
    if found != float(still_distance):
        return f"with still_distance {found:g}, not {still_distance:g}"
    if extra["stops"].get("motion") != motion_rule():
        return "before memlog found them from the log's motion (or with other motion thresholds)"
    return None

"""The drives' coordinates and runs: what sequences follow along each drive (frames, time, positions),
where a drive stood still, and where its runs begin and end."""

from __future__ import annotations


import numpy as np
import numpy.typing as npt

from memlog.descriptors.table import POSITION_COLUMNS, DescriptorTable
from memlog.errors import DescriptorError
from memlog.io.positions import geo_origin, geo_to_local
from memlog.matching.config import BoolArray, F64, GAP_FACTOR, I64, SequenceConfig

__all__ = ["drive_coordinates", "drive_runs", "resolve_coordinate", "has_positions", "reference_unit", "standing_rows", "stop_runs", "uses_stops", "drive_pace", "frame_interval"]



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


def stop_runs(labels: npt.ArrayLike, standing: npt.ArrayLike, min_stop: int) -> I64 | None:
    """Run labels (drive order, as :func:`drive_runs` gives) with each run also cut at its first
    moving row after a stop of at least ``min_stop`` standing rows (``standing``: as
    :func:`standing_rows` gives); None where no run has such a stop. A drive's speed before a stop
    says nothing of its speed after it: windows of these runs do not cross a stop."""
    lab = np.asarray(labels, dtype=np.int64)
    s = np.asarray(standing, dtype=bool)
    n = len(lab)
    if n < 2:
        return None
    idx = np.arange(n)
    streak = idx - np.maximum.accumulate(np.where(s, -1, idx))  # standing rows ending at each row (0: moving)
    new_run = lab[1:] != lab[:-1]
    cut = ~s[1:] & (streak[:-1] >= min_stop) & ~new_run
    if not cut.any():
        return None
    out: I64 = np.cumsum(np.r_[True, new_run | cut]).astype(np.int64) - 1
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

"""Per-frame score tables (the input of every selector) and selections (their output).

A :class:`ScoreTable` holds, for the frames of one camera topic in log-time order, the
frame index, log time, the three scores MS/SS/ES (NaN where a score was not computed),
and optionally positions and global descriptors. A :class:`Selection` is a keep mask over
the rows of a table, with the reason each dropped frame was dropped.

Invalid tables raise :class:`~memlog.errors.SelectionError` (they are inputs, not
settings); invalid settings raise :class:`~memlog.errors.ConfigError` elsewhere.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from memlog.errors import SelectionError
from memlog.scoring.motion import FrameMotion
from memlog.scoring.scorer import blank_views

__all__ = ["ScoreTable", "Selection", "Gap", "CRITERIA", "REASONS", "DISTINCT"]

#: The three criteria in the scorer's staged (cheap-first) order; a dropped frame's reason
#: is the first of these it fails.
CRITERIA: tuple[str, str, str] = ("staticity", "entropy", "memorability")

#: The criterion computed over the whole drive (:mod:`memlog.selection.distinctiveness`), used
#: when the table has a ``ds`` column and the selection asks for it.
DISTINCT = "distinctiveness"

#: Every reason a selector may give for dropping a frame.
REASONS: tuple[str, ...] = CRITERIA + (DISTINCT, "segment", "duplicate", "not-sampled")

_UNIT_NORM_TOL = 1e-3


def _int_column(name: str, value: ArrayLike) -> NDArray[np.int64]:
    a = np.asarray(value)
    if a.ndim != 1:
        raise SelectionError(f"ScoreTable.{name} must be 1-D, got shape {a.shape}")
    if a.size and a.dtype.kind not in "iu":
        raise SelectionError(f"ScoreTable.{name} must hold integers, got dtype {a.dtype}")
    return a.astype(np.int64, copy=True)


def _float_column(name: str, value: ArrayLike) -> NDArray[np.float64]:
    a = np.asarray(value)
    if a.ndim != 1:
        raise SelectionError(f"ScoreTable.{name} must be 1-D, got shape {a.shape}")
    if a.size and a.dtype.kind not in "biuf":
        raise SelectionError(f"ScoreTable.{name} must hold numbers, got dtype {a.dtype}")
    return a.astype(np.float64, copy=True)


@dataclass(eq=False)
class ScoreTable:
    """Scores of the frames of one camera topic, one row per frame, in log-time order.

    ``index`` (strictly increasing frame indices), ``t_ns`` (non-decreasing int64 log
    times), ``ms``/``ss``/``es`` (float64, NaN = not computed) all have length N.
    ``positions`` is [N, 2] or [N, 3] metres in a local frame (rows with any NaN are
    unknown); ``descriptors`` is [N, d] float32, each finite row L2-normalised (rows with
    any NaN are unknown). ``ds`` is the optional distinctiveness criterion (float64 in (0, 1),
    NaN = unknown; :mod:`memlog.selection.distinctiveness`). ``view`` is the optional [N, v]
    float32 view vector of each frame (:func:`memlog.scoring.scorer.view_vector`: a small
    zero-mean grey thumbnail, unit length, zero for a blank frame, NaN = unknown): consecutive
    frames' distance measures how much the view changed (view segments, stops). ``motion`` is the
    log's own motion at the rows (:func:`memlog.scoring.motion.frame_motion`; None: the log has
    none that knows every row), which decides the stops when given
    (:func:`memlog.scoring.motion.find_stops`). Columns are copied and converted on construction.
    """

    index: NDArray[np.int64]
    t_ns: NDArray[np.int64]
    ms: NDArray[np.float64]
    ss: NDArray[np.float64]
    es: NDArray[np.float64]
    positions: NDArray[np.float64] | None = None
    descriptors: NDArray[np.float32] | None = None
    topic: str = ""
    ds: NDArray[np.float64] | None = None
    view: NDArray[np.float32] | None = None
    motion: FrameMotion | None = None

    def __post_init__(self) -> None:
        self.index = _int_column("index", self.index)
        if self.motion is not None and len(self.motion) != len(self.index):
            raise SelectionError(f"ScoreTable.motion must have {len(self.index)} rows, got {len(self.motion)}")
        if self.view is not None:
            v = np.asarray(self.view, dtype=np.float32)
            if v.ndim != 2 or v.shape[0] != len(self.index):
                raise SelectionError(f"ScoreTable.view must have shape [{len(self.index)}, v], got {v.shape}")
            self.view = v.copy()
        if self.ds is not None:
            self.ds = _float_column("ds", self.ds)
            if len(self.ds) != len(self.index):
                raise SelectionError(f"ScoreTable columns differ in length: index has {len(self.index)} rows, "
                                      f"ds has {len(self.ds)}")
        self.t_ns = _int_column("t_ns", self.t_ns)
        self.ms = _float_column("ms", self.ms)
        self.ss = _float_column("ss", self.ss)
        self.es = _float_column("es", self.es)
        n = len(self.index)
        for name in ("t_ns", "ms", "ss", "es"):
            got = len(getattr(self, name))
            if got != n:
                raise SelectionError(
                    f"ScoreTable columns differ in length: index has {n} rows, {name} has {got}"
                )
        if n > 1:
            if np.any(np.diff(self.index) <= 0):
                bad = int(np.flatnonzero(np.diff(self.index) <= 0)[0])
                raise SelectionError(
                    "ScoreTable.index must be strictly increasing; row "
                    f"{bad + 1} has index {self.index[bad + 1]} after {self.index[bad]}"
                )
            if np.any(np.diff(self.t_ns) < 0):
                bad = int(np.flatnonzero(np.diff(self.t_ns) < 0)[0])
                raise SelectionError(
                    "ScoreTable.t_ns must be non-decreasing (log-time order); frame "
                    f"{self.index[bad + 1]} has t_ns {self.t_ns[bad + 1]} < {self.t_ns[bad]}"
                )
        if self.positions is not None:
            p = np.asarray(self.positions, dtype=np.float64)
            if p.ndim != 2 or p.shape[0] != n or p.shape[1] not in (2, 3):
                raise SelectionError(
                    f"ScoreTable.positions must have shape [{n}, 2] or [{n}, 3], got {p.shape}"
                )
            self.positions = p.copy()
        if self.descriptors is not None:
            d = np.asarray(self.descriptors)
            if d.ndim != 2 or d.shape[0] != n or d.shape[1] < 1:
                raise SelectionError(
                    f"ScoreTable.descriptors must have shape [{n}, d] with d >= 1, got {d.shape}"
                )
            d = d.astype(np.float32, copy=True)
            ok = np.all(np.isfinite(d), axis=1)
            norms = np.linalg.norm(d[ok].astype(np.float64), axis=1)
            off = np.abs(norms - 1.0) > _UNIT_NORM_TOL
            if np.any(off):
                row = int(np.flatnonzero(ok)[np.flatnonzero(off)[0]])
                raise SelectionError(
                    "ScoreTable.descriptors must be L2-normalised; frame "
                    f"{self.index[row]} has norm {norms[np.flatnonzero(off)[0]]:.6g}"
                )
            self.descriptors = d

    def __len__(self) -> int:
        return len(self.index)

    @property
    def n(self) -> int:
        """Number of frames (rows)."""
        return len(self.index)

    def known_positions(self) -> NDArray[np.bool_]:
        """Rows whose position is known (all coordinates finite); all False without positions."""
        if self.positions is None:
            return np.zeros(self.n, dtype=bool)
        return np.asarray(np.all(np.isfinite(self.positions), axis=1), dtype=bool)

    def known_descriptors(self) -> NDArray[np.bool_]:
        """Rows whose descriptor is known (all finite); all False without descriptors."""
        if self.descriptors is None:
            return np.zeros(self.n, dtype=bool)
        return np.asarray(np.all(np.isfinite(self.descriptors), axis=1), dtype=bool)

    def take(self, rows: ArrayLike) -> ScoreTable:
        """A new table with the given rows (a bool mask or increasing row positions)."""
        r = np.asarray(rows)
        if r.dtype == bool:
            if r.shape != (self.n,):
                raise SelectionError(f"row mask must have shape ({self.n},), got {r.shape}")
            r = np.flatnonzero(r)
        return ScoreTable(
            index=self.index[r],
            t_ns=self.t_ns[r],
            ms=self.ms[r],
            ss=self.ss[r],
            es=self.es[r],
            positions=None if self.positions is None else self.positions[r],
            descriptors=None if self.descriptors is None else self.descriptors[r],
            topic=self.topic,
            ds=None if self.ds is None else self.ds[r],
            view=None if self.view is None else self.view[r],
            motion=None if self.motion is None else self.motion.take(r),
        )

    def blank_view(self) -> NDArray[np.bool_]:
        """Rows whose view vector is blank (a flat frame: zero vector); all False without view vectors."""
        if self.view is None:
            return np.zeros(self.n, dtype=bool)
        return blank_views(self.view)


@dataclass(eq=False)
class Gap:
    """A place segment of which no frame passed the minimum thresholds (so none was kept).

    ``start_index``/``end_index`` are the frame indices of its first/last frame (inclusive),
    ``start_t_ns``/``end_t_ns`` their log times; ``reason`` is the criterion most of its
    frames failed first (ties go to the earlier stage), ``counts`` the number per criterion.
    """

    segment: int
    start_index: int
    end_index: int
    start_t_ns: int
    end_t_ns: int
    n_frames: int
    reason: str
    counts: dict[str, int] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict."""
        return {
            "segment": self.segment,
            "start_index": self.start_index,
            "end_index": self.end_index,
            "start_t_ns": self.start_t_ns,
            "end_t_ns": self.end_t_ns,
            "n_frames": self.n_frames,
            "reason": self.reason,
            "counts": dict(self.counts),
        }


def _jsonable(value: Any) -> Any:
    """Convert numpy scalars/arrays, tuples and nested containers to JSON-ready values."""
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return [_jsonable(v) for v in value.tolist()]
    if isinstance(value, np.generic):
        return _jsonable(value.item())
    if isinstance(value, float) and not np.isfinite(value):
        return None
    if hasattr(value, "to_dict"):
        return _jsonable(value.to_dict())
    return value


@dataclass(eq=False)
class Selection:
    """Which frames of a :class:`ScoreTable` to keep, and why the others were dropped.

    ``keep[i]`` and ``reason[i]`` refer to row ``i`` of the table (frame ``index[i]``);
    ``reason[i]`` is None exactly for kept frames, else one of :data:`REASONS`.
    ``thresholds`` are the thresholds a kept frame had to pass (keys ``mt``, ``st``,
    ``et``; empty for baselines); ``duplicates`` maps a frame index dropped as a
    near-duplicate to the frame index of the kept frame it repeats; ``segment_id`` gives
    the place segment of each row for segment selections.
    """

    mode: str
    index: NDArray[np.int64]
    keep: NDArray[np.bool_]
    reason: list[str | None]
    thresholds: dict[str, float] = field(default_factory=dict)
    gaps: list[Gap] = field(default_factory=list)
    duplicates: dict[int, int] = field(default_factory=dict)
    info: dict[str, Any] = field(default_factory=dict)
    segment_id: NDArray[np.int64] | None = None

    def __post_init__(self) -> None:
        self.index = np.asarray(self.index, dtype=np.int64)
        self.keep = np.asarray(self.keep, dtype=bool)
        n = len(self.index)
        if self.keep.shape != (n,) or len(self.reason) != n:
            raise SelectionError(
                f"Selection: index ({n}), keep {self.keep.shape} and reason "
                f"({len(self.reason)}) must have the same length"
            )
        for i, (k, r) in enumerate(zip(self.keep.tolist(), self.reason)):
            if k != (r is None):
                raise SelectionError(
                    f"Selection: frame {self.index[i]} is {'kept' if k else 'dropped'} "
                    f"but has reason {r!r} (reason must be None exactly for kept frames)"
                )
            if r is not None and r not in REASONS:
                raise SelectionError(f"Selection: unknown reason {r!r} for frame {self.index[i]}")

    @property
    def n_frames(self) -> int:
        """Number of frames the selection covers."""
        return len(self.index)

    @property
    def n_kept(self) -> int:
        """Number of kept frames."""
        return int(np.count_nonzero(self.keep))

    @property
    def kept_rows(self) -> NDArray[np.int64]:
        """Row positions (0..N-1) of the kept frames."""
        return np.flatnonzero(self.keep).astype(np.int64)

    @property
    def kept_indices(self) -> NDArray[np.int64]:
        """Frame indices (``table.index``) of the kept frames."""
        return self.index[self.keep]

    @property
    def fraction(self) -> float:
        """Kept frames / all frames (0.0 for an empty table)."""
        return self.n_kept / self.n_frames if self.n_frames else 0.0

    def shortfall(self) -> str | None:
        """Why a segment selection kept fewer frames than its keep fraction asks (some segments
        hold no frame: a stop is one place), or None when it kept as many as asked or its size
        came from the drive's view change (``spacing_view``: no fraction was asked)."""
        asked, made = self.info.get("n_bins"), self.info.get("n_segments")
        if asked is None or made is None or made >= asked or "spacing_view" in self.info:
            return None
        still = self.info.get("still_frames") or 0
        return (f"fewer frames than --keep-fraction asks: {made} of the {asked} segments hold a frame"
                + (f" ({still} frame(s) stood still, and a stop is one place)" if still else ""))

    def reason_counts(self) -> dict[str, int]:
        """Number of dropped frames per reason."""
        return dict(Counter(r for r in self.reason if r is not None))

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary: counts, kept frame indices, dropped frames with reasons."""
        out: dict[str, Any] = {
            "mode": self.mode,
            "n_frames": self.n_frames,
            "n_kept": self.n_kept,
            "fraction": self.fraction,
            "thresholds": dict(self.thresholds),
            "kept_indices": self.kept_indices.tolist(),
            "reason_counts": self.reason_counts(),
            "dropped": [
                [int(i), r] for i, r in zip(self.index.tolist(), self.reason) if r is not None
            ],
            "gaps": [g.to_dict() for g in self.gaps],
            "duplicates": [[int(k), int(v)] for k, v in self.duplicates.items()],
            "info": self.info,
        }
        result: dict[str, Any] = _jsonable(out)
        return result

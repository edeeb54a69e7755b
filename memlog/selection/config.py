"""One typed selection config, built once (flags or the ``[select]`` table) and passed down.

:class:`SelectionConfig` says how the map's frames are chosen; :meth:`SelectionConfig.run`
applies it to a :class:`~memlog.selection.table.ScoreTable` through the named selectors of
:mod:`memlog.selection.selectors`, then drops near-duplicates when ``dedup`` is set.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any, Literal

from memlog.errors import ConfigError
from memlog.settings import Flag, cosine_distance, nonneg_float, positive_float, setting, unit_interval
from memlog.settings import fraction as a_fraction
from memlog.selection._checks import finite_number, fraction, positive_number
from memlog.selection.redundancy import RedundancyConfig
from memlog.selection.segment import SEGMENT_DEFAULTS, SIZE_KEYS
from memlog.selection.selectors import select
from memlog.selection.table import ScoreTable, Selection

__all__ = ["SelectionConfig", "SIZES"]

#: The settings that size a map (at most one is given): a keep fraction, then the spacings.
SIZES = tuple(k for k in SIZE_KEYS if k != "spacing_frames")


DEFAULT_CANDIDATES: int | Literal["all"] = 1
"""``memlog map --candidates``: segment selection runs ResMem on at most this many frames per
segment (``"all"``: exactly the frames that can still win). Chosen on the Nordland pair with
``benchmarks/shortlist_table.py`` and ``benchmarks/run.py map`` (README, defaults table)."""

@dataclass(frozen=True)
class SelectionConfig:
    """How frames are selected for the map.

    ``mode``: ``"segment"`` (default: the best frame of each place segment) or ``"paper"`` (the
    tri-threshold rule). ``keep_fraction``: paper mode calibrates the thresholds to keep this
    fraction; segment mode makes this fraction of the frames segments. ``spacing_view``: segment
    mode, one frame per this much view change (the default size when none is given:
    ``SEGMENT_DEFAULTS.view_spacing``). ``mt``/``st``/``et``: the paper rule's fixed thresholds
    (the scoring config's). ``spacing_m``/``spacing_s``: segment mode, one frame per metres / seconds.
    ``segment_by``: how segments are cut. ``dedup``: drop a kept frame within this cosine
    distance of an already kept one (descriptor: the thumbnail). ``min_ss``/``min_ms``/``min_es``,
    ``weights``, ``combine``, ``still_distance``, ``centre_tolerance`` (the ``--candidates`` shortlist's
    preference for a segment's middle): segment mode's tuning (defaults:
    :data:`~memlog.selection.segment.SEGMENT_DEFAULTS`, chosen on the shared Nordland slice).
    ``view_distance`` (with ``segment_by="view"`` and no size): a new segment where the view moved
    this far (cosine distance) from the segment's first frame, instead of ``keep_fraction``.

    Distinctiveness (:mod:`memlog.selection.distinctiveness`), a fourth criterion computed from
    the reference drive's (whitened) descriptors: ``dt`` is its threshold in paper mode (keep
    DS >= dt), ``distinct_weight`` its weight in segment mode's combined score;
    ``distinct_window``/``distinct_exclusion`` (rows) say what counts as the frame's own place
    and as a distant part of the drive.
    """

    mode: Literal["segment", "paper"] = setting("segment", Flag(
        ("--select",), "segment (default): the best frame of each place segment by the three scores, so no stretch "
        "of the drive is lost; paper: the frames passing MT/ST/ET", choices=("paper", "segment"), dest="select"))
    keep_fraction: float | None = setting(None, Flag(
        ("--keep-fraction",), "keep about this fraction of the frames: segment size (segment) or thresholds "
        "(paper). Default (segment): sized by the drive's view change, see --spacing-view", check=a_fraction,
        metavar="F"))
    mt: float = 0.5
    st: float = 0.6
    et: float = 0.4
    spacing_view: float | None = setting(None, Flag(
        ("--spacing-view",), "segment: one frame per this much view change (capped chords of the 32x16 view "
        f"vectors, stops left out; the default size, {SEGMENT_DEFAULTS.view_spacing:g}: a frame per step that "
        "changed the whole view, so a sparse route keeps every moving frame and a video one frame per several)",
        "selection", positive_float, metavar="V"))
    spacing_m: float | None = setting(None, Flag(("--spacing-m",), "segment: one frame per this many metres "
                                                 "travelled", "selection", positive_float, metavar="M"))
    spacing_s: float | None = setting(None, Flag(("--spacing-s",), "segment: one frame per this many seconds",
                                                 "selection", positive_float, metavar="S"))
    segment_by: Literal["auto", "distance", "time", "count", "view"] = setting(SEGMENT_DEFAULTS.by, Flag(
        ("--segment-by",), "segment boundaries", "selection", choices=("auto", "distance", "time", "count", "view")))
    dedup: float | None = setting(None, Flag(
        ("--dedup",), "drop kept frames within this cosine distance (thumbnail descriptor) of an already kept one "
        "(loops, stops)", "selection", cosine_distance, metavar="DIST"))
    min_ms: float = SEGMENT_DEFAULTS.min_ms
    min_ss: float = SEGMENT_DEFAULTS.min_ss
    min_es: float = SEGMENT_DEFAULTS.min_es
    weights: tuple[float, float, float] = SEGMENT_DEFAULTS.weights
    combine: Literal["geometric", "rank"] = SEGMENT_DEFAULTS.combine
    view_distance: float | None = None
    still_distance: float = SEGMENT_DEFAULTS.still_distance
    centre_tolerance: float = SEGMENT_DEFAULTS.centre_tolerance
    dt: float | None = setting(None, Flag(
        ("--dt",), "(experimental) paper mode: also keep only frames whose distinctiveness (rank in the drive, 0..1) "
        "is >= DT (computed from the reference drive's descriptors; off: it did not beat uniform maps)",
        "experimental", unit_interval))
    distinct_weight: float = setting(SEGMENT_DEFAULTS.distinct_weight, Flag(
        ("--distinct-weight",), "(experimental) segment mode: weight of distinctiveness in the combined score (0 = "
        "off; with weights = [0, 0, 0] in the --config file's [select] table it selects by distinctiveness alone)",
        "experimental", nonneg_float, metavar="W"))
    distinct_window: int = 2
    distinct_exclusion: int = 10

    def __post_init__(self) -> None:
        if self.mode not in ("segment", "paper"):
            raise ConfigError(f"select mode must be 'segment' or 'paper', got {self.mode!r}")
        if self.keep_fraction is not None:
            fraction("keep_fraction", self.keep_fraction)
        for name in ("mt", "st", "et"):
            v = finite_number(name, getattr(self, name))
            if not 0.0 <= v <= 1.0:
                raise ConfigError(f"{name} must be within [0, 1], got {v}")
        spacings = [k for k in SIZES[1:] if getattr(self, k) is not None]
        for name in spacings:
            positive_number(name, getattr(self, name))
        seg_only = list(spacings)
        if self.segment_by != "auto":
            seg_only.append("segment_by")
        if seg_only and self.mode != "segment":
            raise ConfigError(f"{', '.join(seg_only)} need the segment selection mode")
        sizes = [k for k in SIZES if getattr(self, k) is not None]
        if len(sizes) > 1:
            raise ConfigError(f"give one of {', '.join(SIZES)} (got {', '.join(sizes)})")
        if self.view_distance is not None and (self.segment_by != "view" or sizes):
            raise ConfigError("view_distance sizes segments by view change: it needs segment_by='view' and no "
                              "keep_fraction or spacing")
        if self.dedup is not None:
            RedundancyConfig(dup_distance=self.dedup)  # checks the range
        if self.dt is not None:
            v = finite_number("dt", self.dt)
            if not 0.0 <= v <= 1.0:
                raise ConfigError(f"dt must be within [0, 1], got {v}")
            if self.mode != "paper":
                raise ConfigError("dt (distinctiveness threshold) needs the paper selection mode; segment mode "
                                  "weighs distinctiveness with distinct_weight")
            if self.keep_fraction is not None:
                raise ConfigError("dt cannot be combined with keep_fraction (calibrated thresholds): give the "
                                  "thresholds, or use segment mode with distinct_weight")
        if finite_number("distinct_weight", self.distinct_weight) < 0:
            raise ConfigError(f"distinct_weight must be >= 0, got {self.distinct_weight}")
        if self.distinct_weight > 0 and self.mode != "segment":
            raise ConfigError("distinct_weight needs the segment selection mode; paper mode uses dt")
        self.distinct_config()  # checks window/exclusion
        if self.mode == "segment":
            self.segment_settings()  # checks by/size/minimums together

    # -- what the run needs ----------------------------------------------------------------
    @property
    def needs_descriptors(self) -> bool:
        """Whether selecting needs a descriptor per frame (near-duplicates)."""
        return self.dedup is not None

    @property
    def needs_view(self) -> bool:
        """Whether selecting needs every frame's view vector (segments by view change, and the
        stops that every segment coordinate leaves out)."""
        return self.mode == "segment"

    @property
    def needs_distinctiveness(self) -> bool:
        """Whether selecting needs the distinctiveness of every frame (descriptors of the whole drive)."""
        return self.dt is not None or (self.mode == "segment" and self.distinct_weight > 0)

    def distinct_config(self) -> Any:
        """Settings of :func:`~memlog.selection.distinctiveness.distinctiveness`."""
        from memlog.selection.distinctiveness import DistinctConfig

        return DistinctConfig(window=self.distinct_window, exclusion=self.distinct_exclusion)

    @property
    def needs_all_scores(self) -> bool:
        """Whether selecting needs every score of every frame (segment mode, calibration)."""
        return self.mode == "segment" or self.keep_fraction is not None

    @property
    def thresholds(self) -> dict[str, float]:
        """The paper rule's thresholds (``dt`` only when set)."""
        th = {"mt": self.mt, "st": self.st, "et": self.et}
        if self.dt is not None:
            th["dt"] = self.dt
        return th

    def segment_settings(self) -> dict[str, Any]:
        """Settings of the segment selector (:class:`~memlog.selection.segment.SegmentConfig`)."""
        from memlog.selection.segment import SegmentConfig

        kw: dict[str, Any] = {
            "by": self.segment_by, "min_ms": self.min_ms, "min_ss": self.min_ss, "min_es": self.min_es,
            "weights": tuple(self.weights), "combine": self.combine,
            "view_distance": SEGMENT_DEFAULTS.view_distance if self.view_distance is None else self.view_distance,
            "still_distance": self.still_distance, "centre_tolerance": self.centre_tolerance,
            "distinct_weight": self.distinct_weight,
        }
        given = {k: getattr(self, k) for k in SIZES if getattr(self, k) is not None}
        if given:
            kw.update(given)  # one at most (checked above)
        elif self.view_distance is None or self.segment_by != "view":
            kw["spacing_view"] = SEGMENT_DEFAULTS.view_spacing
        SegmentConfig(**kw)
        return kw

    def run(self, table: ScoreTable, *, shortlist: int | None = None, ms_bound: str = "ss") -> Selection:
        """Select frames of ``table`` by this config; segment mode with ``shortlist=K``: the
        best of K candidates per segment (``memlog map --candidates K``, see
        :class:`~memlog.selection.segment.SegmentConfig`)."""
        dedup = None if self.dedup is None else RedundancyConfig(dup_distance=self.dedup)
        if self.mode == "paper":
            if self.keep_fraction is not None:
                return select(table, "calibrated", keep_fraction=self.keep_fraction, dedup=dedup)
            return select(table, "paper", dedup=dedup, **self.thresholds)
        return select(table, "segment", dedup=dedup, shortlist=shortlist, ms_bound=ms_bound, **self.segment_settings())

    def label(self) -> str:
        """What a selection's thresholds are, for messages."""
        return "segment minimum scores" if self.mode == "segment" else "thresholds"

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready settings."""
        d = asdict(self)
        d["weights"] = list(self.weights)
        return d

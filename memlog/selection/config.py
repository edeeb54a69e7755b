"""One typed selection config, built once (flags or the ``[select]`` table) and passed down.

:class:`SelectionConfig` says how the map's frames are chosen; :meth:`SelectionConfig.run`
applies it to a :class:`~memlog.selection.table.ScoreTable` through the named selectors of
:mod:`memlog.selection.selectors`, then drops near-duplicates when ``dedup`` is set.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any, Literal

from memlog.errors import ConfigError
from memlog.selection._checks import finite_number, fraction, positive_number
from memlog.selection.redundancy import RedundancyConfig
from memlog.selection.selectors import SELECTORS, select
from memlog.selection.table import ScoreTable, Selection

__all__ = ["SelectionConfig"]


@dataclass(frozen=True)
class SelectionConfig:
    """How frames are selected for the map.

    ``mode``: ``"segment"`` (default: the best frame of each place segment) or ``"paper"`` (the
    tri-threshold rule). ``keep_fraction``: paper mode calibrates the thresholds to keep this
    fraction; segment mode makes this fraction of the frames segments (default 0.25 when no
    spacing is given). ``mt``/``st``/``et``: the paper rule's fixed thresholds (the scoring
    config's). ``spacing_m``/``spacing_s``: segment mode, one frame per metres / seconds.
    ``segment_by``: how segments are cut. ``dedup``: drop a kept frame within this cosine
    distance of an already kept one (descriptor: the thumbnail). ``min_ss``/``min_ms``/``min_es``,
    ``weights``, ``combine``, ``view_distance``: segment mode's tuning (defaults chosen on the
    shared Nordland slice, see :mod:`memlog.selection.segment`).
    """

    mode: Literal["segment", "paper"] = "segment"
    keep_fraction: float | None = None
    mt: float = 0.5
    st: float = 0.6
    et: float = 0.4
    spacing_m: float | None = None
    spacing_s: float | None = None
    segment_by: Literal["auto", "distance", "time", "count", "view"] = "auto"
    dedup: float | None = None
    min_ms: float = float(SELECTORS["segment"]["min_ms"])
    min_ss: float = float(SELECTORS["segment"]["min_ss"])
    min_es: float = float(SELECTORS["segment"]["min_es"])
    weights: tuple[float, float, float] = tuple(SELECTORS["segment"]["weights"])
    combine: Literal["geometric", "rank"] = SELECTORS["segment"]["combine"]
    view_distance: float = float(SELECTORS["segment"]["view_distance"])

    def __post_init__(self) -> None:
        if self.mode not in ("segment", "paper"):
            raise ConfigError(f"select mode must be 'segment' or 'paper', got {self.mode!r}")
        if self.keep_fraction is not None:
            fraction("keep_fraction", self.keep_fraction)
        for name in ("mt", "st", "et"):
            v = finite_number(name, getattr(self, name))
            if not 0.0 <= v <= 1.0:
                raise ConfigError(f"{name} must be within [0, 1], got {v}")
        for name in ("spacing_m", "spacing_s"):
            if getattr(self, name) is not None:
                positive_number(name, getattr(self, name))
        seg_only = [k for k in ("spacing_m", "spacing_s") if getattr(self, k) is not None]
        if self.segment_by != "auto":
            seg_only.append("segment_by")
        if seg_only and self.mode != "segment":
            raise ConfigError(f"{', '.join(seg_only)} need the segment selection mode")
        sizes = [k for k in ("keep_fraction", "spacing_m", "spacing_s") if getattr(self, k) is not None]
        if len(sizes) > 1:
            raise ConfigError(f"give one of keep_fraction, spacing_m, spacing_s (got {', '.join(sizes)})")
        if self.dedup is not None:
            RedundancyConfig(dup_distance=self.dedup)  # checks the range
        if self.mode == "segment":
            self.segment_settings()  # checks by/size/minimums together

    # -- what the run needs ----------------------------------------------------------------
    @property
    def needs_descriptors(self) -> bool:
        """Whether selecting needs a descriptor per frame (near-duplicates, view segments)."""
        return self.dedup is not None or (self.mode == "segment" and self.segment_by == "view")

    @property
    def needs_all_scores(self) -> bool:
        """Whether selecting needs every score of every frame (segment mode, calibration)."""
        return self.mode == "segment" or self.keep_fraction is not None

    @property
    def thresholds(self) -> dict[str, float]:
        """The paper rule's thresholds."""
        return {"mt": self.mt, "st": self.st, "et": self.et}

    def segment_settings(self) -> dict[str, Any]:
        """Settings of the segment selector (:class:`~memlog.selection.segment.SegmentConfig`)."""
        from memlog.selection.segment import SegmentConfig

        kw: dict[str, Any] = {
            "by": self.segment_by, "min_ms": self.min_ms, "min_ss": self.min_ss, "min_es": self.min_es,
            "weights": tuple(self.weights), "combine": self.combine, "view_distance": self.view_distance,
        }
        if self.keep_fraction is not None:
            kw["keep_fraction"] = self.keep_fraction
        elif self.spacing_m is not None:
            kw["spacing_m"] = self.spacing_m
        elif self.spacing_s is not None:
            kw["spacing_s"] = self.spacing_s
        elif self.segment_by != "view":
            kw["keep_fraction"] = float(SELECTORS["segment"]["keep_fraction"])
        SegmentConfig(**kw)
        return kw

    def run(self, table: ScoreTable) -> Selection:
        """Select frames of ``table`` by this config."""
        dedup = None if self.dedup is None else RedundancyConfig(dup_distance=self.dedup)
        if self.mode == "paper":
            if self.keep_fraction is not None:
                return select(table, "calibrated", keep_fraction=self.keep_fraction, dedup=dedup)
            return select(table, "paper", dedup=dedup, **self.thresholds)
        return select(table, "segment", dedup=dedup, **self.segment_settings())

    def label(self) -> str:
        """What a selection's thresholds are, for messages."""
        return "segment minimum scores" if self.mode == "segment" else "thresholds"

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready settings."""
        d = asdict(self)
        d["weights"] = list(self.weights)
        return d

"""Named default configurations (hloc style) and the :func:`select` entry point."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import fields
from typing import Any

from memlog.errors import ConfigError
from memlog.selection.calibrate import CalibrateConfig, select_calibrated
from memlog.selection.paper import PaperConfig, select_paper
from memlog.selection.redundancy import RedundancyConfig, drop_duplicates
from memlog.selection.segment import SEGMENT_DEFAULTS, SIZE_KEYS, SegmentConfig, select_segments
from memlog.selection.table import ScoreTable, Selection

__all__ = ["SELECTORS", "select"]

#: Default settings per selection mode; :func:`select` overrides them by keyword.
SELECTORS: dict[str, dict[str, Any]] = {
    "paper": {"mt": 0.5, "st": 0.6, "et": 0.4},
    "calibrated": {"keep_fraction": 0.1},
    # memlog.selection.segment.SEGMENT_DEFAULTS: the one source (chosen on the shared Nordland slice)
    "segment": SEGMENT_DEFAULTS.config_dict(),
}

_RUNNERS: dict[str, tuple[type[Any], Callable[[ScoreTable, Any], Selection]]] = {
    "paper": (PaperConfig, select_paper),
    "calibrated": (CalibrateConfig, select_calibrated),
    "segment": (SegmentConfig, select_segments),
}

def select(
    table: ScoreTable,
    name: str,
    *,
    dedup: RedundancyConfig | Mapping[str, Any] | None = None,
    **overrides: Any,
) -> Selection:
    """Run the selector ``name`` with ``SELECTORS[name]`` updated by ``overrides``; then,
    if ``dedup`` is given, drop near-duplicates (:func:`drop_duplicates`).

    For "segment", giving a size (``keep_fraction``, ``spacing_view``/``spacing_m``/``spacing_s``/
    ``spacing_frames``), or ``view_distance`` with ``by="view"`` (segments of a fixed view change
    from their first frame), replaces the default size (``spacing_view``: one frame per
    ``SEGMENT_DEFAULTS.view_spacing`` of view change).
    """
    if name not in _RUNNERS:
        raise ConfigError(f"unknown selector {name!r}; choose one of {sorted(_RUNNERS)}")
    cls, run = _RUNNERS[name]
    settings = dict(SELECTORS.get(name, {}))
    valid = {f.name for f in fields(cls)}
    unknown = sorted(set(overrides) - valid)
    if unknown:
        raise ConfigError(f"unknown setting(s) {unknown} for selector {name!r}; valid: {sorted(valid)}")
    if name == "segment" and "spacing_view" not in overrides:
        if any(overrides.get(k) is not None for k in SIZE_KEYS) or (
                overrides.get("by") == "view" and "view_distance" in overrides):
            settings.pop("spacing_view", None)
    settings.update(overrides)
    if "weights" in settings and settings["weights"] is not None:
        settings["weights"] = tuple(settings["weights"])
    try:
        config = cls(**settings)
    except TypeError as exc:  # e.g. a default dict edited to hold a wrong key
        raise ConfigError(f"invalid settings for selector {name!r}: {exc}") from exc
    sel = run(table, config)
    if dedup is not None:
        rcfg = dedup if isinstance(dedup, RedundancyConfig) else _redundancy(dedup)
        sel = drop_duplicates(table, sel, rcfg)
    return sel


def _redundancy(settings: Mapping[str, Any]) -> RedundancyConfig:
    valid = {f.name for f in fields(RedundancyConfig)}
    unknown = sorted(set(settings) - valid)
    if unknown:
        raise ConfigError(f"unknown dedup setting(s) {unknown}; valid: {sorted(valid)}")
    return RedundancyConfig(**settings)

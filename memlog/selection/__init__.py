"""memlog.selection: choose which scored frames form the memorable map.

Pure numpy on per-frame :class:`ScoreTable` s. Modes: the paper's tri-threshold rule
(``paper``), thresholds calibrated to a keep fraction (``calibrated``), one best frame per
place segment (``segment``); plus near-duplicate removal and uniform/random baselines.
"""

from __future__ import annotations

from memlog.selection.baselines import (
    baseline_selection,
    distance_uniform_mask,
    random_indices,
    random_mask,
    random_masks,
    uniform_indices,
    uniform_mask,
    phase_masks,
)
from memlog.selection.calibrate import CalibrateConfig, Calibration, calibrate, select_calibrated
from memlog.selection.paper import PaperConfig, select_paper
from memlog.selection.redundancy import (
    Duplicates,
    RedundancyConfig,
    drop_duplicates,
    find_duplicates,
)
from memlog.selection.segment import SEGMENT_DEFAULTS, SegmentConfig, combined_score, segment_ids, select_segments
from memlog.selection.selectors import SELECTORS, select
from memlog.selection.table import Gap, ScoreTable, Selection

__all__ = [
    "ScoreTable",
    "Selection",
    "Gap",
    "SELECTORS",
    "select",
    "PaperConfig",
    "select_paper",
    "CalibrateConfig",
    "Calibration",
    "calibrate",
    "select_calibrated",
    "SegmentConfig",
    "SEGMENT_DEFAULTS",
    "select_segments",
    "segment_ids",
    "combined_score",
    "RedundancyConfig",
    "Duplicates",
    "find_duplicates",
    "drop_duplicates",
    "distance_uniform_mask",
    "uniform_indices",
    "uniform_mask",
    "phase_masks",
    "random_indices",
    "random_mask",
    "random_masks",
    "baseline_selection",
]

"""The drive matcher: localize a drive against a map as sequences of frames, not frame by frame.

One module per job: :mod:`~memlog.matching.config` (settings, constants and result),
:mod:`~memlog.matching.coordinates` (the drives' coordinates, runs and stops),
:mod:`~memlog.matching.paths` (path scoring), :mod:`~memlog.matching.voting` (votes and places),
:mod:`~memlog.matching.sequences` (sequences of descriptor arrays), :mod:`~memlog.matching.rerank`
(the patch re-rank), :mod:`~memlog.matching.drive_hmm` (the drive HMM),
:mod:`~memlog.matching.ensemble` (the whitening ensemble) and :mod:`~memlog.matching.matcher`
(:func:`match_tables`, what ``memlog localize`` and ``memlog evaluate`` run). The matcher stage by
stage, each constant in one sentence and what each stage was measured to gain: ``docs/method.md``
("The drive matcher, stage by stage").
"""

from __future__ import annotations

from memlog.matching.config import COORDINATES, FALLBACK_REASONS, STAT_SAMPLE, SequenceConfig, SequenceMatch
from memlog.matching.coordinates import (
    drive_coordinates, drive_runs, has_positions, reference_unit, resolve_coordinate, standing_rows, uses_stops,
)
from memlog.matching.drive_hmm import place_probabilities
from memlog.matching.matcher import match_tables
from memlog.matching.rerank import RERANK_PLACES, rerank_by_patches
from memlog.matching.sequences import match_sequences

__all__ = [
    "SequenceConfig", "SequenceMatch", "match_sequences", "match_tables", "drive_coordinates",
    "drive_runs", "resolve_coordinate", "has_positions", "reference_unit", "standing_rows", "uses_stops",
    "rerank_by_patches", "place_probabilities", "COORDINATES", "STAT_SAMPLE", "FALLBACK_REASONS",
    "RERANK_PLACES",
]

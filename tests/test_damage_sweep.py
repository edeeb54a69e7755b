"""A fast, representative part of the damage sweep (``benchmarks/damage_sweep.py`` runs it all).

Every case is a damaged or wrong copy of a fixture log; the frame stream, ``inspect`` and
``convert`` must give no traceback, hang, internal error, modified input, leftover temporary or
partial file, and must return every message that survived the damage (computed independently
from the intact log by :mod:`tests.damage_kit`). Damage must be reported (exit 3).
"""

from __future__ import annotations

import random
from pathlib import Path

import pytest

from tests.conftest import FIXTURES
from tests.damage_kit import (Case, image_cases, mcap_cases, pipeline_cases, ros1_cases, ros2_cases, run_case,
                              run_pipeline_case)
from tests.stand_in import use_stand_in

_PICK = {
    # MCAP: the index holes and a few cuts/flips
    "demo.mcap:chunk-index-offset+7 (CRC fixed)", "demo.mcap:chunk-index-offset+7 (CRC kept)",
    "demo.mcap:chunk-length-huge (CRC fixed)", "demo.mcap:chunk-length-huge (CRC zeroed)",
    "demo.mcap:chunk-index-entry-dropped (CRC fixed)", "demo.mcap:summary-channel-topic-flip (CRC kept)",
    "demo.mcap:summary-channel-topic-flip (CRC zeroed)", "demo.mcap:summary-crc-garbage",
    "demo.mcap:footer-summary-start-huge", "demo.mcap:chunk-uncompressed-size-huge",
    "demo.mcap:chunk-record-length-huge", "demo.mcap:cut+zeros-32MiB",
    # ROS 1
    "ros1.bag:bag-header-conn_count=0", "ros1.bag:bag-header-chunk_count=0", "ros1.bag:bag-header-index_pos=0",
    "ros1.bag:index-data-garbage", "ros1.bag:index-section-garbage", "ros1.bag:index-conn-topic-flip",
    "ros1.bag:chunk-op-5-to-2", "ros1.bag:magic-line-only", "ros1.bag:cut+zeros-32MiB",
    "ros1.bag:chunk-size-field-huge",
    # ROS 2
    "ros2_sqlite:metadata-missing", "ros2_sqlite:metadata-empty", "ros2_sqlite:metadata-garbage",
    "ros2_sqlite:metadata-empty-file-list", "ros2_sqlite:metadata-empty-topics", "ros2_sqlite:metadata-wrong-type",
    "ros2_sqlite:metadata-wrong-compression", "ros2_sqlite:metadata-wrong-counts",
    "ros2_sqlite:second-garbage-storage-file", "ros2_sqlite:storage-file-is-a-directory",
    "ros2_sqlite:text-timestamp", "ros2_sqlite:negative-timestamp", "ros2_sqlite:unknown-topic-id",
    "ros2_sqlite:text-data", "ros2_mcap:metadata-missing", "ros2_mcap:metadata-garbage",
    "ros2_mcap:second-garbage-storage-file",
}
_TRUNC, _FLIP = 3, 3


def _cases() -> list[Case]:
    rng = random.Random(10)
    out = mcap_cases(FIXTURES / "demo.mcap", rng, _TRUNC, _FLIP)
    out += ros1_cases(FIXTURES / "ros1.bag", rng, _TRUNC, _FLIP)
    out += ros2_cases(FIXTURES / "ros2_sqlite", rng, _TRUNC, 0)
    out += ros2_cases(FIXTURES / "ros2_mcap", rng, 0, 0)
    picked = [c for c in out if c.name in _PICK or c.kind == "truncate" or c.name.startswith("demo.mcap:flip@")]
    return picked + image_cases(FIXTURES)


CASES = _cases()


def test_the_subset_covers_every_named_case() -> None:
    assert _PICK <= {c.name for c in CASES}


@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
def test_damaged_input(case: Case, tmp_path: Path) -> None:
    out = run_case(case, tmp_path, limit=60)
    assert not out.problems, out.problems
    if case.kind != "garbage image":
        # damage that cost or changed something is reported everywhere (exit 3), or the log is refused (1)
        assert set(out.codes.values()) <= {1, 3}, out.codes
    else:
        assert out.codes["read"] == 3


PIPELINE = pipeline_cases(FIXTURES)


@pytest.mark.parametrize("case", PIPELINE, ids=[c.name for c in PIPELINE])
def test_the_pipeline_on_damaged_input(case: Case, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """map (one process and two workers), batch and evaluate on damaged logs: exit 3, complete maps
    of what was readable, each kept frame with its own bytes and scores, same output everywhere
    (ResMem is the stand-in: damage handling does not depend on the model)."""
    use_stand_in(monkeypatch)
    out = run_pipeline_case(case, tmp_path)
    assert not out.problems, out.problems
    assert out.codes["map"] == 3, out.codes

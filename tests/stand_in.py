"""A stand-in for ResMem in tests: a crop's 'memorability' is a smooth, deterministic function of
its pixels, so the crop loop, early exit, segments and thresholds are the real ones while a frame
costs milliseconds instead of seconds. The detector and entropy stay real.

* :func:`use_stand_in` (with pytest's ``monkeypatch``): this process's steps score with it, and
  so do the local worker processes it starts (they are spawned, not forked: each is given the
  stand-in when it starts, by :func:`worker_setup` in place of memlog's);
* :func:`install`: a Ray ``worker_process_setup_hook`` (``"tests.stand_in.install"``): in a Ray
  worker, the steps score with it while the file named by ``$MEMLOG_TEST_STAND_IN`` exists, and
  with the real ResMem otherwise (so one Ray instance serves both kinds of test).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from memlog.models.resmem import OUTPUT_NAME
from memlog.scoring.config import ScoreConfig
from memlog.scoring.memorability import Memorability
from memlog.scoring.scorer import Scorer

SWITCH_ENV = "MEMLOG_TEST_STAND_IN"


class StandInSession:
    """An ONNX-session stand-in: a crop's 'memorability' is a smooth function of its pixels."""

    def run(self, names: list[str], feeds: dict[str, np.ndarray]) -> list[np.ndarray]:
        assert names == [OUTPUT_NAME]
        x = next(iter(feeds.values())).astype(np.float64)
        mean = x.mean(axis=(1, 2, 3))
        std = x.std(axis=(1, 2, 3))
        return [(0.5 + 0.4 * np.tanh(3 * (mean - 0.45)) * 0.5 + 0.3 * std).reshape(-1, 1).astype(np.float32)]


def stand_in_scorer(config: ScoreConfig) -> Scorer:
    """A scorer with the real detector and entropy and the stand-in ResMem (its 'model file', for
    the provenance outputs record, is this module)."""
    mem = Memorability.__new__(Memorability)
    mem.path, mem.batch, mem.session = Path(__file__), 5, StandInSession()
    return Scorer(config, memorability=mem)


def _patched(real: Callable[[ScoreConfig], Scorer], active: Callable[[], bool]) -> Callable[[ScoreConfig], Scorer]:
    from memlog.steps.parallel import cached

    def scorer_for(config: ScoreConfig) -> Scorer:
        if active():
            return cached(("stand-in", config), lambda: stand_in_scorer(config))
        return real(config)

    return scorer_for


def use_stand_in(monkeypatch: Any) -> None:
    """Score with the stand-in in this process and in the local worker processes it starts."""
    from memlog.steps import map_scoring, parallel
    from memlog.steps import score as score_mod

    for mod in (map_scoring, score_mod):
        monkeypatch.setattr(mod, "_scorer_for", _patched(mod._scorer_for, lambda: True))
    monkeypatch.setattr(parallel, "worker_setup", worker_setup)


def worker_setup(quiet: bool, levels: dict[str, int]) -> None:
    """A local worker's start (``Processes`` passes it by name; a spawned worker imports memlog
    afresh, so this process's patches are not there): memlog's own, then the stand-in."""
    from memlog.steps import map_scoring, parallel
    from memlog.steps import score as score_mod

    parallel.worker_setup(quiet, levels)
    for mod in (map_scoring, score_mod):
        mod._scorer_for = _patched(mod._scorer_for, lambda: True)  # type: ignore[attr-defined]


def install() -> None:
    """Ray worker setup hook: the stand-in while ``$MEMLOG_TEST_STAND_IN`` names an existing file."""
    from memlog.steps import map_scoring
    from memlog.steps import score as score_mod

    def active() -> bool:
        flag = os.environ.get(SWITCH_ENV)
        return bool(flag) and os.path.exists(flag)

    for mod in (map_scoring, score_mod):
        mod._scorer_for = _patched(mod._scorer_for, active)  # type: ignore[attr-defined]

"""Staged segment selection: ResMem only where it can change the map, and the same map as scoring
every frame with every score.

* :func:`choose_in_segment` against brute force on random segments, with a crop loop that bounds
  MS the way ResMem's does (ties, minimum MS, normalised MS);
* ``memlog map`` staged vs every score on the demo fixture with the real ResMem;
* on the shared EuRoC and Nordland logs at several keep fractions, a spacing and with --dedup,
  with a stand-in ResMem (a deterministic function of each crop's pixels, so the crop loop,
  segments, positions and thresholds are the real ones and both runs stay fast).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from memlog.outputs.annotated import read_scores
from memlog.scoring.config import ScoreConfig
from memlog.selection import ScoreTable
from memlog.selection.config import SelectionConfig
from memlog.selection.segment import geometric_score, select_segments, SegmentConfig
from memlog.selection.staged import MSResult, choose_in_segment, ms_to_beat, shortlist_rows
from memlog.steps.map import MapConfig, make_map
from memlog.steps.score import score
from tests.conftest import FIXTURES, shared

DEMO = FIXTURES / "demo.mcap"
COMP = "/camera/image/compressed"


# -- the chooser against brute force --------------------------------------------------------------
def _crop_loop(m: np.ndarray, w: np.ndarray, threshold: float | None, known: np.ndarray | None,
               batch: int = 5) -> MSResult:
    """MS bounds as ResMem's crop loop gives them: crops by decreasing weight, unscored in 0..1."""
    vals = np.full(25, np.nan) if known is None else np.array(known, dtype=np.float64).reshape(-1)
    have = ~np.isnan(vals)
    order = [k for k in np.argsort(-w, kind="stable") if w[k] > 0 and not have[k]]
    done = float(np.dot(w[have], vals[have]))
    left = float(w[order].sum())
    before = int(have.sum())
    n = 0
    while n < len(order):
        if threshold is not None:
            if done >= threshold + 1e-6:
                return MSResult(done, done + left, False, vals.copy(), int((~np.isnan(vals)).sum()) - before)
            if done + left < threshold - 1e-6:
                return MSResult(done, done + left, False, vals.copy(), int((~np.isnan(vals)).sum()) - before)
        idx = order[n:n + batch]
        vals[idx] = m[idx]
        done += float(np.dot(w[idx], m[idx]))
        left -= float(w[idx].sum())
        n += len(idx)
    ms = float(np.dot(w, np.where(np.isnan(vals), 0.0, vals)))
    return MSResult(ms, ms, True, vals.copy(), int((~np.isnan(vals)).sum()) - before)


@pytest.mark.parametrize("seed", range(60))
def test_chooser_picks_the_brute_force_winner(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 14))
    ss = np.round(rng.uniform(0.3, 1.0, n), 6)
    es = np.round(rng.uniform(0.05, 0.5, n), 6)
    if seed % 5 == 0:  # exact ties in the cheap scores
        ss[:] = 1.0
        es[:] = es[0]
    weights = [(1.0, 1.0, 1.0), (2.0, 1.0, 1.0), (1.0, 0.0, 2.0)][seed % 3]
    min_ms = [0.0, 0.0, 0.3][seed % 3]
    crop_w = [rng.dirichlet(np.ones(25)) * s for s in ss]  # weights sum to SS, as for ResMem
    crop_m = [rng.uniform(0.4, 0.9, 25) if seed % 7 else np.full(25, 0.6) for _ in range(n)]  # %7==0: equal MS
    true_ms = np.array([float(np.dot(w, m)) for w, m in zip(crop_w, crop_m)])
    rounded = np.round(true_ms, 6)
    calls = {"crops": 0}

    def scorer(row: int, threshold: float | None, known: np.ndarray | None) -> MSResult:
        r = _crop_loop(crop_m[row], crop_w[row], threshold, known)
        calls["crops"] += r.crops_run
        return r

    winner, states = choose_in_segment(list(range(n)), ss, es, scorer, weights=weights, min_ms=min_ms)
    value = np.where(rounded >= min_ms, geometric_score(rounded, ss, es, weights), -np.inf)
    best = int(np.lexsort((np.arange(n), -value))[0])
    want = None if value[best] == -np.inf else best
    assert winner == want
    for r, st in states.items():  # bounds are bounds, and exact values are exact
        assert st.low - 1e-9 <= true_ms[r] <= st.high + 1e-9
        if st.exact:
            assert st.low == pytest.approx(true_ms[r], abs=1e-12)
    if winner is not None:
        assert states[winner].exact
    assert calls["crops"] <= 25 * n


def test_chooser_skips_what_cannot_win() -> None:
    """One clear winner by its cheap scores: the others never reach the CNN."""
    ss = np.array([1.0, 1.0, 1.0, 1.0])
    es = np.array([0.9, 0.05, 0.04, 0.03])
    m = [np.full(25, 0.8)] * 4
    w = [np.full(25, 1 / 25)] * 4
    scored: list[int] = []

    def scorer(row: int, threshold: float | None, known: np.ndarray | None) -> MSResult:
        scored.append(row)
        return _crop_loop(m[row], w[row], threshold, known)

    winner, states = choose_in_segment([0, 1, 2, 3], ss, es, scorer)
    assert winner == 0 and scored == [0]
    assert not states[1].scored and states[1].low == 0.0 and states[1].high == pytest.approx(1.0)


def test_ms_to_beat_inverts_the_score() -> None:
    for ss, es, ms in ((0.9, 0.3, 0.7), (1.0, 0.05, 0.2), (0.5, 0.5, 0.99)):
        for w in ((1.0, 1.0, 1.0), (2.0, 0.0, 1.0)):
            v = float(geometric_score(ms, ss, es, w)[0])
            assert ms_to_beat(v, ss, es, w) == pytest.approx(ms, rel=1e-9)
    assert ms_to_beat(0.5, 0.0, 0.3, (1.0, 1.0, 1.0)) == math.inf


def test_shortlist_spreads_over_the_segment() -> None:
    rows = list(range(10))
    upper = [0.9, 0.8, 0.1, 0.2, 0.3, 0.95, 0.1, 0.1, 0.5, 0.4]
    assert shortlist_rows(rows, upper, 3) == [0, 5, 8]
    assert shortlist_rows(rows, upper, 20) == rows


# -- the map step with the real ResMem ------------------------------------------------------------
def _kept(res: Any) -> dict[str, list[int]]:
    return {t: s.kept_indices.tolist() for t, s in res.selections.items()}


def test_staged_map_equals_full_scoring_with_resmem(tmp_path: Path) -> None:
    scored = tmp_path / "all.mcap"
    score(DEMO, scored, ScoreConfig(all_scores=True))
    for sel in (SelectionConfig(keep_fraction=0.5), SelectionConfig(keep_fraction=0.25, dedup=0.05)):
        full = make_map(DEMO, tmp_path / "full.mcap", MapConfig(select=sel, topics=(COMP,), descriptor=None),
                        scores=scored)
        staged = make_map(DEMO, tmp_path / "staged.mcap", MapConfig(select=sel, topics=(COMP,), descriptor=None,
                                                                    candidates="all"))
        assert _kept(staged) == _kept(full)
        assert staged.crops_run is not None and staged.crops_full is not None
        assert staged.crops_run < staged.crops_full  # ResMem skipped where it could not change the map
        recs = {r["frame_index"]: r for r in read_scores(tmp_path / "staged.mcap")[COMP]}
        all_recs = {r["frame_index"]: r for r in read_scores(scored)[COMP]}
        for i in staged.selections[COMP].kept_indices:  # kept frames carry their exact MS
            assert recs[int(i)]["ms_exact"] and recs[int(i)]["ms"] == pytest.approx(all_recs[int(i)]["ms"], abs=2e-6)


# -- shared logs, stand-in ResMem -----------------------------------------------------------------
@pytest.fixture()
def stand_in(monkeypatch: pytest.MonkeyPatch) -> None:
    from tests.stand_in import use_stand_in

    use_stand_in(monkeypatch)


@pytest.mark.parametrize("name,stride", [("euroc_micro_ros2_db3", 3), ("nordland_dev_summer.mcap", 20)])
def test_staged_map_equals_full_scoring_on_shared_logs(name: str, stride: int, tmp_path: Path,
                                                        stand_in: None) -> None:
    log = shared(name)
    configs = [SelectionConfig(keep_fraction=0.25), SelectionConfig(keep_fraction=0.5, dedup=0.02),
               SelectionConfig(spacing_s=0.6 if "euroc" in name else 2.0)]
    for i, sel in enumerate(configs):
        full = make_map(log, tmp_path / f"full{i}.mcap", MapConfig(score=ScoreConfig(all_scores=True), select=sel, candidates="all",
                                                                   descriptor=None, stride=stride))
        staged = make_map(log, tmp_path / f"staged{i}.mcap", MapConfig(select=sel, descriptor=None, stride=stride,
                                                                       candidates="all"))
        assert _kept(staged) == _kept(full), sel
        assert staged.crops_run is not None and staged.crops_full is not None and full.crops_run is not None
        assert staged.crops_run <= full.crops_run


def test_staged_table_is_what_full_scoring_selects_from() -> None:
    """Unscored frames enter selection with their lower bound and never win their segment."""
    t = ScoreTable(index=np.arange(4), t_ns=np.arange(4), ms=np.array([0.7, 0.0, 0.0, 0.6]),
                   ss=np.ones(4), es=np.array([0.3, 0.1, 0.1, 0.3]))
    sel = select_segments(t, SegmentConfig(keep_fraction=0.5, by="count"))
    assert sel.kept_indices.tolist() == [0, 3]


@pytest.mark.parametrize("k", [1, 2])
def test_shortlist_map_keeps_the_best_candidate_of_each_segment(k: int, tmp_path: Path, stand_in: None) -> None:
    """``--candidates K``: each segment is cut into K consecutive parts, the frame with the best
    cheap bound (SS^2 ES: MS <= SS) of each part is a candidate, and the kept frame is the best
    candidate by the scores full scoring computes."""
    from memlog.io import FrameWindow

    log = shared("nordland_dev_summer.mcap")
    sel = SelectionConfig(keep_fraction=0.25)
    from tests.stand_in import stand_in_scorer

    cfg = ScoreConfig(all_scores=True)
    score(log, tmp_path / "all.mcap", cfg, FrameWindow(stride=20), scorer=stand_in_scorer(cfg))
    (topic, recs), = read_scores(tmp_path / "all.mcap").items()
    every = {r["frame_index"]: r for r in recs}
    short = make_map(log, tmp_path / "short.mcap", MapConfig(select=sel, descriptor=None, stride=20, candidates=k))
    s = short.selections[topic]
    assert s.segment_id is not None and sorted(every) == s.index.tolist()

    def full_value(i: int) -> float:
        e = every[i]
        return float(geometric_score(np.array([e["ms"]]), np.array([e["ss"]]), np.array([e["es"]]))[0])

    n_segments = 0
    for sid in np.unique(s.segment_id):
        members = s.index[s.segment_id == sid].tolist()
        cands = []
        for part in np.array_split(np.array(members), min(k, len(members))):
            cands.append(max(part.tolist(), key=lambda i: (every[i]["ss"] ** 2 * every[i]["es"], -i)))
        expect = max(cands, key=lambda i: (full_value(i), -i))
        kept = [i for i in members if s.keep[s.index.tolist().index(i)]]
        assert kept == [expect], (sid, members, cands)
        n_segments += 1
    assert n_segments > 5 and short.crops_run is not None and short.crops_run <= k * 25 * n_segments
    recs_map = {r["frame_index"]: r for r in read_scores(tmp_path / "short.mcap")[topic]}
    for i in s.kept_indices.tolist():  # kept frames carry full scoring's MS
        assert recs_map[i]["ms_exact"] and recs_map[i]["ms"] == pytest.approx(every[i]["ms"], abs=2e-6)
    # a shortlist as long as every segment is the exact selection
    wide = make_map(log, tmp_path / "wide.mcap", MapConfig(select=sel, descriptor=None, stride=20, candidates=1000))
    exact = make_map(log, tmp_path / "exact.mcap", MapConfig(select=sel, descriptor=None, stride=20, candidates="all"))
    assert _kept(wide) == _kept(exact)

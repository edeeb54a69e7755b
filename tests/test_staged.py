"""Staged segment selection: ResMem only where it can change the map, and the same map as scoring
every frame with every score.

* :func:`choose_in_segment` against brute force on random segments, with a crop loop that bounds
  MS the way ResMem's does (ties, minimum MS, normalised MS);
* ``memlog map`` staged vs every score on the demo fixture with the real ResMem; the staged
  selection (``--candidates all``, and the default ``--candidates 1``) against an independent
  scoring of every frame (:class:`~memlog.scoring.scorer.Scorer`, no map code);
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
from memlog.selection.segment import SEGMENT_DEFAULTS, geometric_score, segment_ids, select_segments, SegmentConfig
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


def test_one_candidate_without_an_ms_minimum_needs_no_resmem() -> None:
    """``--candidates 1``: the segment's one candidate (best SS^2 ES of the segment) is kept without
    ResMem; with an MS minimum it is scored (the minimum may drop it); the selection from records
    where its MS is unknown keeps the same frames as the selection from every MS."""
    ss = np.array([0.9, 1.0, 0.8, 0.95])
    es = np.array([0.5, 0.6, 0.7, 0.4])
    scored: list[int] = []

    def scorer(row: int, threshold: float | None, known: np.ndarray | None) -> MSResult:
        scored.append(row)
        return _crop_loop(np.full(25, 0.3), np.full(25, ss[row] / 25), threshold, known)

    winner, states = choose_in_segment([0, 1, 2, 3], ss, es, scorer, shortlist=1, score_alone=False)
    assert winner == 1 and scored == [] and not states[1].scored and not states[1].exact
    winner, _ = choose_in_segment([0, 1, 2, 3], ss, es, scorer, shortlist=1, score_alone=False, min_ms=0.5)
    assert winner is None and scored == [1]  # scored: the minimum decides (0.3 < 0.5: a gap)
    # selection from records: unknown MS of the one candidate, against MS known everywhere
    rng = np.random.default_rng(2)
    n = 40
    known = ScoreTable(index=np.arange(n), t_ns=np.arange(n) * 10**8, ms=rng.uniform(0.4, 0.9, n),
                       ss=rng.uniform(0.3, 1.0, n), es=rng.uniform(0.2, 0.8, n))
    cfg = SegmentConfig(keep_fraction=0.2, by="time", shortlist=1)
    want = select_segments(known, cfg)
    cand = want.kept_indices
    unknown_ms = known.ms.copy()
    unknown_ms[np.setdiff1d(np.arange(n), cand)] = 0.5  # other frames: anything
    unknown_ms[cand] = np.nan  # the candidates: not scored
    got = select_segments(ScoreTable(index=known.index, t_ns=known.t_ns, ms=unknown_ms, ss=known.ss, es=known.es), cfg)
    assert got.kept_indices.tolist() == cand.tolist() and len(cand) == 8
    # an MS minimum needs the MS: unknown fails it
    strict = SegmentConfig(keep_fraction=0.2, by="time", shortlist=1, min_ms=0.1)
    assert select_segments(ScoreTable(index=known.index, t_ns=known.t_ns, ms=unknown_ms, ss=known.ss,
                                      es=known.es), strict).kept_indices.size == 0


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


def test_shortlist_prefers_the_middle_of_each_part_within_the_tolerance() -> None:
    # one segment (bin 3) of 10 rows evenly spread over [3, 4); scores within 5 % of each other
    # except row 8, which is 20 % better
    rows = list(range(10))
    coord = [3.0 + (i + 0.5) / 10 for i in rows]
    upper = [0.50, 0.49, 0.48, 0.485, 0.49, 0.492, 0.47, 0.49, 0.60, 0.48]
    # tolerance 0: the best bound; 0.03 of the best (0.60): only row 8 is near enough
    assert shortlist_rows(rows, upper, 1, coord, 0.0) == [8]
    assert shortlist_rows(rows, upper, 1, coord, 0.03) == [8]
    # without row 8's lead, every row within 3 % of 0.50 counts and the middle (3.5) decides:
    # rows 4 and 5 are equally near (3.45, 3.55), the higher bound (row 5) wins
    flat = upper[:8] + [0.49, 0.48]
    assert shortlist_rows(rows, flat, 1, coord, 0.03) == [5]
    # two parts (rows 0-4 and 5-9): their middles are 3.25 and 3.75 (rows 2 and 7), but row 2 is
    # 4 % below its part's best: rows 1 (3.15) and 3 (3.35) are equally near, the higher bound wins
    assert shortlist_rows(rows, flat, 2, coord, 0.03) == [1, 7]
    # brute force over random segments: the chosen row is within the tolerance, and no row within
    # it lies nearer the part's middle
    rng = np.random.default_rng(4)
    for _ in range(200):
        m, k, tol = int(rng.integers(2, 30)), int(rng.integers(1, 4)), float(rng.choice([0.01, 0.05, 0.2]))
        c = np.sort(rng.uniform(7.0, 8.0, m)).tolist()
        u = rng.uniform(0.2, 0.6, m).tolist()
        got = shortlist_rows(list(range(m)), u, k, c, tol)
        if k >= m:
            assert got == list(range(m))
            continue
        for j, part in enumerate(np.array_split(np.arange(m), k)):
            ok = [i for i in part.tolist() if u[i] >= (1 - tol) * max(u[i] for i in part.tolist())]
            mid = 7.0 + (j + 0.5) / k
            (pick,) = [g for g in got if g in part.tolist()]
            assert pick in ok
            assert abs(c[pick] - mid) == min(abs(c[i] - mid) for i in ok)


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


class _Independent:
    """Scores of demo's frames computed here, frame by frame, with the scorer alone (every score,
    no early exit; no map, staged or selection code): the expectation the map step is checked
    against. SS/ES of every frame at once (cheap); MS (ResMem) only for the frames asked for."""

    def __init__(self) -> None:
        from memlog.io.open import open_log
        from memlog.io.positions import read_track
        from memlog.scoring.scorer import Scorer

        self.scorer = Scorer(ScoreConfig(all_scores=True))
        self.frames: dict[str, list[tuple[int, int]]] = {}  # topic -> (frame index, log time)
        self.cheap: dict[tuple[str, int], Any] = {}
        self._ms: dict[tuple[str, int], tuple[float, int]] = {}
        with open_log(DEMO) as log:
            self.track = read_track(log)
            for f in log.frames():
                self.frames.setdefault(f.topic, []).append((f.index, f.log_time_ns))
                self.cheap[(f.topic, f.index)] = self.scorer.cheap(f.decode_bgr(), keep_maps=False)

    def ss_es(self, topic: str) -> tuple[np.ndarray, np.ndarray]:
        """SS and ES of every frame of ``topic``, as score records store them (6 decimals)."""
        c = [self.cheap[(topic, i)] for i, _ in self.frames[topic]]
        return np.array([round(x.ss, 6) for x in c]), np.array([round(float(x.es), 6) for x in c])

    def ms(self, topic: str, index: int) -> float:
        """ResMem's MS of one frame (every crop), as score records store it."""
        return round(self._full(topic, index)[0], 6)

    def crops(self, topic: str, index: int) -> int:
        """The crops ResMem scores for that frame's exact MS."""
        return self._full(topic, index)[1]

    def _full(self, topic: str, index: int) -> tuple[float, int]:
        key = (topic, index)
        if key not in self._ms:
            r = self.scorer.finish(self.cheap[key])
            assert r.ms_exact and r.ms is not None
            self._ms[key] = (float(r.ms), r.crops_scored)
        return self._ms[key]

    def table(self, topic: str, with_ms: bool = True) -> ScoreTable:
        """The ScoreTable full scoring selects from: every frame, every score, the log's positions."""
        ss, es = self.ss_es(topic)
        idx = np.array([i for i, _ in self.frames[topic]], dtype=np.int64)
        t = np.array([ts for _, ts in self.frames[topic]], dtype=np.int64)
        ms = np.array([self.ms(topic, int(i)) for i in idx]) if with_ms else np.zeros(len(idx))
        pos = self.track.at(t.tolist()) if self.track is not None else None
        return ScoreTable(index=idx, t_ns=t, ms=ms, ss=ss, es=es, positions=pos, topic=topic)


@pytest.fixture(scope="module")
def independent() -> _Independent:
    return _Independent()


# demo's drive: the camera frames lie at 0, 5, 10, 15, 15, 15, 20, 25 m (a stop at 15 m), so a quarter of
# 8 frames is 2 segments of 12.5 m each: frames 0-2 and 3-7
DEMO_SEGMENTS = [0, 0, 0, 1, 1, 1, 1, 1]


# On demo the frame with the best cheap bound of a segment is also its best frame by default, so
# two settings make the staged choice go further: a minimum MS that frame 6 (MS 0.857, the best
# bound of frames 3-7) misses and frame 5 (0.896) passes, and MS weighted so that frame 5 wins;
# the staged map must then score past the first candidate (and stop the crop loop of others early).
STAGED_SETTINGS = {"default": {}, "min_ms": {"min_ms": 0.86}, "ms_weight": {"weights": (10.0, 1.0, 1.0)}}


@pytest.mark.parametrize("setting", sorted(STAGED_SETTINGS))
def test_staged_table_is_what_full_scoring_selects_from(setting: str, tmp_path: Path, independent: _Independent,
                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    """The staged map (``--candidates all``) keeps the frames that scoring every frame with every
    score and selecting by segment keeps; the table it selected from (unscored frames with their
    lower bound) bounds every frame's true MS and gives that selection."""
    import memlog.steps.map as map_step

    seen: dict[str, tuple[list[dict[str, Any]], ScoreTable]] = {}
    real_table = map_step.score_table

    def spy(records: list[dict[str, Any]], topic: str, *args: Any, **kw: Any) -> ScoreTable:
        table = real_table(records, topic, *args, **kw)
        seen[topic] = (list(records), table)
        return table

    monkeypatch.setattr(map_step, "score_table", spy)
    sel = SelectionConfig(keep_fraction=0.25, **STAGED_SETTINGS[setting])
    staged = make_map(DEMO, tmp_path / "staged.mcap",
                      MapConfig(select=sel, topics=(COMP,), descriptor=None, candidates="all"))
    assert staged.crops_run is not None and staged.crops_full is not None
    assert staged.crops_run < staged.crops_full  # ResMem skipped where it could not change the map

    full = independent.table(COMP)
    want = select_segments(full, SegmentConfig(**sel.segment_settings()))
    assert want.segment_id is not None and want.segment_id.tolist() == DEMO_SEGMENTS
    assert want.kept_indices.tolist() == {"default": [2, 6], "min_ms": [5], "ms_weight": [2, 5]}[setting]
    assert _kept(staged) == {COMP: want.kept_indices.tolist()}
    assert staged.selections[COMP].segment_id.tolist() == DEMO_SEGMENTS

    records, table = seen[COMP]
    assert table.index.tolist() == full.index.tolist()
    assert table.ss == pytest.approx(full.ss, abs=1e-6) and table.es == pytest.approx(full.es, abs=1e-6)
    unscored = 0
    for r, true_ms, ms_in_table in zip(records, full.ms, table.ms):
        if r["ms_exact"]:
            assert r["ms"] == pytest.approx(true_ms, abs=2e-6) and ms_in_table == r["ms"]
        else:  # MS not computed: bounds that hold the true MS, the lower one in the table
            assert r["ms"] is None and ms_in_table == r["ms_low"]
            assert r["ms_low"] - 1e-6 <= true_ms <= r["ms_high"] + 1e-6
            unscored += r["ss"] >= sel.min_ss
    assert unscored > 0  # frames that could have been kept entered selection with a bound only (the staged path)
    again = select_segments(table, SegmentConfig(**sel.segment_settings()))
    assert again.kept_indices.tolist() == want.kept_indices.tolist()


def test_default_map_keeps_the_best_cheap_bound_of_each_segment(tmp_path: Path, independent: _Independent) -> None:
    """``memlog map`` with its defaults (``--candidates 1``) on a fixture: per place segment, the
    kept frame is the frame with the largest SS^2 ES (the bound of the geometric score, MS <= SS)
    among the frames passing the minimum scores. ResMem does not run (its MS would choose nothing):
    the record holds MS's bounds. With ``score_kept`` the same frames carry ResMem's exact MS, and
    ResMem ran on those frames only."""
    # the size is fixed here (a quarter: DEMO_SEGMENTS) so the segments can be cut from the scores alone;
    # the default size by view change is tested in tests/test_drive_selection.py
    sel = SelectionConfig(keep_fraction=0.25)
    assert MapConfig().candidates == 1 and not MapConfig().score_kept  # the defaults this test is about
    default = make_map(DEMO, tmp_path / "default.mcap", MapConfig(select=sel))
    assert default.crops_run == 0
    res = make_map(DEMO, tmp_path / "map.mcap", MapConfig(select=sel, score_kept=True))
    assert {t: s.kept_indices.tolist() for t, s in default.selections.items()} == {
        t: s.kept_indices.tolist() for t, s in res.selections.items()}
    unscored = read_scores(tmp_path / "default.mcap")
    recs = read_scores(tmp_path / "map.mcap")
    assert sorted(res.selections) == sorted(independent.frames) == [COMP, "/camera/image_raw"]
    crops = 0
    for topic in sorted(independent.frames):
        ss, es = independent.ss_es(topic)
        cheap_table = independent.table(topic, with_ms=False)
        seg, _ = segment_ids(cheap_table, SegmentConfig(**sel.segment_settings()))
        assert seg.tolist() == DEMO_SEGMENTS
        index = cheap_table.index.tolist()
        passing = (ss >= sel.min_ss) & (es >= sel.min_es)
        want = []
        for sid in np.unique(seg):
            rows = [int(r) for r in np.flatnonzero(seg == sid) if passing[r]]
            if not rows:
                continue  # a gap
            best = index[max(rows, key=lambda r: (ss[r] ** 2 * es[r], -r))]
            if independent.ms(topic, best) >= sel.min_ms:  # (the one candidate must still pass min_ms)
                want.append(best)
        s = res.selections[topic]
        assert s.index.tolist() == index and s.kept_indices.tolist() == want, topic
        assert s.segment_id is not None and s.segment_id.tolist() == DEMO_SEGMENTS
        by_index = {r["frame_index"]: r for r in recs[topic]}
        assert sorted(by_index) == want  # the map holds the kept frames, each with its scores
        for i in want:
            u = {r["frame_index"]: r for r in unscored[topic]}[i]
            assert u["ms"] is None and not u["ms_exact"] and u["ms_low"] <= independent.ms(topic, i) <= u["ms_high"] + 1e-6
            assert (u["ss"], u["es"]) == (by_index[i]["ss"], by_index[i]["es"])
            r = by_index[i]
            assert r["ms_exact"] and r["ms"] == pytest.approx(independent.ms(topic, i), abs=2e-6), (topic, i)
            assert r["ss"] == pytest.approx(ss[index.index(i)], abs=1e-6)
            assert r["es"] == pytest.approx(es[index.index(i)], abs=1e-6)
            crops += independent.crops(topic, i)
    assert res.crops_run == crops  # ResMem on the one candidate of each segment, nothing else


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


@pytest.mark.parametrize("k,centre", [(1, False), (2, False), (1, True), (2, True)])
def test_shortlist_map_keeps_the_best_candidate_of_each_segment(k: int, centre: bool, tmp_path: Path,
                                                                 stand_in: None) -> None:
    """``--candidates K``: each segment is cut into K consecutive parts, the frame with the best
    cheap bound (SS^2 ES: MS <= SS) of each part is a candidate (with the centre rule: the frame
    nearest the middle of the part's share of the segment among those within the tolerance of the
    part's best bound; segments by frame count, so a row's place is known without memlog's code),
    and the kept frame is the best candidate by the scores full scoring computes."""
    from memlog.io import FrameWindow

    log = shared("nordland_dev_summer.mcap")
    tol = SEGMENT_DEFAULTS.centre_tolerance
    sel = (SelectionConfig(keep_fraction=0.25, segment_by="count") if centre
           else SelectionConfig(keep_fraction=0.25, centre_tolerance=0.0))
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
    rows = s.index.tolist()
    n, n_seg = len(rows), int(np.unique(s.segment_id).size)

    def bound(i: int) -> float:
        return float(every[i]["ss"] ** 2 * every[i]["es"])

    for sid in np.unique(s.segment_id):
        members = s.index[s.segment_id == sid].tolist()
        cands = []
        for j, part in enumerate(np.array_split(np.array(members), min(k, len(members)))):
            best = max(part.tolist(), key=lambda i: (bound(i), -i))
            if centre and len(members) > k:
                # count segments: row r covers [r, r + 1) of n rows cut into n_seg equal segments
                mid = sid + (j + 0.5) / k
                near = [i for i in part.tolist() if bound(i) ** (1 / 3) >= (1 - tol) * bound(best) ** (1 / 3)]
                best = min(near, key=lambda i: (abs((rows.index(i) + 0.5) * n_seg / n - mid), -bound(i), i))
            cands.append(best)
        expect = max(cands, key=lambda i: (full_value(i), -i))
        kept = [i for i in members if s.keep[s.index.tolist().index(i)]]
        assert kept == [expect], (sid, members, cands)
        n_segments += 1
    assert n_segments > 5 and short.crops_run is not None and short.crops_run <= k * 25 * n_segments
    recs_map = {r["frame_index"]: r for r in read_scores(tmp_path / "short.mcap")[topic]}
    if k == 1:  # MS chooses nothing: ResMem did not run, the kept frames' MS is unknown (within its bounds)
        assert short.crops_run == 0
        for i in s.kept_indices.tolist():
            r = recs_map[i]
            assert r["ms"] is None and not r["ms_exact"] and r["ms_low"] <= every[i]["ms"] <= r["ms_high"] + 1e-6
        kept = make_map(log, tmp_path / "kept.mcap", MapConfig(select=sel, descriptor=None, stride=20, candidates=k,
                                                               score_kept=True))
        assert _kept(kept) == _kept(short)  # --score-kept records MS, it chooses nothing
        recs_map = {r["frame_index"]: r for r in read_scores(tmp_path / "kept.mcap")[topic]}
    for i in s.kept_indices.tolist():  # kept frames carry full scoring's MS
        assert recs_map[i]["ms_exact"] and recs_map[i]["ms"] == pytest.approx(every[i]["ms"], abs=2e-6)
    # a shortlist as long as every segment is the exact selection
    wide = make_map(log, tmp_path / "wide.mcap", MapConfig(select=sel, descriptor=None, stride=20, candidates=1000))
    exact = make_map(log, tmp_path / "exact.mcap", MapConfig(select=sel, descriptor=None, stride=20, candidates="all"))
    assert _kept(wide) == _kept(exact)

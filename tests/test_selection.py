"""Tests of memlog.selection against independent, straightforward expectations."""

from __future__ import annotations

import json
import math
from typing import Any

import numpy as np
import pytest
from numpy.typing import NDArray

from memlog.errors import ConfigError, EvaluationError, MemlogError, SelectionError
from memlog.selection.coordinates import count_cut
from memlog.selection import (
    SELECTORS,
    CalibrateConfig,
    PaperConfig,
    RedundancyConfig,
    ScoreTable,
    SegmentConfig,
    Selection,
    baseline_selection,
    calibrate,
    drop_duplicates,
    find_duplicates,
    random_indices,
    random_mask,
    random_masks,
    select,
    select_calibrated,
    select_paper,
    select_segments,
    phase_masks,
    uniform_indices,
    uniform_mask,
)

F64 = NDArray[np.float64]


def make_table(
    ms: Any,
    ss: Any,
    es: Any,
    *,
    t_ns: Any = None,
    index: Any = None,
    positions: Any = None,
    descriptors: Any = None,
) -> ScoreTable:
    n = len(ms)
    return ScoreTable(
        index=np.arange(n) if index is None else index,
        t_ns=np.arange(n, dtype=np.int64) * 100_000_000 if t_ns is None else t_ns,
        ms=ms,
        ss=ss,
        es=es,
        positions=positions,
        descriptors=descriptors,
    )


def random_table(n: int, seed: int = 0, nan_frac: float = 0.0, **kw: Any) -> ScoreTable:
    rng = np.random.default_rng(seed)
    ms, ss, es = rng.random(n), rng.random(n), rng.random(n)
    for col in (ms, ss, es):
        col[rng.random(n) < nan_frac] = np.nan
    return make_table(ms, ss, es, **kw)


def correlated_scores(n: int, seed: int) -> tuple[F64, F64, F64]:
    rng = np.random.default_rng(seed)
    z = rng.normal(size=n)
    ms = 1 / (1 + np.exp(-(z + 0.5 * rng.normal(size=n))))
    ss = np.clip(0.7 + 0.2 * z + 0.1 * rng.normal(size=n), 0, 1)
    es = 0.3 + 0.05 * (z + 0.7 * rng.normal(size=n))
    return ms, ss, es


def unit_rows(x: F64) -> NDArray[np.float32]:
    return (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32)


def mid_ranks(x: F64) -> F64:
    """Percentile mid-ranks by brute force (O(n^2)), NaN for NaN."""
    ok = np.isfinite(x)
    v = x[ok]
    out = np.full(len(x), np.nan)
    for i in np.flatnonzero(ok):
        out[i] = (np.sum(v < x[i]) + 0.5 * np.sum(v == x[i])) / len(v)
    return out


# ---------------------------------------------------------------- ScoreTable / Selection


def test_score_table_validates_lengths_and_shapes() -> None:
    with pytest.raises(SelectionError, match="length"):
        make_table([0.1, 0.2], [0.1], [0.3, 0.4])
    with pytest.raises(SelectionError, match="positions"):
        make_table([0.1, 0.2], [0.1, 0.2], [0.3, 0.4], positions=np.zeros((2, 4)))
    with pytest.raises(SelectionError, match="descriptors"):
        make_table([0.1, 0.2], [0.1, 0.2], [0.3, 0.4], descriptors=np.ones((3, 4)))
    with pytest.raises(SelectionError, match="L2-normalised"):
        make_table([0.1, 0.2], [0.1, 0.2], [0.3, 0.4], descriptors=np.ones((2, 4)))
    with pytest.raises(SelectionError, match="strictly increasing"):
        make_table([0.1, 0.2], [0.1, 0.2], [0.3, 0.4], index=[3, 3])
    with pytest.raises(SelectionError, match="non-decreasing"):
        make_table([0.1, 0.2], [0.1, 0.2], [0.3, 0.4], t_ns=[5, 4])
    with pytest.raises(SelectionError, match="integers"):
        make_table([0.1, 0.2], [0.1, 0.2], [0.3, 0.4], index=[0.0, 1.0])
    assert issubclass(SelectionError, MemlogError)
    # NaN rows of descriptors/positions are allowed (unknown)
    d = unit_rows(np.ones((2, 4)))
    d[1] = np.nan
    p = np.array([[0.0, 0.0], [np.nan, np.nan]])
    t = make_table([0.1, 0.2], [0.1, 0.2], [0.3, 0.4], descriptors=d, positions=p)
    assert t.known_descriptors().tolist() == [True, False]
    assert t.known_positions().tolist() == [True, False]
    assert t.descriptors is not None and t.descriptors.dtype == np.float32
    assert len(make_table([], [], [])) == 0


def test_selection_to_dict_is_json_and_uses_frame_indices() -> None:
    t = random_table(30, seed=3, index=np.arange(100, 130))
    sel = select(t, "paper", mt=0.3, st=0.3, et=0.3)
    d = json.loads(json.dumps(sel.to_dict()))
    assert d["kept_indices"] == (np.arange(100, 130)[sel.keep]).tolist()
    assert d["n_kept"] == sel.n_kept == len(sel.kept_indices)
    assert math.isclose(d["fraction"], sel.n_kept / 30)
    assert sum(d["reason_counts"].values()) == 30 - sel.n_kept
    assert all(i >= 100 for i, _ in d["dropped"])
    with pytest.raises(SelectionError):
        Selection(mode="x", index=np.arange(2), keep=np.array([True, False]), reason=[None, None])


# ---------------------------------------------------------------- paper rule


def test_paper_rule_matches_per_frame_loop_with_nans() -> None:
    t = random_table(500, seed=1, nan_frac=0.1)
    mt, st, et = 0.5, 0.6, 0.4
    sel = select_paper(t, PaperConfig(mt, st, et))
    for i in range(t.n):
        ms, ss, es = t.ms[i], t.ss[i], t.es[i]
        # NaN >= x is False in Python, so NaN fails naturally
        if not ss >= st:
            want: str | None = "staticity"
        elif not es >= et:
            want = "entropy"
        elif not ms >= mt:
            want = "memorability"
        else:
            want = None
        assert sel.reason[i] == want, i
        assert bool(sel.keep[i]) == (want is None)
    assert sel.thresholds == {"mt": 0.5, "st": 0.6, "et": 0.4}
    assert 0 < sel.n_kept < t.n


def test_paper_reason_order_and_boundaries() -> None:
    t = make_table(
        ms=[0.0, 0.0, 0.0, 0.5, np.nan, 0.9],
        ss=[0.0, 1.0, 1.0, 0.6, 1.0, 1.0],
        es=[0.0, 0.0, 0.9, 0.4, 0.9, np.nan],
    )
    sel = select_paper(t)
    assert sel.reason == ["staticity", "entropy", "memorability", None, "memorability", "entropy"]
    assert sel.kept_indices.tolist() == [3]  # exactly at all three thresholds: kept (>=)


def test_select_paper_defaults_overrides_and_errors() -> None:
    t = random_table(100, seed=2)
    a = select(t, "paper")
    assert a.thresholds == {"mt": 0.5, "st": 0.6, "et": 0.4}
    b = select(t, "paper", et=0.0)
    assert b.n_kept >= a.n_kept
    assert SELECTORS["paper"] == {"mt": 0.5, "st": 0.6, "et": 0.4}  # not mutated
    with pytest.raises(ConfigError, match="unknown setting"):
        select(t, "paper", foo=1)
    with pytest.raises(ConfigError, match="unknown selector"):
        select(t, "nope")
    with pytest.raises(ConfigError):
        PaperConfig(mt=float("nan"))
    empty = select(make_table([], [], []), "paper")
    assert empty.n_frames == 0 and empty.fraction == 0.0


# ---------------------------------------------------------------- calibration


def joint_count(t: ScoreTable, mt: float, st: float, et: float) -> int:
    with np.errstate(invalid="ignore"):
        return int(np.sum((t.ms >= mt) & (t.ss >= st) & (t.es >= et)))


@pytest.mark.parametrize("f", [0.25, 0.5, 0.75])
def test_calibrate_hits_fraction_with_common_quantile(f: float) -> None:
    n = 400
    ms, ss, es = correlated_scores(n, seed=7)
    t = make_table(ms, ss, es)
    cal = calibrate(t, f)
    # thresholds are the same quantile q of each criterion
    assert cal.mt == pytest.approx(float(np.quantile(ms, cal.q)), abs=0)
    assert cal.st == pytest.approx(float(np.quantile(ss, cal.q)), abs=0)
    assert cal.et == pytest.approx(float(np.quantile(es, cal.q)), abs=0)
    # achieved fraction recomputed independently
    c = joint_count(t, cal.mt, cal.st, cal.et)
    assert c == cal.n_kept and cal.achieved == c / n
    assert abs(cal.achieved - f) <= 1.0 / n
    assert cal.reachable
    # no q on a fine grid does better
    qs = np.linspace(0, 1, 4001)
    grid = [np.quantile(x, qs) for x in (ms, ss, es)]
    best = min(abs(joint_count(t, grid[0][i], grid[1][i], grid[2][i]) - f * n) for i in range(len(qs)))
    assert abs(c - f * n) <= best
    sel = select_calibrated(t, CalibrateConfig(keep_fraction=f))
    assert sel.n_kept == c and sel.mode == "calibrated"
    assert sel.info["calibration"]["q"] == cal.q


def test_calibrate_staticity_all_one() -> None:
    n = 300
    ms, _, es = correlated_scores(n, seed=11)
    t = make_table(ms, np.ones(n), es)
    for f in (0.1, 0.5, 1.0):
        cal = calibrate(t, f)
        assert cal.st == 1.0
        assert abs(cal.achieved - f) <= 1.0 / n
        assert np.all(select_paper(t, cal.paper_config()).reason.count("staticity") == 0)


def test_calibrate_with_nans_and_unreachable() -> None:
    n = 200
    ms, ss, es = correlated_scores(n, seed=5)
    es[::4] = np.nan  # 25 % of frames lack ES: at most 75 % can pass
    t = make_table(ms, ss, es)
    assert cal_q_matches(t, calibrate(t, 0.5))
    cal = calibrate(t, 0.9)
    assert not cal.reachable and cal.note and "unreachable" in cal.note
    assert cal.q == 0.0 and cal.achieved == pytest.approx(0.75)
    assert cal.et == float(np.nanmin(es))
    # every frame tied: nothing below 100 % is achievable
    tied = make_table(np.full(50, 0.3), np.ones(50), np.full(50, 0.2))
    cal = calibrate(tied, 0.2)
    assert not cal.reachable and cal.achieved == 1.0 and cal.note
    assert (cal.mt, cal.st, cal.et) == (0.3, 1.0, 0.2)
    # F = 1 on complete scores: q = 0, everything kept
    full = make_table(*correlated_scores(40, seed=1))
    cal = calibrate(full, 1.0)
    assert cal.q == 0.0 and cal.achieved == 1.0 and cal.reachable and cal.note is None


def cal_q_matches(t: ScoreTable, cal: Any) -> bool:
    qs = [float(np.quantile(x[np.isfinite(x)], cal.q)) for x in (t.ms, t.ss, t.es)]
    return qs == [cal.mt, cal.st, cal.et] and abs(cal.achieved - 0.5) <= 1.0 / t.n


def test_calibrate_errors() -> None:
    t = random_table(10)
    for bad in (0.0, -0.1, 1.5, float("nan")):
        with pytest.raises(ConfigError):
            calibrate(t, bad)
    with pytest.raises(SelectionError, match="empty"):
        calibrate(make_table([], [], []), 0.5)
    with pytest.raises(SelectionError, match="entropy"):
        calibrate(make_table([0.5, 0.6], [1.0, 1.0], [np.nan, np.nan]), 0.5)


# ---------------------------------------------------------------- segments


def expected_best(
    t: ScoreTable, rows: NDArray[np.int64], cfg: SegmentConfig, score: F64
) -> int | None:
    """Best passing row of a segment by ``score``, or None."""
    best, best_v = None, -np.inf
    for r in rows.tolist():
        ok = t.ms[r] >= cfg.min_ms and t.ss[r] >= cfg.min_ss and t.es[r] >= cfg.min_es
        if ok and score[r] > best_v:
            best, best_v = r, score[r]
    return best


def variable_speed_positions(n: int, seed: int) -> F64:
    rng = np.random.default_rng(seed)
    speed = np.concatenate([np.full(n // 3, 0.05), np.full(n // 3, 1.0), np.full(n - 2 * (n // 3), 0.3)])
    speed *= 1 + 0.2 * rng.random(n)
    heading = np.cumsum(0.05 * rng.normal(size=n))
    steps = np.c_[speed * np.cos(heading), speed * np.sin(heading)]
    steps[0] = 0
    return np.cumsum(steps, axis=0)


def check_one_per_bin(sel: Selection, t: ScoreTable, bins: NDArray[np.int64], cfg: SegmentConfig) -> None:
    """One kept frame per bin: the best by the weighted mean of brute-force mid-ranks (rank) or
    the weighted geometric mean of the raw scores (geometric)."""
    w = np.asarray(cfg.weights, dtype=np.float64)
    if cfg.combine == "rank":
        ranks = [mid_ranks(c) for c in (t.ms, t.ss, t.es)]
        score = sum(wi * r for wi, r in zip(w, ranks)) / w.sum()
    else:
        score = np.prod([np.power(c, wi / w.sum()) for wi, c in zip(w, (t.ms, t.ss, t.es))], axis=0)
    for b in np.unique(bins):
        rows = np.flatnonzero(bins == b)
        kept = rows[sel.keep[rows]]
        want = expected_best(t, rows, cfg, score)
        assert kept.tolist() == ([] if want is None else [want]), b


def test_segment_by_distance_variable_speed() -> None:
    n = 300
    pos = variable_speed_positions(n, seed=4)
    t = random_table(n, seed=4, positions=pos)
    cumlen = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pos, axis=0), axis=1))])
    # explicit spacing: segment k covers path length [5k, 5k + 5) m
    cfg = SegmentConfig(spacing_m=5.0)
    sel = select_segments(t, cfg)
    bins = np.floor(cumlen / 5.0).astype(np.int64)
    assert sel.info["by"] == "distance"
    assert sel.info["n_segments"] == len(np.unique(bins))
    check_one_per_bin(sel, t, bins, cfg)
    assert sel.segment_id is not None
    for s in np.unique(sel.segment_id):
        rows = np.flatnonzero(sel.segment_id == s)
        assert cumlen[rows[-1]] - cumlen[rows[0]] < 5.0
    counts = np.bincount(bins)
    assert counts.max() > 3 * counts[counts > 0].min()  # equal metres, unequal frame counts
    # keep_fraction: round(F*N) equal-length parts of the whole path
    cfg2 = SegmentConfig(keep_fraction=0.05)
    sel2 = select_segments(t, cfg2)
    s_count = 15
    bins2 = np.minimum(np.floor(cumlen / (cumlen[-1] / s_count)), s_count - 1).astype(np.int64)
    assert sel2.info["by"] == "distance" and sel2.info["n_bins"] == s_count
    assert sel2.info["spacing_m"] == pytest.approx(cumlen[-1] / s_count)
    check_one_per_bin(sel2, t, bins2, cfg2)
    # non-kept frames that pass the minimums lost to their segment's best
    for i in np.flatnonzero(~sel2.keep):
        if t.ms[i] >= 0.05 and t.ss[i] >= 0.1 and t.es[i] >= 0.05:
            assert sel2.reason[i] == "segment"


def test_keep_fraction_keeps_its_size_through_a_fast_stretch() -> None:
    """Positions 8 m apart, then a stretch at 16 m per frame (the Stromovka drive pair's map drive):
    seven tenths of the frames cut into equal parts of the path (13 m each) leaves parts of the fast
    stretch empty; the map still gets its size, every fast-stretch frame among them."""
    steps = np.r_[0.0, np.full(40, 8.0), np.full(15, 16.0), np.full(45, 8.0)]
    s = np.cumsum(steps)
    n = len(s)
    pos = np.c_[s, np.zeros(n)]
    rng = np.random.default_rng(5)
    t = make_table(*rng.uniform(0.5, 1.0, (3, n)), positions=pos)  # every frame passes the minimums
    asked = math.floor(0.7 * n + 0.5)
    assert held_parts(s, asked) < asked  # equal parts of the path: some hold no frame
    sel = select_segments(t, SegmentConfig(keep_fraction=0.7))
    assert sel.info["by"] == "distance" and sel.n_kept == sel.info["n_segments"] >= asked
    assert sel.n_kept <= asked + 2 and sel.shortfall() is None
    assert sel.keep[41:56].all()  # the fast stretch: 16 m per frame, more than a part
    m = round(s[-1] / sel.info["spacing_m"])
    assert held_parts(s, m) >= asked > held_parts(s, m - 1)  # the cut is as coarse as the size allows
    assert count_cut(s, asked) == m and count_cut(s, 10) == 10  # coarse parts all hold a frame
    # fewer distinct places than asked (a stop is one place): as many parts as places, then a shortfall
    still = np.r_[s[:20], np.full(60, s[20]), s[21:41]]
    assert count_cut(still, 60) >= 60 and held_parts(still, count_cut(still, 60)) == 41


def held_parts(value: NDArray[np.float64], m: int) -> int:
    """How many of ``m`` equal parts of the span of ``value`` hold a value."""
    return len(np.unique(np.minimum(np.floor(value / (value[-1] / m)), m - 1)))


def test_segment_by_time_irregular_timestamps() -> None:
    n = 200
    rng = np.random.default_rng(9)
    dt = rng.exponential(0.2e9, size=n).astype(np.int64)
    dt[50:53] = 20_000_000_000  # three 20 s dropouts in the log
    t_ns = 1_700_000_000_000_000_000 + np.cumsum(dt)
    t = random_table(n, seed=9, t_ns=t_ns)
    cfg = SegmentConfig(spacing_s=1.0)
    sel = select_segments(t, cfg)
    bins = ((t_ns - t_ns[0]) // 1_000_000_000).astype(np.int64)
    assert sel.info["by"] == "time"
    check_one_per_bin(sel, t, bins, cfg)
    # auto without positions uses time; keep_fraction splits the span into equal parts, and since the
    # dropout leaves 20 equal parts with empty ones, into the fewest equal parts of which 20 hold a frame
    cfg2 = SegmentConfig(keep_fraction=0.1)
    sel2 = select_segments(t, cfg2)
    span = float(t_ns[-1] - t_ns[0])

    def parts_of(m: int) -> NDArray[np.int64]:
        return np.minimum(np.floor((t_ns - t_ns[0]) / (span / m)), m - 1).astype(np.int64)

    assert len(np.unique(parts_of(20))) < 20  # the dropout leaves empty parts
    m = next(m for m in range(20, 200) if len(np.unique(parts_of(m))) >= 20)  # scanned one by one
    bins2 = parts_of(m)
    assert sel2.info["by"] == "time" and m > 20
    check_one_per_bin(sel2, t, bins2, cfg2)
    assert sel2.info["n_segments"] == len(np.unique(bins2)) >= 20 == sel2.info["n_bins"]
    assert sel2.info["spacing_s"] == pytest.approx(span / m / 1e9)
    assert sel2.shortfall() is None


def test_segment_by_count() -> None:
    n = 95
    t = random_table(n, seed=12)
    cfg = SegmentConfig(by="count", keep_fraction=0.1)
    sel = select_segments(t, cfg)
    assert sel.info["n_segments"] == 10  # floor(9.5 + 0.5)
    assert sel.segment_id is not None
    sizes = np.bincount(sel.segment_id)
    assert sizes.sum() == n and set(sizes.tolist()) <= {9, 10}
    check_one_per_bin(sel, t, sel.segment_id, cfg)
    sel2 = select(t, "segment", spacing_frames=7)  # replaces the default keep_fraction
    check_one_per_bin(sel2, t, np.arange(n) // 7, SegmentConfig(spacing_frames=7))


def test_segment_by_view_change_three_places() -> None:
    rng = np.random.default_rng(0)
    places = unit_rows(rng.normal(size=(3, 64)))
    which = np.repeat([0, 1, 2], [25, 40, 35])
    desc = unit_rows(places[which] + 0.05 * rng.normal(size=(100, 64)))
    t = random_table(100, seed=1, descriptors=desc)
    sel = select(t, "segment", by="view", view_distance=0.5)
    assert sel.info["by"] == "view" and sel.info["n_segments"] == 3
    assert sel.segment_id is not None
    assert sel.segment_id.tolist() == which.tolist()
    check_one_per_bin(sel, t, which, SegmentConfig(by="view", view_distance=0.5))
    with pytest.raises(ConfigError, match="descriptors"):
        select(random_table(10), "segment", by="view", view_distance=0.5)
    with pytest.raises(ConfigError, match="view vectors"):
        select(random_table(10), "segment", by="view")


def test_segment_gap_reporting() -> None:
    n = 50
    t_ns = np.arange(n, dtype=np.int64) * 1_000_000_000
    ms, ss, es = np.full(n, 0.6), np.full(n, 0.9), np.full(n, 0.5)
    ms[::3] += 0.1
    ss[20:30] = 0.0  # segment 2 fully dynamic
    es[25:30] = 0.0
    t = make_table(ms, ss, es, t_ns=t_ns, index=np.arange(1000, 1000 + n))
    sel = select(t, "segment", spacing_frames=10)
    assert sel.n_kept == 4
    assert len(sel.gaps) == 1
    g = sel.gaps[0]
    assert (g.segment, g.start_index, g.end_index, g.n_frames) == (2, 1020, 1029, 10)
    assert (g.start_t_ns, g.end_t_ns) == (20_000_000_000, 29_000_000_000)
    assert g.reason == "staticity" and g.counts == {"staticity": 10}
    assert all(sel.reason[i] == "staticity" for i in range(20, 30))
    d = json.loads(json.dumps(sel.to_dict()))
    assert d["gaps"][0]["start_index"] == 1020


def test_segment_edge_cases() -> None:
    empty = select(make_table([], [], []), "segment")
    assert empty.n_frames == 0 and empty.n_kept == 0 and empty.gaps == []
    one = select(make_table([0.5], [0.9], [0.3]), "segment")
    assert one.keep.tolist() == [True]
    one_bad = select(make_table([0.5], [0.0], [0.3]), "segment")
    assert one_bad.keep.tolist() == [False] and len(one_bad.gaps) == 1
    t = random_table(40, seed=8)
    allf = select(t, "segment", by="count", keep_fraction=1.0)
    d = SELECTORS["segment"]
    passing = (t.ms >= d["min_ms"]) & (t.ss >= d["min_ss"]) & (t.es >= d["min_es"])
    assert allf.keep.tolist() == passing.tolist()
    assert len(allf.gaps) == int(np.sum(~passing))


def test_segment_stopping_robot_no_division_by_zero() -> None:
    n = 60
    pos = np.zeros((n, 3))
    pos[40:, 0] = np.arange(1, 21)  # stands still for 40 frames, then drives 20 m
    pos[10] = np.nan  # one unknown position
    t = random_table(n, seed=3, positions=pos)
    with np.errstate(all="raise"):
        sel = select(t, "segment", keep_fraction=0.2)
        assert sel.info["by"] == "distance"
        # the 40 stopped frames all lie at 0 m: one segment; 20 m in 12 bins of 5/3 m
        assert sel.segment_id is not None
        assert len(set(sel.segment_id[:40].tolist())) == 1
        still = random_table(n, seed=3, positions=np.ones((n, 2)), t_ns=np.zeros(n, dtype=np.int64))
        sel2 = select(still, "segment", keep_fraction=0.2)
        assert sel2.info["by"] == "count" and sel2.info["n_segments"] == 12
        sel3 = select(still, "segment", by="distance", keep_fraction=0.2)
        assert sel3.info["n_segments"] == 1 and sel3.n_kept == 1
        sel4 = select(still, "segment", by="time", keep_fraction=0.2)
        assert sel4.info["n_segments"] == 1


def test_combined_score_is_scale_free_and_weighted() -> None:
    n = 120
    t = random_table(n, seed=21)
    low_es = make_table(t.ms, t.ss, 0.3 + 0.05 * t.es)  # same order, tiny-resolution ES range
    a = select(t, "segment", spacing_frames=10, min_es=0.0, combine="rank")
    b = select(low_es, "segment", spacing_frames=10, min_es=0.0, combine="rank")
    assert a.keep.tolist() == b.keep.tolist()  # ranks: any increasing transform
    scaled = make_table(t.ms, t.ss, 0.3 * t.es)
    c = select(t, "segment", spacing_frames=10, min_es=0.0, combine="geometric")
    e = select(scaled, "segment", spacing_frames=10, min_es=0.0, combine="geometric")
    assert c.keep.tolist() == e.keep.tolist()  # geometric mean: rescaling one criterion
    es_only = select(t, "segment", spacing_frames=10, weights=(0, 0, 1), min_ms=0, min_ss=0, min_es=0)
    want = [10 * k + int(np.argmax(t.es[10 * k : 10 * k + 10])) for k in range(12)]
    assert es_only.kept_rows.tolist() == want
    geo = select(t, "segment", spacing_frames=10, combine="geometric", min_ms=0, min_ss=0, min_es=0)
    g = (t.ms * t.ss * t.es) ** (1 / 3)
    assert geo.kept_rows.tolist() == [10 * k + int(np.argmax(g[10 * k : 10 * k + 10])) for k in range(12)]


def test_segment_config_errors() -> None:
    with pytest.raises(ConfigError, match="exactly one"):
        SegmentConfig(keep_fraction=0.1, spacing_m=3.0)
    with pytest.raises(ConfigError, match="exactly one"):
        SegmentConfig()
    with pytest.raises(ConfigError):
        SegmentConfig(by="time", spacing_m=3.0)
    with pytest.raises(ConfigError):
        SegmentConfig(spacing_m=0.0)
    with pytest.raises(ConfigError):
        SegmentConfig(keep_fraction=0.1, weights=(0.0, 0.0, 0.0))
    with pytest.raises(ConfigError):
        SegmentConfig(keep_fraction=0.1, combine="max")  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="positions"):
        select(random_table(10), "segment", by="distance")


# ---------------------------------------------------------------- redundancy


def brute_force_dedup(
    desc: NDArray[np.float32] | None,
    pos: F64 | None,
    keep: NDArray[np.bool_],
    dd: float | None,
    rr: float | None,
) -> tuple[list[bool], list[int]]:
    kept: list[int] = []
    out = keep.copy()
    dup = [-1] * len(keep)
    for i in np.flatnonzero(keep).tolist():
        best, best_v = -1, np.inf
        for j in kept:
            ok = True
            metric = np.inf
            if dd is not None:
                assert desc is not None
                cd = 1.0 - float(np.dot(desc[i].astype(np.float64), desc[j].astype(np.float64)))
                ok = ok and cd < dd
                metric = cd
            if rr is not None:
                assert pos is not None
                pd = float(np.linalg.norm(pos[i] - pos[j]))
                ok = ok and pd <= rr
                metric = pd if dd is None else metric
            if ok and metric < best_v:
                best, best_v = j, metric
        if best >= 0:
            out[i] = False
            dup[i] = best
        else:
            kept.append(i)
    return out.tolist(), dup


def test_redundancy_catches_loop_and_points_to_first_visit() -> None:
    rng = np.random.default_rng(2)
    first = unit_rows(rng.normal(size=(30, 128)))
    revisit = unit_rows(first[5:15] + 0.01 * rng.normal(size=(10, 128)))
    desc = np.concatenate([first, unit_rows(rng.normal(size=(10, 128))), revisit])
    t = random_table(50, seed=2, descriptors=desc, index=np.arange(500, 550))
    res = find_duplicates(t, np.ones(50, dtype=bool), RedundancyConfig(dup_distance=0.05))
    assert res.keep[:40].all() and not res.keep[40:].any()
    assert res.duplicate_of[40:].tolist() == list(range(5, 15))
    assert (res.duplicate_of[:40] == -1).all()
    sel = drop_duplicates(t, select(t, "paper", mt=0, st=0, et=0), RedundancyConfig(dup_distance=0.05))
    assert sel.duplicates == {540 + k: 505 + k for k in range(10)}
    assert sel.reason[40:] == ["duplicate"] * 10 and sel.n_kept == 40
    assert sel.info["dedup"]["n_dropped"] == 10


def test_redundancy_matches_brute_force_across_blocks() -> None:
    rng = np.random.default_rng(5)
    centres = unit_rows(rng.normal(size=(15, 16)))
    desc = unit_rows(centres[rng.integers(0, 15, size=400)] + 0.15 * rng.normal(size=(400, 16)))
    desc[7] = np.nan  # unknown descriptor: never a duplicate, never matched
    pos = rng.uniform(0, 30, size=(400, 2))
    pos[11] = np.nan
    t = random_table(400, seed=5, descriptors=desc, positions=pos)
    keep = rng.random(400) < 0.8
    for dd, rr in ((0.1, None), (None, 2.0), (0.2, 10.0)):
        cfg = RedundancyConfig(dup_distance=dd, dup_radius_m=rr, block_elements=64)
        res = find_duplicates(t, keep, cfg)
        want_keep, want_dup = brute_force_dedup(t.descriptors, t.positions, keep, dd, rr)
        assert res.keep.tolist() == want_keep, (dd, rr)
        assert res.duplicate_of.tolist() == want_dup, (dd, rr)
        assert 0 < int(np.sum(keep & ~res.keep)) < int(keep.sum())
        assert not (res.keep & ~keep).any()  # never adds frames


def test_redundancy_positions_radius_and_distinct_frames() -> None:
    n = 20
    pos = np.c_[np.arange(n) * 3.0, np.zeros(n)]
    pos[15] = [0.5, 0.5]  # back near frame 0
    pos[16] = [30.2, 0.0]  # near frame 10
    t = random_table(n, seed=6, positions=pos)
    res = find_duplicates(t, np.ones(n, dtype=bool), RedundancyConfig(dup_distance=None, dup_radius_m=1.0))
    assert np.flatnonzero(~res.keep).tolist() == [15, 16]
    assert res.duplicate_of[15] == 0 and res.duplicate_of[16] == 10
    assert res.distance[15] == pytest.approx(math.hypot(0.5, 0.5))
    # with descriptors too, both conditions must hold: look-alikes far apart are kept
    rng = np.random.default_rng(0)
    desc = np.repeat(unit_rows(rng.normal(size=(1, 8))), n, axis=0)
    t2 = random_table(n, seed=6, positions=pos, descriptors=desc)
    both = find_duplicates(t2, np.ones(n, dtype=bool), RedundancyConfig(dup_distance=0.1, dup_radius_m=1.0))
    assert np.flatnonzero(~both.keep).tolist() == [15, 16]
    desc_only = find_duplicates(t2, np.ones(n, dtype=bool), RedundancyConfig(dup_distance=0.1))
    assert np.flatnonzero(desc_only.keep).tolist() == [0]
    # distinct frames are all kept
    d3 = unit_rows(np.eye(n, 32))
    t3 = random_table(n, seed=6, descriptors=d3)
    assert find_duplicates(t3, np.ones(n, dtype=bool)).keep.all()
    # via select(..., dedup=...)
    s = select(t2, "paper", mt=0, st=0, et=0, dedup={"dup_distance": 0.1, "dup_radius_m": 1.0})
    assert s.duplicates == {15: 0, 16: 10}
    with pytest.raises(ConfigError):
        RedundancyConfig(dup_distance=None, dup_radius_m=None)
    with pytest.raises(ConfigError, match="descriptors"):
        find_duplicates(random_table(5), np.ones(5, dtype=bool))


# ---------------------------------------------------------------- baselines


def test_uniform_baseline() -> None:
    for n, k in ((100, 7), (10, 10), (1000, 333), (5, 1), (7, 2)):
        idx = uniform_indices(n, k)
        assert len(idx) == k == len(set(idx.tolist()))
        assert idx[0] == 0 and (k < 2 or idx[-1] == n - 1)
        assert np.all(np.diff(idx) > 0)
        if k >= 2:
            step = (n - 1) / (k - 1)
            assert np.all(np.abs(idx - step * np.arange(k)) <= 0.5)
        assert uniform_mask(n, k).sum() == k
    assert uniform_indices(10, 0).tolist() == []
    assert uniform_indices(0, 0).tolist() == []
    with pytest.raises(ConfigError):
        uniform_indices(5, 6)
    with pytest.raises(ConfigError):
        uniform_indices(5, -1)


def test_every_kth_from_its_start_offsets() -> None:
    # every other frame of 9: the even frames, then the odd ones (the last shifted past frame 8 wraps to 0)
    m = phase_masks(9, 5)
    assert [np.flatnonzero(r).tolist() for r in m] == [[0, 2, 4, 6, 8], [0, 1, 3, 5, 7]]
    assert np.array_equal(m[0], uniform_mask(9, 5))
    # a spacing of 2.25 (5 of 10): three offsets, shifted 0, 1 and 2 frames (rint of 0, 0.75, 1.5)
    assert [np.flatnonzero(r).tolist() for r in phase_masks(10, 5)] == [[0, 2, 4, 7, 9], [0, 1, 3, 5, 8],
                                                                        [1, 2, 4, 6, 9]]
    # every 5.2th of 100 (spacing 99/19): every offset, shifts of 0 .. 5 frames (rint of j * 5.21 / 6);
    # four of them asked for: 0, 1, 3 and 4 (rint of j * 5.21 / 4); a row shifted past frame 99 wraps
    base = uniform_indices(100, 20)
    assert [np.flatnonzero(r).tolist() for r in phase_masks(100, 20)] == [
        sorted(int(v) for v in (base + d) % 100) for d in range(6)]
    m = phase_masks(100, 20, phases=4)
    want = [sorted(int(v) for v in (base + d) % 100) for d in (0, 1, 3, 4)]
    assert [np.flatnonzero(r).tolist() for r in m] == want
    assert (m.sum(axis=1) == 20).all()
    assert len(phase_masks(100, 20, phases=2)) == 2 and len(phase_masks(100, 20, phases=1)) == 1
    # one offset only where every frame is kept, or one frame
    assert phase_masks(10, 10).shape == (1, 10) and phase_masks(10, 1).shape == (1, 10)
    assert phase_masks(10, 0).sum() == 0
    with pytest.raises(ConfigError):
        phase_masks(10, 5, phases=0)
    with pytest.raises(ConfigError):
        phase_masks(5, 6)


def test_random_baseline() -> None:
    a = random_indices(100, 10, seed=3)
    assert len(set(a.tolist())) == 10 and a.min() >= 0 and a.max() < 100
    assert np.array_equal(a, random_indices(100, 10, seed=3))
    masks = random_masks(100, 10)
    assert masks.shape == (20, 100) and (masks.sum(axis=1) == 10).all()
    assert len({m.tobytes() for m in masks}) == 20
    assert np.array_equal(masks[4], random_mask(100, 10, 4))
    assert random_masks(100, 10, seeds=[]).shape == (0, 100)
    t = random_table(30, seed=1, index=np.arange(7, 37))
    u = baseline_selection(t, 5)
    assert u.kept_indices.tolist() == (7 + uniform_indices(30, 5)).tolist()
    r = baseline_selection(t, 5, seed=1)
    assert r.n_kept == 5 and set(r.reason) == {None, "not-sampled"}


# ---------------------------------------------------------------- the selection layer's own error class


def test_selection_inputs_raise_selection_error_not_evaluation_error() -> None:
    """Invalid inputs of the selection layer (layer 4) raise its own SelectionError, never the
    evaluation layer's EvaluationError; both stay MemlogErrors that are not UsageErrors (exit 1)."""
    from memlog.errors import UsageError
    from memlog.selection.distinctiveness import distinctiveness, margins

    t = random_table(6, seed=1)
    unit = unit_rows(np.ones((6, 4)))
    cases: list[tuple[str, Any]] = [
        ("empty", lambda: calibrate(make_table([], [], []), 0.5)),
        ("entropy", lambda: calibrate(make_table([0.5, 0.6], [1.0, 1.0], [np.nan, np.nan]), 0.5)),
        ("shape", lambda: margins(np.ones(5))),
        ("shape", lambda: distinctiveness(np.ones((2, 3, 4)))),
        ("bool mask", lambda: find_duplicates(make_table(t.ms, t.ss, t.es, descriptors=unit), np.ones(5, bool))),
        ("bool mask", lambda: find_duplicates(make_table(t.ms, t.ss, t.es, descriptors=unit), np.ones(6))),
        ("different frames", lambda: drop_duplicates(
            make_table(t.ms, t.ss, t.es, descriptors=unit), select(random_table(5, seed=1), "paper"))),
        ("length", lambda: make_table([0.1, 0.2], [0.1], [0.3, 0.4])),
        ("non-decreasing", lambda: make_table([0.1, 0.2], [0.1, 0.2], [0.3, 0.4], t_ns=[5, 4])),
        ("row mask", lambda: t.take(np.ones(3, dtype=bool))),
        ("reason", lambda: Selection(mode="x", index=np.arange(2), keep=np.array([True, False]),
                                     reason=[None, None])),
    ]
    for match, call in cases:
        with pytest.raises(SelectionError, match=match) as info:
            call()
        assert not isinstance(info.value, EvaluationError), match
    assert issubclass(SelectionError, MemlogError) and not issubclass(SelectionError, UsageError)


# ---------------------------------------------------------------- the segment defaults


def test_segment_defaults_have_one_source_and_combined_score_defaults_to_geometric() -> None:
    """combined_score without ``combine`` is the weighted geometric mean (the documented default),
    and every entry point's segment default is the one in SEGMENT_DEFAULTS."""
    t = random_table(50, seed=31)
    # behaviour first, against a hand-computed expectation: (MS*SS*ES)^(1/3)
    from memlog.selection import combined_score

    np.testing.assert_allclose(combined_score(t), (t.ms * t.ss * t.es) ** (1 / 3), rtol=1e-12)

    from memlog.selection.config import SelectionConfig
    from memlog.selection.segment import SEGMENT_DEFAULTS

    # the documented choices (README "defaults" table, segment module docstring)
    d = SEGMENT_DEFAULTS
    from memlog.selection.coordinates import VIEW_STEP_CAP

    assert (d.combine, d.view_spacing, d.keep_fraction, d.min_ss) == ("geometric", VIEW_STEP_CAP, 0.25, 0.1)
    keys = ("by", "combine", "weights", "min_ms", "min_ss", "min_es", "view_distance", "distinct_weight")
    want = {k: getattr(SEGMENT_DEFAULTS, k) for k in keys}
    # SELECTORS["segment"] (what select() and so SelectionConfig.run start from): sized by view change
    assert {k: SELECTORS["segment"][k] for k in keys} == want
    assert SELECTORS["segment"]["spacing_view"] == d.view_spacing and "keep_fraction" not in SELECTORS["segment"]
    # SegmentConfig's field defaults (a size must be given)
    seg = SegmentConfig(spacing_view=SEGMENT_DEFAULTS.view_spacing)
    assert {k: getattr(seg, k) for k in keys} == want
    # SelectionConfig's segment settings (the view spacing filled in when no size is given)
    settings = SelectionConfig().segment_settings()
    assert {k: settings[k] for k in keys} == want
    assert settings["spacing_view"] == d.view_spacing and "keep_fraction" not in settings
    # combined_score's own parameter defaults
    import inspect

    params = inspect.signature(combined_score).parameters
    assert params["combine"].default == want["combine"] and params["weights"].default == want["weights"]
    assert params["distinct_weight"].default == want["distinct_weight"]
    # select_segments with no config: the default keep fraction of segments, picked by the default combine
    sel = select_segments(t)
    assert sel.info["n_bins"] == math.floor(0.25 * 50 + 0.5) and sel.info["combine"] == "geometric"
    assert sel.keep.tolist() == select_segments(t, seg).keep.tolist()


# ---------------------------------------------------------------- distance segments across a GNSS gap


def gap_drive(speed: Any = 2.0, radius: float = 200.0) -> tuple[ScoreTable, NDArray[np.bool_], F64]:
    """10 Hz frames for 300 s along a circle of ``radius`` metres at ``speed`` m/s (a number or a
    function of time in seconds); positions unknown (NaN) from 120 s to 180 s, a tunnel. Returns the
    table, the gap rows and the frame times in seconds."""
    n = 3000
    t_s = np.arange(n) / 10.0
    v = speed(t_s) if callable(speed) else np.full(n, float(speed))
    arc = np.concatenate([[0.0], np.cumsum(v[:-1] * 0.1)])
    pos = np.c_[radius * np.sin(arc / radius), radius * (1 - np.cos(arc / radius))]
    gap = (t_s >= 120.0) & (t_s < 180.0)
    pos[gap] = np.nan
    table = random_table(n, seed=5, positions=pos, t_ns=(np.arange(n) * 100_000_000).astype(np.int64))
    return table, gap, t_s


def whole_segments(seg: NDArray[np.int64], rows: NDArray[np.bool_]) -> list[int]:
    """Segments lying wholly within ``rows``."""
    return [int(s) for s in np.unique(seg[rows]) if rows[seg == s].all()]


@pytest.mark.parametrize("size", [{"spacing_m": 10.0}, {"keep_fraction": 0.02}])
def test_distance_segments_are_cut_by_time_across_a_gnss_gap(size: dict[str, float]) -> None:
    from memlog.selection import segment_ids

    table, gap, t_s = gap_drive()
    seg, info = segment_ids(table, SegmentConfig(by="distance", **size))
    assert np.all(np.diff(seg) >= 0) and np.all(np.diff(seg) <= 1) and seg[0] == 0  # consecutive ids
    # 2 m/s everywhere: 10 m segments are 5 s long (keep_fraction 0.02 of 3000 frames: 60 segments
    # of 600 m), also in the tunnel (before the fix: its 60 s were one segment, the last one of the
    # known stretch before it)
    rest = len(whole_segments(seg, ~gap)) / 240.0
    in_gap = len(whole_segments(seg, gap)) / 60.0
    assert rest == pytest.approx(0.2, rel=0.05)
    assert in_gap == pytest.approx(rest, rel=0.1)
    durations = [np.ptp(t_s[seg == s]) + 0.1 for s in whole_segments(seg, gap)]
    assert np.allclose(durations, 5.0, atol=0.15)
    # info says how many segments were cut by time in the gap
    assert info["position_gaps"] == 1
    assert info["time_segments"] == len(np.unique(seg[gap]))
    assert 11 <= info["time_segments"] <= 13


def test_gnss_gap_length_from_the_speed_around_it_or_the_straight_line() -> None:
    from memlog.selection import segment_ids

    cfg = SegmentConfig(by="distance", spacing_m=10.0)
    # a tunnel that loops (circle of 180 m: the fixes either side of it are ~0 m apart), at 3 m/s
    # around it while the drive's ends crawl at 0.5 m/s: the tunnel's 60 s are 180 m, 18 segments
    loop = lambda t: np.where((t >= 60.0) & (t < 240.0), 3.0, 0.5)
    table, gap, _ = gap_drive(loop, radius=180.0 / (2 * np.pi))
    seg, info = segment_ids(table, cfg)
    assert len(whole_segments(seg, gap)) in (17, 18) and info["time_segments"] in (18, 19)
    # a straight tunnel driven faster (3 m/s) than around it (1 m/s): the straight line between the
    # fixes (180 m) is longer than speed x time (60 m) and is the gap's length
    fast = lambda t: np.where((t >= 120.0) & (t < 180.0), 3.0, 1.0)
    table, gap, _ = gap_drive(fast, radius=1e9)
    seg, info = segment_ids(table, cfg)
    assert len(whole_segments(seg, gap)) in (17, 18) and info["time_segments"] in (18, 19)
    assert info["gap_length_m"] == pytest.approx(180.0, abs=0.5)


def test_a_missing_fix_at_the_fixes_rate_is_no_gap() -> None:
    from memlog.selection import segment_ids

    table, gap, _ = gap_drive()
    pos = table.positions
    assert pos is not None
    pos = pos.copy()
    pos[gap] = pos[np.flatnonzero(gap)[0] - 1]  # the tunnel filled in: the robot stood there
    pos[[500, 2500, 2501]] = np.nan  # one missing fix, two missing fixes
    t = ScoreTable(index=table.index, t_ns=table.t_ns, ms=table.ms, ss=table.ss, es=table.es, positions=pos)
    seg, info = segment_ids(t, SegmentConfig(by="distance", spacing_m=10.0))
    assert info["position_gaps"] == 0 and info["time_segments"] == 0
    assert len(set(seg[np.flatnonzero(gap)[0] - 1 : np.flatnonzero(gap)[-1] + 1].tolist())) == 1  # standing: one

"""Distinctiveness: values against a loop written out by hand, and the criterion in both selection modes."""

from __future__ import annotations

import numpy as np
import pytest

from memlog.descriptors.base import l2_normalize
from memlog.errors import ConfigError
from memlog.selection.config import SelectionConfig
from memlog.selection.distinctiveness import DistinctConfig, distinctiveness, margins
from memlog.selection.table import ScoreTable


def _drive(n: int = 60, d: int = 16, seed: int = 0) -> np.ndarray:
    """A drive whose views change slowly (a random walk), unit rows."""
    rng = np.random.default_rng(seed)
    x = np.cumsum(rng.normal(size=(n, d)), axis=0) + rng.normal(size=(n, d)) * 0.3
    return l2_normalize(x)


def _by_hand(d: np.ndarray, window: int, exclusion: int) -> tuple[list[float], list[float]]:
    near, far = [], []
    for i in range(len(d)):
        own = [float(d[i] @ d[j]) for j in range(len(d)) if 1 <= abs(i - j) <= window]
        dist = [float(d[i] @ d[j]) for j in range(len(d)) if abs(i - j) > exclusion]
        near.append(sum(own) / len(own))
        far.append(max(dist) if dist else float("nan"))
    return near, far


@pytest.mark.parametrize("block_rows", [1, 7, 1024])
def test_margins_match_a_plain_loop(block_rows: int) -> None:
    d = _drive()
    cfg = DistinctConfig(window=2, exclusion=5, block_rows=block_rows)
    near, far = margins(d, cfg)
    n_ref, f_ref = _by_hand(d, 2, 5)
    np.testing.assert_allclose(near, n_ref, atol=1e-5)
    np.testing.assert_allclose(far, f_ref, atol=1e-5)


def test_an_aliased_frame_is_the_least_distinctive() -> None:
    d0 = _drive(n=50)
    d = d0.copy()
    d[40] = d[10]  # frame 40 looks exactly like a distant part of the drive (and 10 like 40)
    cfg = DistinctConfig(window=1, exclusion=5)
    ds, before = distinctiveness(d, cfg), distinctiveness(d0, cfg)
    assert int(np.argmin(ds)) == 40
    assert ds[10] < before[10]  # frame 10 became aliased too
    assert np.all((ds > 0) & (ds < 1))
    # NaN descriptors give NaN and are ignored by the others
    d2 = d.copy()
    d2[3] = np.nan
    ds2 = distinctiveness(d2, DistinctConfig(window=1, exclusion=5))
    assert np.isnan(ds2[3]) and np.all(np.isfinite(np.delete(ds2, 3)))


def _table(ds: np.ndarray) -> ScoreTable:
    n = len(ds)
    return ScoreTable(index=np.arange(n), t_ns=np.arange(n) * 10**8, ms=np.full(n, 0.8), ss=np.ones(n),
                      es=np.full(n, 0.7), ds=ds)


def test_paper_mode_threshold_on_distinctiveness() -> None:
    rng = np.random.default_rng(1)
    ds = rng.random(40)
    sel = SelectionConfig(mode="paper", mt=0, st=0, et=0, dt=0.5).run(_table(ds))
    np.testing.assert_array_equal(sel.keep, ds >= 0.5)
    assert set(sel.reason_counts()) == {"distinctiveness"} and sel.thresholds["dt"] == 0.5
    # combined with the paper's criteria: a frame failing MS is dropped for memorability first
    t = _table(ds)
    t.ms[0] = 0.1
    sel2 = SelectionConfig(mode="paper", mt=0.5, st=0, et=0, dt=0.5).run(t)
    assert sel2.reason[0] == "memorability" and np.array_equal(sel2.keep[1:], ds[1:] >= 0.5)


def test_segment_mode_picks_the_most_distinctive_frame_of_each_segment() -> None:
    rng = np.random.default_rng(2)
    ds = rng.random(40)
    cfg = SelectionConfig(keep_fraction=0.25, segment_by="count", weights=(0.0, 0.0, 0.0), distinct_weight=1.0)
    sel = cfg.run(_table(ds))
    seg = sel.segment_id
    assert seg is not None and sel.n_kept == 10
    for s in range(10):
        rows = np.flatnonzero(seg == s)
        assert sel.keep[rows[np.argmax(ds[rows])]]
    # combined: equal weights with constant MS/SS/ES still follow DS (the geometric mean is monotone in it)
    sel2 = SelectionConfig(keep_fraction=0.25, segment_by="count", distinct_weight=1.0).run(_table(ds))
    np.testing.assert_array_equal(sel2.keep, sel.keep)
    # without it the earliest frame of each segment wins the tie
    sel3 = SelectionConfig(keep_fraction=0.25, segment_by="count").run(_table(ds))
    assert not np.array_equal(sel3.keep, sel.keep)


def test_config_checks() -> None:
    assert SelectionConfig(mode="paper", dt=0.3).needs_distinctiveness
    assert SelectionConfig(distinct_weight=0.5).needs_distinctiveness
    assert not SelectionConfig().needs_distinctiveness
    with pytest.raises(ConfigError, match="paper selection mode"):
        SelectionConfig(dt=0.3)
    with pytest.raises(ConfigError, match="segment selection mode"):
        SelectionConfig(mode="paper", distinct_weight=1.0)
    with pytest.raises(ConfigError, match="keep_fraction"):
        SelectionConfig(mode="paper", dt=0.3, keep_fraction=0.5)
    with pytest.raises(ConfigError, match="larger"):
        SelectionConfig(distinct_window=5, distinct_exclusion=5)
    with pytest.raises(ConfigError, match="ds"):
        SelectionConfig(mode="paper", dt=0.3).run(ScoreTable(index=np.arange(3), t_ns=np.arange(3),
                                                             ms=np.ones(3), ss=np.ones(3), es=np.ones(3)))


def test_map_selects_by_distinctiveness_of_the_whitened_drive(tmp_path) -> None:  # type: ignore[no-untyped-def]
    """End to end on the real EuRoC frames: the map step's DS equals DS computed here from the
    describer's output whitened by a transform fitted on every frame; both modes keep accordingly."""
    from memlog.descriptors.registry import make_describer
    from memlog.descriptors.whitening import fit_whitening
    from memlog.io import open_log
    from memlog.outputs.descriptor_table import read_descriptors
    from memlog.steps.map import MapConfig, make_map
    from tests.conftest import shared

    log, topic = shared("euroc_micro_ros2.mcap"), "/cam0/image_raw"
    with open_log(log) as r:
        frames = list(r.frames([topic]))
        imgs = [f.decode_bgr() for f in frames]
    recs = {topic: [{"frame_index": f.index, "log_time": f.log_time_ns, "ms": 0.9, "ss": 1.0, "es": 0.9}
                    for f in frames]}
    raw = make_describer("thumbnail").describe(imgs)
    w = fit_whitening(raw)
    ds = distinctiveness(w.apply(raw))
    seg = SelectionConfig(keep_fraction=0.2, segment_by="count", weights=(0.0, 0.0, 0.0), distinct_weight=1.0)
    res = make_map(log, tmp_path / "m.mcap", MapConfig(select=seg, topics=(topic,), descriptor="thumbnail"),
                   scores=recs)
    want = seg.run(_table(ds)).kept_indices
    np.testing.assert_array_equal(res.selections[topic].kept_indices, want)
    t = read_descriptors(res.descriptors)
    assert t.whitening is not None and t.whitening.sha256 == w.sha256  # the same transform, fitted once
    np.testing.assert_allclose(t.descriptors, w.apply(raw)[want], atol=1e-5)
    pap = SelectionConfig(mode="paper", mt=0.0, st=0.0, et=0.0, dt=0.6)
    res2 = make_map(log, tmp_path / "p.mcap", MapConfig(select=pap, topics=(topic,), descriptor="thumbnail"),
                    scores=recs)
    np.testing.assert_array_equal(res2.selections[topic].kept_indices, np.flatnonzero(ds >= 0.6))
    # scores of part of the drive: the whitening and DS are computed on those frames only
    part = {topic: recs[topic][:60]}
    res3 = make_map(log, tmp_path / "q.mcap", MapConfig(select=seg, topics=(topic,), descriptor="thumbnail"),
                    scores=part)
    w60 = fit_whitening(raw[:60])
    t3 = read_descriptors(res3.descriptors)
    assert t3.whitening is not None and t3.whitening.n_fit == 60 and t3.whitening.sha256 == w60.sha256
    np.testing.assert_array_equal(res3.selections[topic].kept_indices,
                                  seg.run(_table(distinctiveness(w60.apply(raw[:60])))).kept_indices)

"""Tests of memlog.matching: drives matched as sequences.

Every expectation is independent of the code under test: the synthetic drives are built from a
list of true places (the query's path, with stops and a fast stretch), and a result is checked
against that list; single-frame results are checked against a brute-force argmax.
"""

from __future__ import annotations

import numpy as np
import pytest

from memlog.descriptors.base import DescriptorMeta
from memlog.matching import (
    STAT_SAMPLE,
    SequenceConfig,
    drive_runs,
    match_sequences,
    match_tables,
    resolve_coordinate,
)
from memlog.descriptors.table import DescriptorTable
from memlog.errors import ConfigError, DescriptorError

N_PLACES = 300
DIM = 32
NOISE = 0.7  # noise of a query frame: single frames are often wrong (R@1 about 0.5), sequences are not


def _unit(x: np.ndarray) -> np.ndarray:
    return (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32)


@pytest.fixture(scope="module")
def places() -> np.ndarray:
    """Descriptors of N_PLACES unrelated places (like Nordland's frames: a neighbour is another place)."""
    return np.random.default_rng(0).normal(size=(N_PLACES, DIM))


def _path() -> np.ndarray:
    """The query's true places: normal speed, a stop of 30 frames, a 3x stretch, a 2x stretch, normal."""
    return np.r_[np.arange(0, 60), np.full(30, 60), np.arange(61, 150, 3), np.arange(150, 220, 2),
                 np.arange(220, 290)].astype(np.int64)


def _query(places: np.ndarray, path: np.ndarray, seed: int = 1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return _unit(places[path] + NOISE * rng.normal(size=(len(path), DIM)) * np.sqrt(DIM) / 2)


def _single_best(q: np.ndarray, r: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    sim = q.astype(np.float64) @ r.astype(np.float64).T
    if mask is not None:
        sim[:, ~mask] = -np.inf
    return np.argmax(sim, axis=1)


def _share_within(found: np.ndarray, true: np.ndarray, tol: float) -> float:
    return float(np.mean(np.abs(found - true) <= tol))


def test_stops_and_a_fast_stretch_localize(places: np.ndarray) -> None:
    path = _path()
    ref = _unit(places)
    q = _query(places, path)
    # the stop is left out as match_tables leaves it out: the moving index, and the stop's frames
    # after its first standing (they take its first frame's match)
    standing = np.r_[False, path[1:] == path[:-1]]
    frames = (np.arange(len(path)) - np.cumsum(standing)).astype(np.float64)
    single = _share_within(_single_best(q, ref), path, 1)
    assert single < 0.6  # the task is hard frame by frame (measured 0.48)
    for cfg in (SequenceConfig(), SequenceConfig(causal=True)):
        res = match_sequences(q, frames, ref, np.arange(N_PLACES, dtype=np.float64), cfg, k=3, standing=standing)
        assert res.sequence.all() if not cfg.causal else res.sequence[cfg.length:].all()
        # causal windows straddle each change of speed for up to N frames
        got = _share_within(res.indices[res.sequence, 0], path[res.sequence], 1)
        assert got >= (0.9 if cfg.causal else 0.95), (cfg.causal, got)
        stop = slice(70 if cfg.causal else 60, 90)  # standing still at place 60 (causal: once N frames in)
        assert _share_within(res.indices[stop, 0], path[stop], 1) == 1.0
        ranks = res.indices[:, :3]
        assert np.all(np.abs(ranks[:, 0] - ranks[:, 1]) > cfg.exclude)  # ranks are distinct places
        assert np.all(res.margin[res.sequence] >= 0)
    # the stop's frames take its first frame's match; about speed 3 in the 3x stretch (offline)
    res = match_sequences(q, frames, ref, np.arange(N_PLACES, dtype=np.float64), SequenceConfig(), k=1,
                          standing=standing)
    assert np.all(res.indices[61:90, 0] == res.indices[60, 0]) and res.info["standing_rows"] == 29
    assert np.median(res.speed[100:110]) == pytest.approx(3.0, abs=0.3)


def test_a_map_at_another_frame_rate(places: np.ndarray) -> None:
    """The map shows every place twice (twice the frame rate): in frames the query's speed doubles
    (2 map frames per query frame, 6 in its 3x stretch: beyond the default 0..3, so the range is
    widened); in stamps it stays 1 (10 Hz query, 20 Hz map)."""
    path = _path()
    ref = _unit(np.repeat(places, 2, axis=0) + 0.05 * np.random.default_rng(3).normal(size=(2 * N_PLACES, DIM)))
    q = _query(places, path)
    frames = np.arange(len(path), dtype=float)
    wide = SequenceConfig(speeds=(0, 6.5), speed_prior=0.0)
    res = match_sequences(q, frames, ref, np.arange(2 * N_PLACES, dtype=float), wide, k=1)
    assert _share_within(res.indices[:, 0] // 2, path, 1) >= 0.95
    assert np.median(res.speed[:50]) == pytest.approx(2.0, abs=0.2)
    narrow = match_sequences(q, frames, ref, np.arange(2 * N_PLACES, dtype=float), SequenceConfig(), k=1)
    assert _share_within(narrow.indices[90:120, 0] // 2, path[90:120], 1) < 0.5  # 6x is outside 0..3
    ref_t = _table(ref, np.arange(2 * N_PLACES), np.arange(2 * N_PLACES) * 50_000_000)  # 20 Hz
    q_t = _table(q, np.arange(len(path)), 10**18 + np.arange(len(path)) * 100_000_000)  # 10 Hz
    q_t.moving_index = np.arange(len(path)) - np.cumsum(np.r_[False, path[1:] == path[:-1]])  # the stop
    res_t = match_tables(q_t, ref_t, SequenceConfig(coordinate="time"), k=1)
    assert _share_within(res_t.indices[:, 0] // 2, path, 1) >= 0.95
    assert np.median(res_t.speed[:50]) == pytest.approx(1.0, abs=0.1)
    # in frames, the drive's pace is the ratio of the frame intervals (2 map frames per query frame):
    # the default speeds and the prior are taken around it, so the moving stretches are found
    res_f = match_tables(q_t, ref_t, SequenceConfig(coordinate="frames"), k=1)
    assert res_f.info["pace"] == pytest.approx(2.0)
    moving = np.r_[np.arange(10, 55), np.arange(155, 215)]  # away from the stop, which no moving index marks
    assert _share_within(res_f.indices[moving, 0] // 2, path[moving], 1) >= 0.95
    assert np.median(res_f.speed[:50]) == pytest.approx(2.0, abs=0.2)


def test_a_drive_finds_itself_up_to_its_ends(places: np.ndarray) -> None:
    ref = _unit(places)
    c = np.arange(N_PLACES, dtype=np.float64)
    res = match_sequences(ref, c, ref, c, SequenceConfig(), k=2)
    np.testing.assert_array_equal(res.indices[:, 0], np.arange(N_PLACES))
    assert np.all(res.speed == pytest.approx(1.0, abs=0.11))


def test_causal_uses_no_future_frame(places: np.ndarray) -> None:
    path = _path()
    ref = _unit(places)
    q = _query(places, path)
    frames = np.arange(len(path), dtype=np.float64)
    rc = np.arange(N_PLACES, dtype=np.float64)
    cfg = SequenceConfig(causal=True)
    a = match_sequences(q, frames, ref, rc, cfg, k=3)
    for cut in (15, 75, 140):
        other = q.copy()
        other[cut + 1:] = _unit(np.random.default_rng(cut).normal(size=(len(q) - cut - 1, DIM)))  # another future
        b = match_sequences(other, frames, ref, rc, cfg, k=3)
        past = slice(0, cut + 1)
        for name in ("indices", "scores", "margin", "speed", "window", "sequence"):
            np.testing.assert_array_equal(getattr(a, name)[past], getattr(b, name)[past], err_msg=f"{name} {cut}")
    # and offline matching does use the future (the check above is not vacuous)
    off = match_sequences(q, frames, ref, rc, SequenceConfig(), k=3)
    other = q.copy()
    other[76:] = _unit(np.random.default_rng(9).normal(size=(len(q) - 76, DIM)))
    assert not np.array_equal(off.scores[:76], match_sequences(other, frames, ref, rc, SequenceConfig(), k=3).scores[:76])
    # the first frames of a run have no full causal window yet: matched frame by frame, and said so
    assert not a.sequence[: cfg.length].any() and a.sequence[cfg.length:].all()
    assert "10 frame(s): fewer frames of its run before it than the causal window needs" in a.info["fallback"]
    assert set(a.fallback[: cfg.length]) == {"causal-start"} and set(a.fallback[cfg.length:]) == {""}


def test_the_fallback_message_counts_the_standing_frames_it_covers(places: np.ndarray) -> None:
    """A causal drive that stands 20 frames at its start: those frames take the first frame's
    match, which has no window yet, so they too are matched frame by frame. With the first 10
    frames of the moving drive that makes 29 single frames, and the message says 29, as
    ``single_queries`` does, not the 10 moving ones (``localize`` says it, once: ``test_localize``)."""
    path = np.r_[np.zeros(20, np.int64), np.arange(1, 120)]
    standing = np.r_[False, path[1:] == path[:-1]]
    moving = np.arange(len(path)) - np.cumsum(standing)  # the frame index with the stop left out
    cfg = SequenceConfig(causal=True)
    res = match_sequences(_query(places, path), moving.astype(np.float64), _unit(places),
                          np.arange(N_PLACES, dtype=np.float64), cfg, k=3, standing=standing)
    n_single = 19 + cfg.length  # the stop after its first frame, and the moving frames without a full window
    assert int((~res.sequence).sum()) == n_single == res.info["single_queries"]
    assert res.info["fallback"].startswith(f"{n_single} of {len(path)} frames matched frame by frame")
    assert f"{n_single} frame(s): fewer frames of its run before it" in res.info["fallback"]


def test_results_do_not_depend_on_blocking(places: np.ndarray) -> None:
    path = _path()
    ref = _unit(places)
    q = _query(places, path)
    frames = np.arange(len(path), dtype=np.float64)
    rc = np.arange(N_PLACES, dtype=np.float64)
    runs = (np.arange(len(path)) >= 100).astype(np.int64)  # two runs: windows stop at the boundary
    results = [match_sequences(q, frames, ref, rc, SequenceConfig(block=b), k=4, runs=runs)
               for b in (1, 7, 64, 10_000)]
    for r in results[1:]:
        for name in ("indices", "scores", "similarities", "margin", "speed", "window", "sequence"):
            np.testing.assert_array_equal(getattr(results[0], name), getattr(r, name), err_msg=name)
    # windows never cross the run boundary: frame 99's offline window is its 11 past frames and itself
    assert results[0].window[99] == 11 and results[0].window[100] == 11 and results[0].window[50] == 21


@pytest.mark.parametrize("step", [2, 4])
def test_sparse_maps_localize(places: np.ndarray, step: int) -> None:
    """A map keeping every 2nd / 4th frame of a drive along the places: the best match is the kept
    frame nearest the true place (within half the spacing), for a mask and for a table of the kept
    frames only (with their frame indices in the reference drive)."""
    path = _path()
    ref = _unit(places + 0.1 * np.random.default_rng(5).normal(size=places.shape))  # the map drive's own noise
    q = _query(places, path)
    standing = np.r_[False, path[1:] == path[:-1]]  # the stop, left out as match_tables leaves it out
    frames = (np.arange(len(path)) - np.cumsum(standing)).astype(np.float64)
    rc = np.arange(N_PLACES, dtype=np.float64)
    mask = np.arange(N_PLACES) % step == 0
    single = _share_within(_single_best(q, ref, mask), path, step / 2)
    res = match_sequences(q, frames, ref, rc, SequenceConfig(), k=2, ref_mask=mask, standing=standing)
    assert np.all(mask[res.indices[:, 0]])  # only map frames are returned, as rows of the full reference
    got = _share_within(res.indices[:, 0], path, step / 2)
    # measured 0.88 / 0.88: the speed prior costs most of the 3x stretch (1.5 map frames per query
    # frame on the half map), right elsewhere; without it 0.94 / 0.92, but worse on real drives
    assert got >= 0.85 and got > single + 0.4, (got, single)
    kept = np.flatnonzero(mask)  # the same map as a table of the kept frames: rows are kept frames
    res2 = match_sequences(q, frames, ref[kept], kept.astype(np.float64), SequenceConfig(), k=2, ref_unit=1.0,
                           standing=standing)
    np.testing.assert_array_equal(kept[res2.indices[:, 0]], res.indices[:, 0])


def _table(desc: np.ndarray, frames: np.ndarray, t_ns: np.ndarray, xy: np.ndarray | None = None,
           topic: str = "/cam") -> DescriptorTable:
    pos = {} if xy is None else {"x": xy[:, 0], "y": xy[:, 1], "z": np.zeros(len(desc))}
    return DescriptorTable(topic=[topic] * len(desc), frame_index=frames, log_time_ns=t_ns, stamp_ns=t_ns,
                           descriptors=desc, meta=DescriptorMeta("test", {}, desc.shape[1]), positions=pos)


def test_positions_mode_matches_in_metres(places: np.ndarray) -> None:
    """Both drives carry positions: the query's stop adds no distance, its fast stretch covers more
    metres per frame; matched in metres the speed is about 1 everywhere."""
    path = _path()
    ref_desc = _unit(places)
    q = _query(places, path)
    rng = np.random.default_rng(7)
    along = lambda p: np.stack([np.asarray(p, float) * 8.0, np.zeros(len(p))], axis=1)  # noqa: E731
    ref = _table(ref_desc, np.arange(N_PLACES), np.arange(N_PLACES) * 100_000_000, along(np.arange(N_PLACES)))
    qxy = along(path) + rng.normal(0, 0.05, (len(path), 2))
    qt = _table(q, np.arange(len(path)), 10**18 + np.arange(len(path)) * 100_000_000, qxy)
    assert resolve_coordinate("auto", qt, ref) == ("positions", None)
    res = match_tables(qt, ref, SequenceConfig(), k=1)
    assert res.info["coordinate"] == "positions" and res.info["speeds"] == [0.8, 1.25]
    assert _share_within(res.indices[:, 0], path, 1) >= 0.95
    moving = np.r_[20:50, 95:115, 160:220]  # rows of the normal, 3x and normal stretches
    assert np.median(res.speed[moving]) == pytest.approx(1.0, abs=0.1)
    # without positions in the query, auto matches in frames and says so; positions is refused
    bare = _table(q, np.arange(len(path)), 10**18 + np.arange(len(path)) * 100_000_000)
    assert resolve_coordinate("auto", bare, ref) == ("frames", "no positions in both drives: matched in frames")
    with pytest.raises(DescriptorError, match="the query has no position"):
        match_tables(bare, ref, SequenceConfig(coordinate="positions"))


def test_time_mode_follows_the_stamps(places: np.ndarray) -> None:
    """Matched in stamps, a query at half the frame rate (every 2nd place, 5 Hz) has speed 1."""
    path = np.arange(0, 280, 2)
    ref = _table(_unit(places), np.arange(N_PLACES), np.arange(N_PLACES) * 100_000_000)
    qt = _table(_query(places, path), np.arange(len(path)), 10**18 + np.arange(len(path)) * 200_000_000)
    res = match_tables(qt, ref, SequenceConfig(coordinate="time"), k=1)
    assert _share_within(res.indices[:, 0], path, 1) >= 0.95
    assert np.median(res.speed) == pytest.approx(1.0, abs=0.1)


def test_single_images_and_unordered_frames_fall_back(places: np.ndarray) -> None:
    ref_desc = _unit(places)
    ref = _table(ref_desc, np.arange(N_PLACES), np.arange(N_PLACES) * 100_000_000)
    q = _query(places, np.arange(40, 80))
    # one image
    one = match_tables(_table(q[:1], np.arange(1), np.array([5])), ref, SequenceConfig(), k=3)
    assert not one.sequence.any() and "a single image" in one.info["fallback"]
    np.testing.assert_array_equal(one.indices[0], np.argsort(-(q[:1].astype(np.float64) @ ref_desc.T.astype(np.float64))[0])[:3])
    # a log of unordered frames: stamps do not increase, so no run reaches 11 frames
    rng = np.random.default_rng(4)
    stamps = rng.permutation(40) * 100_000_000
    shuffled = _table(q, np.arange(40), stamps)
    labels, _gap = drive_runs(shuffled)
    assert np.bincount(labels).max() < 11
    res = match_tables(shuffled, ref, SequenceConfig(), k=2)
    assert not res.sequence.any() and res.info["sequence_queries"] == 0
    np.testing.assert_array_equal(res.indices[:, 0], _single_best(q, ref_desc))
    np.testing.assert_array_equal(res.window, 1)
    # the same frames in order are matched as a sequence
    ordered = match_tables(_table(q, np.arange(40), np.arange(40) * 100_000_000), ref, SequenceConfig(), k=2)
    assert ordered.sequence.all() and ordered.info["fallback"] is None
    # a gap in the stamps cuts the drive into runs; a run of 5 frames is matched frame by frame
    gap = np.arange(40) * 100_000_000 + np.where(np.arange(40) >= 35, 60_000_000_000, 0)
    cut = match_tables(_table(q, np.arange(40), gap), ref, SequenceConfig(), k=2)
    assert cut.sequence[:35].all() and not cut.sequence[35:].any() and cut.info["runs"] == 2
    assert "5 frame(s): its run of ordered frames is shorter than the window" in cut.info["fallback"]
    assert cut.info["fallback_reasons"] == {"short-run": 5}


def test_sequence_zero_is_single_frame_search(places: np.ndarray) -> None:
    ref = _unit(places)
    q = _query(places, _path())
    res = match_sequences(q, np.arange(len(q), dtype=float), ref, np.arange(N_PLACES, dtype=float),
                          SequenceConfig(length=0), k=4)
    sim = q.astype(np.float64) @ ref.astype(np.float64).T
    order = np.argsort(-sim, axis=1, kind="stable")[:, :4]
    np.testing.assert_array_equal(res.indices, order)
    # the score of a single frame is its contrast-normalised similarity z (a path of one pair), with
    # the statistics of an even sample of the map, and the confidence is its margin over the best
    # candidate of another place (outside one frame of the best), as for a sequence
    sample = np.unique(np.linspace(0, N_PLACES - 1, min(STAT_SAMPLE, N_PLACES)).astype(np.int64))
    mu, sd = sim[:, sample].mean(axis=1), sim[:, sample].std(axis=1)
    z = (sim - mu[:, None]) / sd[:, None]
    np.testing.assert_allclose(res.scores, np.take_along_axis(z, order, axis=1), atol=1e-4)
    assert not res.sequence.any() and res.info["fallback"].startswith("every frame matched frame by frame")
    assert set(res.fallback) == {"single"}
    other = np.abs(order - order[:, :1]) > 1  # candidates of another place
    second = np.argmax(other, axis=1)
    expect = z[np.arange(len(q)), order[:, 0]] - z[np.arange(len(q)), order[np.arange(len(q)), second]]
    found = other.any(axis=1)
    np.testing.assert_allclose(res.confidence[found], expect[found], atol=1e-4)


def test_two_topics_never_mix(places: np.ndarray) -> None:
    """Two cameras in the query are two drives; a map of two cameras keeps them apart."""
    ref_desc = _unit(places)
    t = np.arange(N_PLACES) * 100_000_000
    ref = DescriptorTable(topic=["/a"] * N_PLACES + ["/b"] * N_PLACES, frame_index=np.r_[np.arange(N_PLACES), np.arange(N_PLACES)],
                          log_time_ns=np.r_[t, t], stamp_ns=np.r_[t, t], descriptors=np.r_[ref_desc, ref_desc[::-1]],
                          meta=DescriptorMeta("test", {}, DIM))
    path = np.arange(100, 160)
    q = _query(places, path)
    inter = np.empty((2 * len(path), DIM), np.float32)  # interleaved rows of two topics, as a log holds them
    inter[0::2], inter[1::2] = q, q
    qt = DescriptorTable(topic=["/a", "/b"] * len(path), frame_index=np.arange(len(path)).repeat(2),
                         log_time_ns=10**18 + np.arange(len(path)).repeat(2) * 100_000_000,
                         stamp_ns=10**18 + np.arange(len(path)).repeat(2) * 100_000_000, descriptors=inter,
                         meta=DescriptorMeta("test", {}, DIM))
    res = match_tables(qt, ref, SequenceConfig(), k=1)
    assert res.sequence.all() and res.info["runs"] == 2
    best = res.indices[:, 0]
    assert np.all(best < N_PLACES)  # the map's /a frames are the places in order; /b holds them reversed
    assert _share_within(best[0::2], path, 1) >= 0.95 and _share_within(best[1::2], path, 1) >= 0.95


@pytest.mark.parametrize("kw, message", [
    ({"length": -1}, "length must be an integer >= 0"),
    ({"length": 2.5}, "length must be an integer"),
    ({"length": 0, "causal": True}, "causal needs a sequence"),
    ({"speeds": (3.0, 1.0)}, "0 <= min <= max"),
    ({"speeds": (-1.0, 2.0)}, "0 <= min <= max"),
    ({"candidates": 0}, "candidates must be an integer >= 1"),
    ({"coordinate": "metres"}, "coordinate must be one of"),
    ({"max_gap_s": 0}, "max_gap_s must be a number > 0"),
])
def test_bad_settings_are_config_errors(kw: dict, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        SequenceConfig(**kw)


def _moving(path: np.ndarray) -> np.ndarray:
    """The moving index of a drive from its true places: frames that stay at a place add nothing."""
    return np.cumsum(np.r_[0, (np.diff(path) != 0).astype(np.int64)])


def test_stops_are_left_out_of_both_drives(places: np.ndarray) -> None:
    """The map stands 40 frames at place 150, the query 60 frames at place 60 and 25 at 220. Along
    the moving index (the default) a standing query frame takes its stop's first frame's result and
    both drives are localized everywhere, also on a half map; along the frame index the half map
    loses the stretch where the query's stop meets the map's (measured 0.92 overall, 0.58 there)."""
    from dataclasses import replace

    rpath = np.r_[np.arange(0, 150), np.full(40, 150), np.arange(151, N_PLACES)]
    ref = _unit(places[rpath] + 0.02 * np.random.default_rng(5).normal(size=(len(rpath), DIM)))
    qpath = np.r_[np.arange(0, 60), np.full(60, 60), np.arange(61, 220), np.full(25, 220), np.arange(221, 290)]
    q = _query(places, qpath)
    half = np.arange(0, len(rpath), 2)
    ref_t = _table(ref[half], half, half * 100_000_000)
    ref_t = replace(ref_t, moving_index=_moving(rpath)[half])
    q_t = replace(_table(q, np.arange(len(qpath)), 10**18 + np.arange(len(qpath)) * 100_000_000),
                  moving_index=_moving(qpath))
    stops = match_tables(q_t, ref_t, SequenceConfig(), k=2)
    kept = match_tables(q_t, ref_t, SequenceConfig(stops=False), k=2)
    place = lambda res: rpath[half[res.indices[:, 0]]]  # noqa: E731
    standing = np.r_[False, np.diff(qpath) == 0]
    assert stops.info["stops"] and stops.info["standing_rows"] == int(standing.sum()) == 83
    assert not kept.info["stops"] and kept.info["standing_rows"] == 0
    assert _share_within(place(stops), qpath, 1) == 1.0
    assert _share_within(place(kept), qpath, 1) < 0.95
    # a standing frame has the result of its stop's first frame, with its own similarities
    first = np.maximum.accumulate(np.where(standing, 0, np.arange(len(qpath))))
    np.testing.assert_array_equal(stops.indices, stops.indices[first])
    np.testing.assert_array_equal(stops.margin, stops.margin[first])
    want = np.einsum("qd,qkd->qk", q.astype(np.float64), ref[half][stops.indices].astype(np.float64))
    found = stops.indices >= 0
    np.testing.assert_allclose(stops.similarities[found], want[found], atol=1e-5)
    assert np.all(stops.similarities[~found] == -np.inf)
    # without a moving index (a table written before it) the frame index is matched, as with stops=False
    plain = match_tables(replace(q_t, moving_index=None), replace(ref_t, moving_index=None), SequenceConfig(), k=2)
    np.testing.assert_array_equal(plain.indices, kept.indices)
    with pytest.raises(DescriptorError, match="one flag per query row"):
        match_sequences(q, np.arange(len(q), dtype=float), ref, np.arange(len(ref), dtype=float), standing=[True])


def test_the_metadata_says_why_each_frame_was_matched_alone(places: np.ndarray) -> None:
    """Truthful metadata: a one-frame map cannot hold a window (every row falls back, said so, no
    sequence query counted); a query standing still throughout falls back because it stood, not
    because its run was short; the window actually used is recorded."""
    q = _query(places, np.arange(40, 80))
    one_map = _table(_unit(places[50:51]), np.array([50]), np.array([5_000_000_000]))
    drive = _table(q, np.arange(40), np.arange(40) * 100_000_000)
    res = match_tables(drive, one_map, SequenceConfig(), k=1)
    assert not res.sequence.any() and set(res.fallback) == {"small-map"}
    assert res.info["sequence_queries"] == 0 and res.info["single_queries"] == 40
    assert res.info["fallback_reasons"] == {"small-map": 40} and "map spans fewer" in res.info["fallback"]
    # a query that stands at one place for 40 frames: its moving index never advances
    ref = _table(_unit(places), np.arange(N_PLACES), np.arange(N_PLACES) * 100_000_000)
    standing = _table(_query(places, np.full(40, 60)), np.arange(40), np.arange(40) * 100_000_000)
    standing.moving_index = np.zeros(40, np.int64)
    res = match_tables(standing, ref, SequenceConfig(), k=1)
    assert not res.sequence.any() and set(res.fallback) == {"standing"}
    assert res.info["standing_rows"] == 39 and res.info["fallback_reasons"] == {"standing": 40}
    # a moving query: every row a sequence, the window used recorded (a half map: twice the length)
    moving = match_tables(drive, ref, SequenceConfig(), k=1)
    assert moving.sequence.all() and moving.info["length_used"] == 10 and set(moving.fallback) == {""}
    half = match_tables(drive, ref, SequenceConfig(), k=1, ref_mask=np.arange(N_PLACES) % 2 == 0)
    assert half.info["length_used"] == 20 and half.window.max() == 40  # its 40 frames, cut at the run's ends


def test_the_map_is_cut_into_runs_like_the_query() -> None:
    """A map's runs: a sparse map (every 4th frame kept) is one run, a recording gap or a second
    camera starts another, and the matcher keeps them apart (their coordinates far from each other)."""
    rng = np.random.default_rng(2)
    desc = _unit(rng.normal(size=(50, DIM)))
    frames = np.arange(0, 200, 4)
    sparse = _table(desc, frames, frames * 100_000_000)
    assert drive_runs(sparse)[0].max() == 0
    gap_ns = frames * 100_000_000 + np.where(frames >= 100, 3_600_000_000_000, 0)  # an hour's gap
    labels, _ = drive_runs(_table(desc, frames, gap_ns))
    assert labels.tolist() == [0] * 25 + [1] * 25
    q = _table(desc[20:30], np.arange(10), np.arange(10) * 400_000_000)
    assert match_tables(q, _table(desc, frames, gap_ns), SequenceConfig(length=3), k=1).info["map_runs"] == 2
    assert match_tables(q, sparse, SequenceConfig(length=3), k=1).info["map_runs"] == 1


def test_a_window_cut_by_its_runs_end_slides_along_the_run_and_keeps_its_length() -> None:
    """``window_rows`` against windows built by hand: offline, each centre's window is the 2n+1
    consecutive rows of its run nearest to being centred on it (a window cut by the run's start
    or end slides along the run; a run shorter than the window is the whole run); causal, the n
    rows before the centre and the centre, never slid; without ``slide``, the centred window cut
    at the run's ends."""
    from memlog.matching.paths import _run_bounds, window_rows

    labels = np.array([0] * 30 + [1] * 7 + [2] * 25, dtype=np.int64)  # runs of 30, 7 (< 21) and 25 rows
    qc = np.arange(len(labels), dtype=np.float64)
    lo, hi = _run_bounds(labels, qc)
    n = 10
    centres = np.arange(len(labels), dtype=np.int64)
    for offs, slide in ((np.arange(-n, n + 1), True), (np.arange(-n, n + 1), False), (np.arange(-n, 1), True)):
        t, valid = window_rows(centres, offs, lo, hi, slide and offs[-1] > 0)
        for c in centres:
            a, b = int(lo[c]), int(hi[c])
            if offs[-1] == 0:  # causal
                want = list(range(max(a, c - n), c + 1))
            elif slide:
                start = min(max(c - n, a), max(a, b - (2 * n + 1)))
                want = list(range(start, min(b, start + 2 * n + 1)))
            else:
                want = list(range(max(a, c - n), min(b, c + n + 1)))
            got = t[c][valid[c]].tolist()
            assert got == want, (c, slide, got, want)
            assert c in got
    assert window_rows(centres, np.arange(-n, n + 1), lo, hi, True)[1].sum(axis=1)[:30].tolist() == [21] * 30

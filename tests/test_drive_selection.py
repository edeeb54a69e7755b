"""Maps of drives that stop, crawl and speed up (issue 20), and evaluate's side-by-side matching.

The drives are built from images: a camera slides along a textured strip (its position known in
pixels), stands still (the same view with sensor noise) and changes speed; the view vectors come
from :func:`memlog.scoring.scorer.view_vector` of each frame as ``memlog map`` computes them.
Expectations are in the strip's own coordinate (where the camera was), not in memlog's.
"""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from memlog.scoring.scorer import view_vector
from memlog.selection import ScoreTable, select
from memlog.selection.segment import SEGMENT_DEFAULTS
from memlog.selection.baselines import distance_uniform_mask, uniform_indices, uniform_mask
from memlog.selection.coordinates import count_cut
from tests.conftest import shared

W, H = 128, 64  # camera frame
NOISE = 2.0  # grey levels of sensor noise


def _strip(length: int, seed: int = 0) -> np.ndarray:
    """A grey strip with texture at several scales (what a camera sliding along sees)."""
    rng = np.random.default_rng(seed)
    img = np.zeros((H, length), np.float64)
    for sigma, amp in ((2, 10.0), (6, 20.0), (16, 30.0)):
        layer = cv2.GaussianBlur(rng.normal(size=(H, length)), (0, 0), sigma)
        img += amp * layer / layer.std()
    return np.clip(img + 128, 0, 255)


def _drive(strip: np.ndarray, x: np.ndarray, seed: int = 1) -> np.ndarray:
    """View vectors of the frames seen at strip positions ``x`` (pixels), each with its own noise."""
    rng = np.random.default_rng(seed)
    out = []
    for xi in x:
        # the crop at sub-pixel position xi (bilinear), as a camera sees a scene moving by less than a pixel
        crop = cv2.getRectSubPix(strip.astype(np.float32), (W, H), (float(xi) + (W - 1) / 2, (H - 1) / 2))
        f = crop.astype(np.float64) + rng.normal(0, NOISE, size=(H, W))
        out.append(view_vector(np.clip(f, 0, 255).astype(np.uint8)))
    return np.asarray(out, np.float32)


def _table(view: np.ndarray) -> ScoreTable:
    n = len(view)
    rng = np.random.default_rng(3)
    return ScoreTable(index=np.arange(n), t_ns=np.arange(n, dtype=np.int64) * 50_000_000,  # 20 Hz
                      ms=rng.uniform(0.6, 0.9, n), ss=np.ones(n), es=rng.uniform(0.4, 0.6, n), view=view)


def test_a_stop_gets_one_map_frame_and_the_moving_drive_the_rest() -> None:
    """Moving, standing 60 frames (sensor noise only), moving again: without positions the default
    segments by view change, the stop is found from the images and holds at most one map frame;
    segments by time (every k-th frame's share) spend several on it."""
    strip = _strip(1200)
    x = np.concatenate([np.arange(0, 300, 6.0), np.full(60, 300.0), np.arange(306, 606, 6.0)])
    stop = np.flatnonzero(x == 300.0)
    t = _table(_drive(strip, x))
    sel = select(t, "segment", keep_fraction=0.1)
    assert sel.info["by"] == "view"  # no positions: view change, chosen automatically
    assert sel.info["still_frames"] == len(stop) - 1  # the frames after the first of the stop
    kept = sel.kept_indices
    assert len(kept) == round(0.1 * len(x)) and np.isin(kept, stop).sum() <= 1
    # the map covers the moving drive evenly: no gap between kept places above twice the mean
    gaps = np.diff(np.unique(x[kept]))
    assert gaps.max() <= 2 * (x[-1] - x[0]) / len(kept), gaps
    by_time = select(t, "segment", by="time", keep_fraction=0.1, still_distance=0.0)
    assert np.isin(by_time.kept_indices, stop).sum() >= 3  # what a map that ignores the stop does


def test_stops_are_found_from_the_images_not_from_time() -> None:
    """A slow crawl (1 px per frame) is not a stop; a standing camera with sensor noise is."""
    strip = _strip(600)
    x = np.concatenate([np.arange(0, 100, 1.0), np.full(30, 100.0), np.arange(101, 201, 1.0)])
    from memlog.scoring.motion import still_rows

    still = still_rows(_drive(strip, x), SEGMENT_DEFAULTS.still_distance)
    want = np.zeros(len(x), bool)
    want[np.flatnonzero(x == 100.0)[1:]] = True
    assert still.tolist() == want.tolist()


@pytest.mark.parametrize("px_per_frame", [0.05, 0.1, 0.2])
def test_a_crawl_below_the_noise_per_frame_is_drive_not_a_stop(px_per_frame: float) -> None:
    """A camera crawling a fraction of a pixel per frame: each step's view change is below the
    still distance (what a frame-to-frame test would call a stop for the whole crawl), yet it
    travels 20-40 px. Stops are measured from the stop's first frame, so the crawl's moving index
    advances along it: at least once per 2 px travelled, evenly in the strip coordinate, while a
    60-frame stop of sensor noise only, on the same drive, keeps one value."""
    from memlog.scoring.scorer import view_steps
    from memlog.scoring.motion import moving_index, still_rows

    strip = _strip(900)
    crawl = 100.0 + np.arange(200) * px_per_frame
    x = np.concatenate([np.arange(0, 100, 4.0), crawl, np.full(60, crawl[-1] + 4.0),
                        crawl[-1] + 8.0 + np.arange(0, 100, 4.0)])
    view = _drive(strip, x)
    in_crawl = np.flatnonzero((x >= 100.0) & (x <= crawl[-1]))[1:]
    assert (view_steps(view)[in_crawl] < SEGMENT_DEFAULTS.still_distance).mean() > 0.5  # steps below the noise
    mi = moving_index(np.arange(len(x)), still_rows(view))
    moves = np.flatnonzero(np.diff(mi[in_crawl]) > 0)
    travelled = crawl[-1] - crawl[0]
    assert len(moves) >= travelled / 2.0, (len(moves), travelled)
    # evenly: no stretch of the crawl longer than 4 px without a step of the moving index
    assert np.diff(np.r_[0, moves, len(in_crawl) - 1]).max() * px_per_frame <= 4.0
    stop = np.flatnonzero(x == crawl[-1] + 4.0)
    assert len(np.unique(mi[stop])) == 1


@pytest.mark.parametrize("px_per_frame", [0.05, 0.1, 0.2])
def test_a_crawl_below_the_noise_covers_as_much_view_change_as_driving_that_stretch(px_per_frame: float) -> None:
    """The view-change coordinate of a crawl whose every step is below the noise: each frame that
    moves after standing counts its drift from the stop's first frame, so 20 px crawled add as much
    view change as the same 20 px driven at 0.5 px per frame (every frame moving; within 25 %),
    where counting only the last step gave about half."""
    from memlog.selection.segment import SegmentConfig, cut_segments

    strip = _strip(600)

    def view_change(px: float) -> float:
        x = 100.0 + np.arange(round(20 / px) + 1) * px
        _seg, _coord, info = cut_segments(_table(_drive(strip, x)), SegmentConfig(by="view", keep_fraction=0.1))
        return float(info["view_change"])

    driven, crawled = view_change(0.5), view_change(px_per_frame)
    assert abs(crawled / driven - 1.0) <= 0.25, (crawled, driven)


def test_moving_index_counts_only_the_frames_that_moved() -> None:
    """The frame index minus the frames spent standing, from the images: a strip drive read with a
    stride of 2 (frame indices 0, 2, 4, ...) with two stops; the expectation counts, in the strip
    coordinate, the frames whose position equals their predecessor's (each stands for 2 frames)."""
    from memlog.errors import SelectionError
    from memlog.scoring.motion import moving_index, still_rows

    strip = _strip(900)
    x = np.concatenate([np.arange(0, 120, 4.0), np.full(15, 120.0), np.arange(124, 300, 4.0), np.full(9, 300.0),
                        np.arange(302, 400, 2.0)])
    index = np.arange(len(x)) * 2
    still = still_rows(_drive(strip, x))
    repeat = np.r_[False, x[1:] == x[:-1]]
    assert still.tolist() == repeat.tolist()
    want = index - 2 * np.cumsum(repeat)
    np.testing.assert_array_equal(moving_index(index, still), want)
    assert len(np.unique(want[x == 120.0])) == 1 and len(np.unique(want[x == 300.0])) == 1  # a stop: one value
    np.testing.assert_array_equal(moving_index([0, 2, 4, 6, 8], [False, False, True, True, False]), [0, 2, 2, 2, 4])
    assert not still_rows(_drive(strip, x), still_distance=0.0).any()
    with pytest.raises(SelectionError, match="5 frame indices but 4 still flags"):
        moving_index(np.arange(5), np.zeros(4, bool))


def test_the_map_and_a_described_query_carry_the_moving_index(tmp_path, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """A log whose frame 1 repeats three times (a stop, identical images): the query's descriptor
    table and the map's carry the frame index with the stop left out (what sequence matching runs
    along, tested in ``test_sequence``)."""
    from memlog.descriptors.extract import describe_log
    from memlog.descriptors.registry import make_describer
    from memlog.outputs.descriptor_table import read_descriptors
    from memlog.selection.config import SelectionConfig
    from memlog.scoring.motion import stop_rule
    from memlog.selection.segment import SEGMENT_DEFAULTS
    from memlog.steps.map import MapConfig, make_map
    from tests.conftest import repeating_log
    from tests.stand_in import use_stand_in

    use_stand_in(monkeypatch)
    log = tmp_path / "stop.mcap"
    repeating_log(log)  # source frames 0, 1, 1, 1, 2, 3, 0, 1
    want = [0, 1, 1, 1, 2, 3, 4, 5]
    t, _report = describe_log(log, make_describer("thumbnail"))
    assert t.moving_index is not None and t.moving_index.tolist() == want
    res = make_map(log, tmp_path / "m.mcap", MapConfig(select=SelectionConfig(keep_fraction=0.75),
                                                        descriptor="thumbnail"))
    assert res.descriptors is not None
    m = read_descriptors(res.descriptors)
    assert m.moving_index is not None and len(m) >= 4
    assert m.moving_index.tolist() == [want[i] for i in m.frame_index]
    assert sum(1 for i in m.frame_index if 1 <= i <= 3) <= 1  # the stop holds one map frame
    # both record how their stops were found; with still_distance 0 the map has none, and says so
    assert t.extra["stops"] == m.extra["stops"] == stop_rule(SEGMENT_DEFAULTS.still_distance)
    res0 = make_map(log, tmp_path / "m0.mcap", MapConfig(select=SelectionConfig(keep_fraction=0.75, still_distance=0.0),
                                                          descriptor="thumbnail"))
    assert res0.descriptors is not None
    m0 = read_descriptors(res0.descriptors)
    assert m0.extra["stops"] == stop_rule(0.0) and m0.moving_index is not None
    # (frames after the stop are kept: with the default rule their moving index would be 2 less)
    assert m0.moving_index.tolist() == m0.frame_index.tolist() and max(m0.frame_index) > 3


def test_map_says_why_it_keeps_fewer_frames_than_keep_fraction_asks(tmp_path) -> None:  # type: ignore[no-untyped-def]
    """Source frames 0, 1, 1, 1, 2, 3, 0, 1: frame 1 stands still for two frames, so at most 6 of
    the 8 segments that --keep-fraction 1 asks for can hold a frame; the CLI says so, with the
    count of standing frames, and says nothing when every segment asked holds one."""
    import re
    import subprocess
    import sys

    from tests.conftest import repeating_log

    log = tmp_path / "stop.mcap"
    repeating_log(log)

    def run(fraction: str) -> str:
        r = subprocess.run([sys.executable, "-m", "memlog", "map", str(log), "-o", str(tmp_path / f"m{fraction}.mcap"),
                            "--keep-fraction", fraction, "--descriptor", "none"], capture_output=True, text=True)
        assert r.returncode == 0, r.stderr
        return r.stderr

    said = re.search(r"fewer frames than --keep-fraction asks: (\d+) of the (\d+) segments hold a frame "
                     r"\((\d+) frame\(s\) stood still", run("1"))
    assert said is not None
    made, asked, still = map(int, said.groups())
    assert asked == 8 and still == 2 and made <= 6
    assert "fewer frames than --keep-fraction asks" not in run("0.25")  # 2 segments, both hold frames


def test_a_crawl_gets_fewer_map_frames_than_every_kth_frame_gives_it() -> None:
    """Creeping at 0.5 px per frame, then driving at 8 px per frame: a view-change map puts fewer
    frames on the crawl than every k-th frame does (which follows the frame count). (The measure
    saturates: steps of 1 px and more count alike, see ``VIEW_STEP_CAP``.)"""
    strip = _strip(1500)
    x = np.concatenate([np.arange(0, 50, 0.5), np.arange(50, 850, 8.0)])  # 100 crawl, 100 fast frames
    t = _table(_drive(strip, x))
    k = 20
    sel = select(t, "segment", keep_fraction=k / len(x))
    assert sel.info["still_frames"] == 0  # a crawl is not a stop
    on_crawl = int((x[sel.kept_indices] < 50).sum())
    every_kth = int((x[uniform_mask(len(x), k)] < 50).sum())
    assert every_kth == k // 2 and on_crawl <= k // 4, (on_crawl, every_kth)


def test_distance_uniform_mask_keeps_k_frames_nearest_the_middles_of_equal_parts() -> None:
    """Against a brute-force search over the travelled distance (variable speed, a stop, a NaN fix,
    a fast stretch whose frames are further apart than a part): the equal parts a map of K frames
    is cut into, of which K hold a frame, and the frame nearest each held part's middle."""
    rng = np.random.default_rng(0)
    step = np.concatenate([rng.uniform(0.5, 2.0, 40), np.zeros(20), rng.uniform(2.0, 4.0, 30),
                           np.full(10, 12.0)])
    pos = np.zeros((len(step), 2))
    pos[:, 0] = np.cumsum(step)
    pos[:, 1] = 0.3 * np.sin(pos[:, 0] / 7)
    pos[55] = np.nan  # an unknown fix carries the distance before it
    s = np.zeros(len(pos))
    last = 0.0
    prev = pos[0]
    for i in range(1, len(pos)):
        if np.all(np.isfinite(pos[i])):
            last += float(np.linalg.norm(pos[i] - prev))
            prev = pos[i]
        s[i] = last
    places = len(set(s.tolist()))
    for k in (5, 17, 33, 60, places, places + 10):
        mask = distance_uniform_mask(pos, k)
        assert mask is not None
        want_k = min(k, places)
        parts = count_cut(s, k)  # checked here by counting: K parts held, one part fewer holds fewer
        part = [min(int(x * parts / s[-1]), parts - 1) for x in s]
        assert len(set(part)) >= want_k
        assert parts == k or len({min(int(x * (parts - 1) / s[-1]), parts - 2) for x in s}) < want_k
        want = []
        for p in sorted(set(part)):
            rows = [i for i in range(len(s)) if part[i] == p]
            d = [abs(s[i] - (p + 0.5) * s[-1] / parts) for i in rows]
            want.append(rows[d.index(min(d))])  # the earliest of the nearest
        if len(want) > want_k:
            want = [want[i] for i in uniform_indices(len(want), want_k)]
        assert np.flatnonzero(mask).tolist() == want, k
        assert mask.sum() == want_k, k  # the size asked, through the fast stretch
        if k >= 60:  # parts shorter than the fast stretch's 12 m steps: every one of its frames kept
            assert mask[-10:].all(), k
    assert distance_uniform_mask(np.ones((10, 2)), 3) is None  # no travelled distance


@pytest.fixture(scope="module")
def nordland_eval(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict, dict]:
    """evaluate summer -> winter (first 200 places, stand-in ResMem) with sequences (the default)
    and with single frames (``--sequence 0``), each with ``--compare-exact`` (the exact selection's
    column beside the map's: opt-in, it scores every reference frame's memorability)."""
    from memlog.matching import SequenceConfig
    from memlog.selection.config import SelectionConfig
    from memlog.steps.evaluate import EvaluateConfig, evaluate
    from tests.stand_in import use_stand_in

    d = tmp_path_factory.mktemp("nordland-eval")
    out = []
    with pytest.MonkeyPatch.context() as mp:
        use_stand_in(mp)
        for name, seq in (("seq", SequenceConfig()), ("single", SequenceConfig(length=0))):
            cfg = EvaluateConfig(select=SelectionConfig(keep_fraction=0.5), max_frames=200, seeds=3, report=False,
                                 sequence=seq, compare_exact=True)
            res = evaluate(shared("nordland_dev_summer.mcap"), shared("nordland_dev_winter.mcap"), d / name, cfg,
                           truth=shared("nordland_dev_truth.json"))
            out.append(json.loads((d / name / "results.json").read_text()))
            assert out[-1]["memorable"]["recall@1"] == res.results["memorable"]["recall@1"]
    return out[0], out[1]


def test_evaluate_reports_sequence_and_single_frames_side_by_side(nordland_eval: tuple[dict, dict]) -> None:
    """Each map's single-frame row is what a single-frame evaluation gives, under both protocols;
    sequences localize the real winter drive far better than single frames."""
    seq, single = nordland_eval
    assert seq["matching"]["matching"] == "sequence" and single["matching"]["matching"] == "single frame"
    for name in ("full", "memorable", "memorable_exact", "uniform", "random"):
        assert "single_frame" not in single[name]
        for key in ("recall@1", "auc"):
            assert seq[name]["single_frame"][key] == pytest.approx(single[name][key], abs=1e-9), (name, key)
            assert seq[name]["single_frame"]["paper_protocol"][key] == pytest.approx(
                single[name]["paper_protocol"][key], abs=1e-9), (name, key)
    assert seq["full"]["recall@1"] > single["full"]["recall@1"] + 0.2, (seq["full"], single["full"])
    # the memorable map evaluated is the map written (default --candidates 1), the exact selection beside it
    assert seq["memorable"]["candidates"] == 1 and "kept_indices" in seq["memorable_exact"]


def test_one_candidate_per_segment_keeps_the_map_evenly_spaced_where_scores_hardly_differ() -> None:
    """The default shortlist (one candidate per segment) takes, among the frames within
    ``centre_tolerance`` of the segment's best cheap bound, the one nearest the segment's middle:
    a camera moving at constant speed past a scene of even texture (ES within +-1 %) gets a map
    spaced evenly along the strip; the best bound alone (tolerance 0) picks by noise in ES and
    leaves irregular gaps. A frame whose bound is clearly better still wins its segment."""
    strip = _strip(1600, seed=5)
    x = np.arange(0, 1200, 4.0)  # 300 frames, 4 px apart
    view = _drive(strip, x, seed=6)
    n = len(x)
    rng = np.random.default_rng(7)
    es = rng.uniform(0.495, 0.505, n)
    t = ScoreTable(index=np.arange(n), t_ns=np.arange(n, dtype=np.int64) * 50_000_000, ms=np.full(n, np.nan),
                   ss=np.ones(n), es=es, view=view)
    gaps = {}
    for tol in (SEGMENT_DEFAULTS.centre_tolerance, 0.0):
        sel = select(t, "segment", keep_fraction=0.1, shortlist=1, centre_tolerance=tol)
        kept = sel.kept_indices
        assert len(kept) == 30
        gaps[tol] = np.diff(x[kept])
    even = gaps[SEGMENT_DEFAULTS.centre_tolerance]
    assert even.max() <= 1.6 * even.mean() and even.min() >= 0.4 * even.mean()
    assert gaps[0.0].max() > even.max() and gaps[0.0].std() > 1.5 * even.std()
    # a frame 10 % better than its neighbours (beyond the 3 % tolerance) is kept wherever it lies
    sel = select(t, "segment", keep_fraction=0.1, shortlist=1)
    seg = sel.segment_id
    rows = np.flatnonzero(seg == 12)
    es2 = es.copy()
    es2[rows[0]] = 0.5 * 1.1 ** 3  # (SS^2 ES)^(1/3) 10 % above the rest
    t2 = ScoreTable(index=t.index, t_ns=t.t_ns, ms=t.ms, ss=t.ss, es=es2, view=view)
    kept2 = select(t2, "segment", keep_fraction=0.1, shortlist=1).kept_indices
    assert rows[0] in kept2 and not np.isin(sel.kept_indices[np.isin(sel.kept_indices, rows)], kept2).any()


def test_centre_tolerance_is_checked() -> None:
    from memlog.errors import ConfigError
    from memlog.selection.config import SelectionConfig

    for bad in (-0.1, 1.5, float("nan")):
        with pytest.raises(ConfigError, match="centre_tolerance"):
            SelectionConfig(keep_fraction=0.25, centre_tolerance=bad)


def test_the_default_size_follows_the_drives_view_change_not_its_frame_count() -> None:
    """Without a size, a map keeps one frame per ``VIEW_STEP_CAP`` of the drive's view change:
    the number of segments is the view change summed here by hand (each step's chord, capped)
    over ``VIEW_STEP_CAP``; the same drive with a 60-frame stop in the middle gets no more
    segments (a stop adds no view change), where a fixed fraction would give it 15 more."""
    from memlog.selection.coordinates import VIEW_STEP_CAP

    strip = _strip(1400)
    moving = np.arange(0, 600, 6.0)
    t = _table(_drive(strip, moving))
    v = t.view.astype(np.float64)
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    chord = np.minimum(np.sqrt(2.0 * np.clip(1.0 - np.sum(v[1:] * v[:-1], axis=1), 0.0, None)), VIEW_STEP_CAP)
    sel = select(t, "segment")
    assert sel.info["by"] == "view" and sel.info["spacing_view"] == VIEW_STEP_CAP
    np.testing.assert_allclose(sel.info["view_change"], chord.sum(), rtol=1e-5)
    assert sel.info["n_bins"] == int(np.ceil(chord.sum() / VIEW_STEP_CAP - 1e-9))
    assert len(sel.kept_indices) == sel.info["n_segments"]
    with_stop = np.concatenate([moving[:50], np.full(60, moving[49]), moving[50:]])
    ts = _table(_drive(strip, with_stop))
    stopped = select(ts, "segment")
    assert stopped.info["still_frames"] == 60
    assert abs(stopped.info["n_bins"] - sel.info["n_bins"]) <= 1
    assert select(ts, "segment", keep_fraction=0.25).info["n_bins"] - select(t, "segment", keep_fraction=0.25).info[
        "n_bins"] == 15
    # a larger spacing, fewer frames; a table without view vectors falls back to a quarter, and says so
    assert select(t, "segment", spacing_view=2 * VIEW_STEP_CAP).info["n_bins"] == int(
        np.ceil(chord.sum() / (2 * VIEW_STEP_CAP) - 1e-9))
    bare = ScoreTable(index=t.index, t_ns=t.t_ns, ms=t.ms, ss=t.ss, es=t.es)
    fallback = select(bare, "segment")
    assert fallback.info["n_bins"] == 25 and "no view vectors" in fallback.info["size_note"]

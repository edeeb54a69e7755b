"""The fast paths of ``memlog map`` (issue 32) keep what the slow paths give.

* staged staticity: :func:`~memlog.selection.staged.detect_in_segment` against selection from every
  score on random segments (ties, dynamic frames, frames failing the minimums, gaps), and the map
  staged vs unstaged (the detector on every frame) on the shared logs: the same kept frames, the
  same scores where the detector ran, ``ss``/``es`` null where it did not;
* the scorer's shortcuts: ES of a frame without dynamic objects taken from its entropy bound,
  the crop count without the 1135 x 1135 product;
* ``evaluate`` scores the reference as the map does (no ResMem, no detector on every frame)
  unless ``--compare-exact``;
* JPEG decoding at a reduced DCT scale; progress ETAs that leave the wait for the first item out.

No timing is asserted here (``benchmarks/speed_table.py`` measures).
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from memlog.models.resmem import crop_weights
from memlog.outputs.annotated import read_scores
from memlog.scoring.config import ScoreConfig
from memlog.scoring.scorer import Scorer, crops_needed, resize_frame
from memlog.selection import ScoreTable
from memlog.selection.config import SelectionConfig
from memlog.selection.segment import SegmentConfig, cut_segments, select_segments, upper_bounds
from memlog.selection.staged import detect_in_segment, staticity_mode
from memlog.steps.map import MapConfig, make_map
from tests.conftest import shared

STROMOVKA = "stromovka_autumn.mcap"


# -- the staged detector against selection from every score -----------------------------------------
def _random_table(rng: np.random.Generator, n: int, ties: bool) -> tuple[ScoreTable, np.ndarray]:
    """A drive of ``n`` frames: true SS/ES (6 decimals) and each frame's ES were it all static."""
    es_static = np.round(rng.uniform(0.2, 0.8, n), 6)
    if ties:  # repeated frames: equal bounds and scores
        es_static = np.round(np.repeat(es_static[: -(-n // 3)], 3)[:n], 6)
    dynamic = rng.random(n) < 0.35
    ss = np.where(dynamic, np.round(rng.uniform(0.02, 1.0, n), 6), 1.0)
    es = np.where(dynamic, np.round(es_static * rng.uniform(0.3, 1.0, n), 6), es_static)
    if ties:
        ss[1::3], es[1::3] = ss[0::3][: len(ss[1::3])], es[0::3][: len(es[1::3])]
    t = np.cumsum(rng.integers(1, 4, n)) * 10**8
    view = rng.normal(size=(n, 16)).astype(np.float32)
    if ties:  # stops: runs of frames with one view, which lie at one coordinate of their segment
        for a in range(0, n, 9):
            view[a:a + int(rng.integers(3, 9))] = view[a]
    view /= np.linalg.norm(view, axis=1, keepdims=True)
    table = ScoreTable(index=np.arange(n), t_ns=t, ms=np.zeros(n), ss=ss, es=es, view=view)
    return table, es_static


@pytest.mark.parametrize("seed", range(60))
def test_staged_detector_keeps_the_frames_every_score_keeps(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n = int(rng.integers(5, 60))
    table, es_static = _random_table(rng, n, ties=seed % 4 == 0)
    by = ["count", "time", "view"][seed % 3]
    tol = [0.03, 0.0, 0.2][seed % 3 if seed % 5 else 2]
    weights = (0.0, 1.0, 1.0) if seed % 7 == 3 else (1.0, 1.0, 1.0)  # MS weight 0: best by SS and ES
    min_ss = [0.1, 0.5, 0.95][seed % 3]  # 0.95: many frames fail it, some segments are gaps
    cfg = SegmentConfig(keep_fraction=float(rng.choice([0.1, 0.25, 0.5])), by=by, shortlist=1, min_ss=min_ss,
                        centre_tolerance=tol, weights=weights)
    want = select_segments(table, cfg)
    seg, coord, info = cut_segments(table, cfg)
    if seed % 4 == 0 and by != "count":
        assert info.get("still_frames", 0) > 0
    mode = staticity_mode(weights, 0.0, 1, es_bounded=True)
    assert mode == ("best" if weights[0] == 0 else "shortlist")
    ss, es = np.full(n, np.nan), np.full(n, np.nan)
    detected = 0
    for sid in np.unique(seg):
        rows = np.flatnonzero(seg == sid)
        got = detect_in_segment(
            len(rows), es_static[rows].tolist(), lambda r, rows=rows: (table.ss[rows[r]], table.es[rows[r]]),
            mode=mode, weights=weights, min_ss=min_ss, coord=None if coord is None else coord[rows].tolist(),
            centre_tolerance=tol)
        for r in got:
            ss[rows[r]], es[rows[r]] = table.ss[rows[r]], table.es[rows[r]]
        detected += len(got)
        if not any(table.ss[rows] >= min_ss):  # a gap: every frame seen, so its reasons are exact
            assert len(got) == len(rows)
    staged = ScoreTable(index=table.index, t_ns=table.t_ns, ms=table.ms, ss=ss, es=es, view=table.view)
    got_sel = select_segments(staged, cfg)
    assert got_sel.kept_indices.tolist() == want.kept_indices.tolist()
    assert [g.to_dict() for g in got_sel.gaps] == [g.to_dict() for g in want.gaps]
    unknown = np.isnan(ss)
    # every frame not detected lies in a segment that keeps a frame, and is dropped for it
    assert all(r == "segment" for r, u in zip(got_sel.reason, unknown) if u)
    assert all(want.reason[i] == got_sel.reason[i] for i in np.flatnonzero(~unknown))


def test_staged_detector_runs_once_per_segment_when_the_best_bound_is_static() -> None:
    """Frames without dynamic objects: the best bound is the leader; with the centre rule the
    frame nearest the middle within 3 % of it is the candidate: at most two detector runs."""
    es_static = [0.50, 0.60, 0.59, 0.40, 0.30]
    seen: list[int] = []

    def detect(r: int) -> tuple[float, float]:
        seen.append(r)
        return 1.0, es_static[r]

    coord = [3.05, 3.25, 3.45, 3.65, 3.85]  # middle 3.5: row 2 nearest, within 3 % (of the cube root)
    detect_in_segment(5, es_static, detect, mode="shortlist", coord=coord, centre_tolerance=0.03)
    assert seen == [1, 2]
    seen.clear()
    detect_in_segment(5, es_static, detect, mode="shortlist", coord=coord, centre_tolerance=0.0)
    assert seen == [1]
    seen.clear()
    detect_in_segment(5, es_static, detect, mode="every")
    assert seen == [0, 1, 2, 3, 4]


def test_staticity_mode() -> None:
    assert staticity_mode((1.0, 1.0, 1.0), 0.0, 1, True) == "shortlist"
    assert staticity_mode((1.0, 1.0, 1.0), 0.0, 2, True) == "every"
    assert staticity_mode((1.0, 1.0, 1.0), 0.0, None, True) == "every"
    assert staticity_mode((0.0, 1.0, 1.0), 0.0, None, True) == "best"
    assert staticity_mode((1.0, 1.0, 1.0), 0.0, 1, False) == "every"  # ES / SS can exceed the bound


def test_the_bound_bounds_the_upper_bound() -> None:
    rng = np.random.default_rng(1)
    es_static = np.round(rng.uniform(0, 1, 2000), 6)
    ss = np.round(rng.uniform(0, 1, 2000), 6)
    es = np.round(es_static * rng.uniform(0, 1, 2000), 6)
    from memlog.selection.segment import geometric_score

    for w in ((1.0, 1.0, 1.0), (2.0, 1.0, 3.0), (1.0, 0.0, 1.0)):
        assert np.all(upper_bounds(ss, es, w) <= geometric_score(np.ones(2000), np.ones(2000), es_static, w))


# -- the scorer's shortcuts ---------------------------------------------------------------------------
def test_crops_needed_is_the_count_of_positive_crop_weights() -> None:
    rng = np.random.default_rng(3)
    maps = [np.ones((1135, 1135), np.uint8), np.zeros((1135, 1135), np.uint8)]
    for _ in range(6):
        s = np.ones((1135, 1135), np.uint8)
        x0, y0 = rng.integers(0, 1000, 2)
        s[y0:y0 + int(rng.integers(50, 1135)), x0:x0 + int(rng.integers(50, 1135))] = 0
        maps.append(s)
    for s in maps:
        assert crops_needed(s) == int(np.count_nonzero(crop_weights(s) > 0))


class _Boxes:
    """A staticity stage that marks a fixed box dynamic (or nothing)."""

    def __init__(self, box: tuple[int, int, int, int] | None) -> None:
        self.box = box

    def __call__(self, f: np.ndarray) -> tuple[np.ndarray, float, list[Any]]:
        s = np.ones(f.shape[:2], np.uint8)
        if self.box is not None:
            x0, y0, x1, y1 = self.box
            s[y0:y1, x0:x1] = 0
        return s, float(s.mean()), []


@pytest.mark.parametrize("box", [None, (100, 200, 700, 900)])
def test_es_from_the_entropy_bound_is_the_es_computed_again(box: tuple[int, int, int, int] | None) -> None:
    """``cheap(es_static=...)`` gives bit for bit the ES of ``cheap()``: the bound itself for a frame
    without dynamic pixels, the masked entropy computed again otherwise."""
    from memlog.io.open import open_log

    with open_log(shared(STROMOVKA)) as r:
        bgr = next(iter(r.frames())).decode_bgr()
    for normalize in ("all", "static"):
        sc = Scorer(ScoreConfig(all_scores=True, normalize=normalize), staticity=_Boxes(box))  # type: ignore[arg-type]
        b = sc.entropy_bound(bgr)
        plain = sc.cheap(bgr, keep_maps=False)
        fast = sc.cheap(bgr, keep_maps=False, es_static=b.es_static)
        assert fast.es == plain.es and fast.ss == plain.ss
        assert (plain.es == b.es_static) == (box is None)
        assert plain.es is not None and plain.es <= b.es_static + 1e-15


# -- the map, staged vs unstaged, on shared logs ------------------------------------------------------
class _Memo(Scorer):
    """The real detector, run once per distinct frame for the whole module (both paths see the
    same boxes, and the tests stay affordable), the stand-in ResMem, and the real entropy, or with
    ``proxy_entropy`` a cheap stand-in for it (a smooth map of local contrast in 0..8 bits) for the
    runs that vary the settings: the staged logic sees the same kind of numbers either way."""

    det: dict[bytes, Any] = {}

    def __init__(self, config: ScoreConfig, proxy_entropy: bool) -> None:
        from tests.stand_in import stand_in_scorer

        super().__init__(config, memorability=stand_in_scorer(config).memorability)
        self.proxy = proxy_entropy
        real = self.staticity
        det = self.det

        def staticity(f: np.ndarray) -> Any:
            key = hashlib.blake2b(f.tobytes(), digest_size=16).digest()
            if key not in det:
                det[key] = real(f)
            s, ss, dets = det[key]
            return s.copy(), ss, list(dets)

        self._stat = staticity

    def _entropy_map(self, gray: np.ndarray) -> np.ndarray:
        if not self.proxy:
            return super()._entropy_map(gray)
        lap = np.abs(cv2.Laplacian(gray, cv2.CV_64F, ksize=3))
        return np.asarray(8.0 * np.tanh(cv2.blur(lap, (11, 11)) / 40.0), np.float64)


def _use_memo(monkeypatch: pytest.MonkeyPatch, proxy_entropy: bool) -> dict[str, int]:
    """Score with :class:`_Memo` in this process; counts the detector's runs."""
    from memlog.steps import map_scoring
    from memlog.steps.parallel import cached

    calls = {"detector": 0}
    real_cheap = Scorer.cheap

    def cheap(self: Scorer, *a: Any, **kw: Any) -> Any:
        calls["detector"] += 1
        return real_cheap(self, *a, **kw)

    monkeypatch.setattr(Scorer, "cheap", cheap)
    monkeypatch.setattr(map_scoring, "_scorer_for",
                        lambda config: cached(("memo", proxy_entropy, config), lambda: _Memo(config, proxy_entropy)))
    return calls


def _kept(res: Any) -> dict[str, list[int]]:
    return {t: s.kept_indices.tolist() for t, s in res.selections.items()}


def _records(path: Path) -> dict[str, dict[int, dict[str, Any]]]:
    return {t: {r["frame_index"]: r for r in recs} for t, recs in read_scores(path).items()}


def _same_map(log: Path, cfg: MapConfig, tmp_path: Path, calls: dict[str, int], tag: str) -> int:
    """The map staged and unstaged: the same kept frames, the same scores where the detector ran
    (null elsewhere, and those frames dropped for their segment), the same gaps; returns the
    detector runs the staged map saved."""
    calls["detector"] = 0
    staged = make_map(log, tmp_path / f"staged{tag}.mcap", cfg)
    n_staged = calls["detector"]
    calls["detector"] = 0
    every = make_map(log, tmp_path / f"every{tag}.mcap", cfg, stage_staticity=False)
    n_every = calls["detector"]
    assert _kept(staged) == _kept(every), cfg.select
    for t, s in staged.selections.items():
        table, full = staged.tables[t], every.tables[t]
        assert s.index.tolist() == every.selections[t].index.tolist()
        known = np.isfinite(table.ss)
        assert np.array_equal(table.ss[known], full.ss[known]) and np.array_equal(table.es[known], full.es[known])
        assert np.isnan(table.es[~known]).all()
        assert all(r == "segment" for r, k in zip(s.reason, known) if not k)
        assert [g.to_dict() for g in s.gaps] == [g.to_dict() for g in every.selections[t].gaps]
    # the kept frames' records (the map log holds them) are the unstaged map's, timing aside
    a, b = _records(tmp_path / f"staged{tag}.mcap"), _records(tmp_path / f"every{tag}.mcap")
    assert {t: sorted(r) for t, r in a.items()} == {t: sorted(r) for t, r in b.items()}
    for t in a:
        for idx, r in a[t].items():
            assert {**r, "timing_ms": None} == {**b[t][idx], "timing_ms": None}, (t, idx)
    return n_every - n_staged


@pytest.mark.parametrize("name,stride", [(STROMOVKA, 1), ("stromovka_winter.mcap", 2), ("euroc_micro_ros1.bag", 2),
                                         ("euroc_micro_ros2_db3", 3)])
def test_staged_staticity_keeps_the_frames_of_the_unstaged_map(name: str, stride: int, tmp_path: Path,
                                                               monkeypatch: pytest.MonkeyPatch) -> None:
    """``memlog map`` with its defaults (real detector, real entropy) runs the detector on part of
    the frames only and keeps exactly the frames it keeps with the detector on every frame."""
    calls = _use_memo(monkeypatch, proxy_entropy=False)
    saved = _same_map(shared(name), MapConfig(descriptor=None, stride=stride), tmp_path, calls, "")
    assert saved > 0


def test_staged_staticity_keeps_the_frames_of_the_unstaged_map_in_other_settings(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The same with other segment settings (a stand-in entropy keeps this affordable): keep
    fractions, no centre rule, MS not counted (the best frame by SS and ES), near-duplicates, a
    staticity minimum that drops frames, and the settings that run the detector on every frame
    (two candidates, ES by the static pixels)."""
    calls = _use_memo(monkeypatch, proxy_entropy=True)
    log = shared(STROMOVKA)
    settings = [MapConfig(), MapConfig(select=SelectionConfig(keep_fraction=0.5)),
                MapConfig(select=SelectionConfig(keep_fraction=0.1, centre_tolerance=0.0)),
                MapConfig(select=SelectionConfig(weights=(0.0, 1.0, 1.0), keep_fraction=0.5)),
                MapConfig(select=SelectionConfig(keep_fraction=0.4, dedup=0.05)),
                MapConfig(select=SelectionConfig(min_ss=0.97, keep_fraction=0.5)),
                MapConfig(candidates=2), MapConfig(score=ScoreConfig(normalize="static"))]
    saved = []
    for i, cfg in enumerate(settings):
        cfg = MapConfig(score=cfg.score, select=cfg.select, candidates=cfg.candidates, descriptor=None, stride=2)
        saved.append(_same_map(log, cfg, tmp_path, calls, str(i)))
    # the default size keeps about every Stromovka frame (each a new place: a segment of its own), so
    # staging has little or nothing to save there; the fixed fractions save detector runs; the last two
    # settings detect every frame
    assert saved[0] >= 0 and all(n > 0 for n in saved[1:6]) and saved[6:] == [0, 0], saved


def test_records_of_frames_the_detector_skipped(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The staged records: ``ss``/``es`` null where the detector did not run (MS within [0, 1],
    'unscored'); the map counts no ResMem crop and no full-scoring crop count (ResMem does not run
    with the defaults, so nothing counted them)."""
    from memlog.steps.map import staged_scores

    _use_memo(monkeypatch, proxy_entropy=True)
    log = shared(STROMOVKA)
    recs, _ = staged_scores(log, MapConfig(descriptor=None))
    (topic, rows), = recs.items()
    skipped = [r for r in rows if r["ss"] is None]
    assert skipped and len(skipped) < len(rows)
    for r in skipped:
        assert r["es"] is None and r["ms"] is None and r["ms_low"] == 0.0 and r["ms_high"] == 1.0
        assert r["rejected_by"] == "unscored" and not r["selected"] and r["error"] is None
    res = make_map(log, tmp_path / "m.mcap", MapConfig(descriptor=None))
    assert res.crops_run == 0 and res.crops_full is None
    dropped = {i for i, why in res.selections[topic].to_dict()["dropped"] if why == "segment"}
    assert dropped >= {r["frame_index"] for r in skipped}


def test_staged_staticity_with_workers_and_resmem(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The detector pass on worker processes (jobs of several segments), and ResMem after it
    (``--score-kept``: the kept frames get their MS), keep the unstaged path's frames and records."""
    from tests.stand_in import use_stand_in

    use_stand_in(monkeypatch)
    log = shared("euroc_micro_ros2.mcap")
    staged = make_map(log, tmp_path / "staged.mcap", MapConfig(descriptor=None, stride=2, score_kept=True, workers=2))
    every = make_map(log, tmp_path / "every.mcap", MapConfig(descriptor=None, stride=2, score_kept=True),
                     stage_staticity=False)
    assert _kept(staged) == _kept(every)
    assert staged.crops_run == every.crops_run and staged.crops_run is not None and staged.crops_run > 0
    assert every.crops_full is not None and staged.crops_full is None  # (frames the detector did not see)
    a, b = _records(tmp_path / "staged.mcap"), _records(tmp_path / "every.mcap")
    assert {t: {i: {**r, "timing_ms": None} for i, r in recs.items()} for t, recs in a.items()} == \
        {t: {i: {**r, "timing_ms": None} for i, r in recs.items()} for t, recs in b.items()}


# -- evaluate: the reference scored as the map scores it ---------------------------------------------
def test_evaluate_scores_the_reference_as_the_map_does(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Without ``--compare-exact``, evaluate scores the reference drive with the map's staged path
    (no ``reference.scored.mcap``, no ResMem: the default map needs none) and its memorable map is
    the map ``memlog map`` writes with the same settings; no exact-selection column."""
    from memlog.steps.evaluate import EvaluateConfig, evaluate
    from tests.stand_in import use_stand_in

    use_stand_in(monkeypatch)
    ran = {"resmem": 0}
    from tests import stand_in

    real_run = stand_in.StandInSession.run

    def run(self: Any, names: Any, feeds: Any) -> Any:
        ran["resmem"] += 1
        return real_run(self, names, feeds)

    monkeypatch.setattr(stand_in.StandInSession, "run", run)
    ref, query = shared("nordland_dev_summer.mcap"), shared("nordland_dev_winter.mcap")
    cfg = EvaluateConfig(max_frames=48, seeds=2, report=False, descriptor="thumbnail")
    evaluate(ref, query, tmp_path / "ev", cfg, truth=shared("nordland_dev_truth.json"))
    results = json.loads((tmp_path / "ev" / "results.json").read_text())
    assert "memorable_exact" not in results and not (tmp_path / "ev" / "reference.scored.mcap").exists()
    assert ran["resmem"] == 0
    from memlog.io.base import FrameWindow
    from memlog.io.open import open_log

    with open_log(ref) as r:
        topic = r.check_camera_topics(None)[0]
        last = [f.log_time_ns for _, f in zip(range(48), r.frames([topic]))][-1]
    from memlog.steps.map import staged_scores

    window = FrameWindow((topic,), None, last + 1)
    cfg_map = MapConfig(descriptor=None, topics=(topic,))
    kept = []
    for staged in (True, False):
        recs, _ = staged_scores(ref, cfg_map, window, stage_staticity=staged)
        assert (None in [r["ss"] for r in recs[topic]]) == staged  # staged: the detector skipped frames
        m = make_map(ref, tmp_path / f"m{staged}.mcap", cfg_map, scores=recs)
        kept.append(m.selections[topic].kept_indices.tolist())
    assert results["memorable"]["kept_indices"] == kept[0] == kept[1]


# -- decoding at a reduced DCT scale ------------------------------------------------------------------
def test_reduced_jpeg_decode() -> None:
    from memlog.io.image import decode_bgr, decode_bgr_reduced, jpeg_reduction
    from memlog.io.open import open_log
    from memlog.io.types import ImagePayload

    assert jpeg_reduction(1024, 384, 224, 224) == 1
    assert jpeg_reduction(1024, 384, 32, 16) == 8
    assert jpeg_reduction(1920, 1080, 224, 224) == 4
    assert jpeg_reduction(1921, 1081, 300, 300) == 2
    with open_log(shared(STROMOVKA)) as r:
        frame = next(iter(r.frames()))
    full = frame.decode_bgr()
    for want, shape in (((224, 224), (384, 1024, 3)), ((300, 150), (192, 512, 3)), ((32, 16), (48, 128, 3))):
        small = frame.decode_bgr_reduced(*want)
        assert small.shape == shape and small.dtype == np.uint8 and small.flags.c_contiguous
        ref = cv2.resize(full, (shape[1], shape[0]), interpolation=cv2.INTER_AREA)
        assert float(np.abs(small.astype(float) - ref).mean()) < 3.0  # the same picture, not the same pixels
    png = ImagePayload("compressed", "png", bytes(cv2.imencode(".png", full[:64, :64])[1]))
    assert np.array_equal(decode_bgr_reduced(png, 8, 8), decode_bgr(png))  # not a JPEG: in full
    grey = ImagePayload("compressed", "jpeg", bytes(cv2.imencode(".jpg", full[:, :, 0])[1]))
    assert decode_bgr_reduced(grey, 100, 100).shape == (192, 512, 3)  # grey replicated like decode_bgr


# -- progress: the time left leaves the wait for the first item out ----------------------------------
def test_time_left_is_estimated_from_the_first_item_on(monkeypatch: pytest.MonkeyPatch,
                                                      caplog: pytest.LogCaptureFixture) -> None:
    import logging

    from memlog import progress as prog

    clock = {"t": 0.0}
    monkeypatch.setattr(prog.time, "monotonic", lambda: clock["t"])

    def items() -> Any:
        clock["t"] += 100.0  # models loading before the first frame
        for i in range(10):
            clock["t"] += 2.0
            yield i

    caplog.set_level(logging.INFO, logger="memlog.progress")
    for _ in prog._log_lines(items(), 50, "score", "frame", every_s=5.0):
        pass
    lines = [r.getMessage() for r in caplog.records if r.name == "memlog.progress"]
    assert lines[0] == "score: 1/50 frames (2 %) (0.00/s, estimating the time left)"
    # 2 s per frame from the first on (counting the 100 s before it: 0.04/s, about 1200 s left)
    assert lines[1] == "score: 4/50 frames (8 %) (0.50/s, about 92 s left)"
    assert lines[-1].startswith("score: 10/50 frames (20 %) in 120.0 s")
    bar = prog.Bar(50, "batch", "frame", every_s=5.0)
    caplog.clear()
    clock["t"] += 100.0
    for _ in range(10):
        clock["t"] += 2.0
        bar.update()
    bar.close()
    lines = [r.getMessage() for r in caplog.records if r.name == "memlog.progress"]
    assert lines[-2].endswith("(0.50/s, about 80 s left)") and lines[-1].startswith("batch: 10/50 frames (20 %) in 120.0 s")


def test_resize_is_the_spec_frame() -> None:
    """(Guards the one decode every consumer of a frame shares: the SPEC's frame from the full decode.)"""
    img = np.random.default_rng(0).integers(0, 255, (384, 1024, 3), dtype=np.uint8)
    assert np.array_equal(resize_frame(img), cv2.resize(img, (1135, 1135), interpolation=cv2.INTER_LINEAR))

"""map -> localize -> evaluate on the fixtures, with the real models."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import jsonschema
import numpy as np
import pyarrow.parquet as pq
import pytest

from memlog.errors import ConfigError
from memlog.io import FrameWindow, open_log
from memlog.io.positions import read_track
from memlog.outputs.annotated import read_scores
from memlog.outputs.descriptor_table import read_descriptors
from memlog.outputs.channels import MATCH, decode_record
from memlog.outputs.schemas import SCHEMAS
from memlog.scoring.config import ScoreConfig, load_config
from memlog.selection.config import SelectionConfig
from memlog.steps.evaluate import EvaluateConfig, evaluate
from memlog.steps.localize import LocalizeConfig, localize
from memlog.steps.map import EmptyMapError, MapConfig, make_map
from memlog.steps.score import score
from tests.conftest import FIXTURES

DEMO = FIXTURES / "demo.mcap"
COMP = "/camera/image/compressed"
RAW = "/camera/image_raw"


@pytest.fixture(scope="session")
def all_scored(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """demo.mcap, compressed topic, every score of every frame (shared by the tests below)."""
    out = tmp_path_factory.mktemp("scored") / "reference.scored.mcap"
    score(DEMO, out, ScoreConfig(all_scores=True), FrameWindow((COMP,)))
    return out


def _passes(rec: dict, mt: float, st: float, et: float) -> bool:
    return rec["ms"] >= mt and rec["ss"] >= st and rec["es"] >= et


def test_map_with_fixed_thresholds(all_scored: Path, tmp_path: Path) -> None:
    recs = read_scores(all_scored)[COMP]
    th = dict(mt=0.5, st=0.6, et=0.15)
    want = [r["frame_index"] for r in recs if _passes(r, **th)]
    assert 0 < len(want) < len(recs), "fixture should keep some frames and drop others at these thresholds"
    out = tmp_path / "map.mcap"
    res = make_map(DEMO, out, MapConfig(select=SelectionConfig(mode="paper", **th), topics=(COMP,),
                                        keep_topics=("/gps/fix",)), scores=all_scored)
    assert res.frames_kept == len(want) and res.frames_in == len(recs)
    with open_log(DEMO) as src, open_log(out) as m:
        kept = list(m.frames([COMP]))
        assert [r["frame_index"] for r in read_scores(out)[COMP]] == want
        src_frames = {f.index: f for f in src.frames([COMP])}
        assert [f.payload.data for f in kept] == [src_frames[i].payload.data for i in want]  # byte for byte
        assert sum(1 for _ in m.messages(["/gps/fix"])) == 8  # kept whole
        meta = dict(m.metadata())
        assert json.loads(meta["memlog_map"]["thresholds"]) == th
    table = read_descriptors(res.descriptors)  # type: ignore[arg-type]
    assert list(table.frame_index) == want
    assert np.allclose(np.linalg.norm(table.descriptors, axis=1), 1.0, atol=1e-5)
    assert np.all(np.isfinite(table.positions["lat"]))
    assert table.meta.kind == "thumbnail" and table.extra["frames_in"] == len(recs)


def test_map_keep_fraction_and_raw_topic_reencoded(all_scored: Path, tmp_path: Path) -> None:
    out = tmp_path / "map.mcap"
    res = make_map(DEMO, out, MapConfig(select=SelectionConfig(mode="paper", keep_fraction=0.5), topics=(COMP,)),
                   scores=all_scored)
    assert 3 <= res.frames_kept <= 5
    th = res.thresholds
    recs = read_scores(all_scored)[COMP]
    assert res.frames_kept == sum(_passes(r, th["mt"], th["st"], th["et"]) for r in recs)
    # a raw topic becomes CompressedImage (JPEG) on T/compressed; pixels close to the source
    raw_scored = tmp_path / "raw.scored.mcap"
    score(FIXTURES / "ros2idl.mcap", raw_scored, ScoreConfig(all_scores=True))
    out2 = tmp_path / "raw_map.mcap"
    make_map(FIXTURES / "ros2idl.mcap", out2,
             MapConfig(select=SelectionConfig(mode="paper", mt=0, st=0, et=0), image_format="png"), scores=raw_scored)
    with open_log(out2) as m, open_log(FIXTURES / "ros2idl.mcap") as src:
        got = list(m.frames(["/camera/image_raw/compressed"]))
        ref = list(src.frames())
        assert len(got) == len(ref) == 2
        for g, r in zip(got, ref):
            assert g.payload.encoding == "png" and g.stamp_ns == r.stamp_ns
            assert np.array_equal(g.decode_bgr(), r.decode_bgr())  # PNG is lossless


def test_empty_map_is_an_error_that_suggests_keep_fraction(all_scored: Path, tmp_path: Path) -> None:
    with pytest.raises(EmptyMapError, match="--keep-fraction"):
        make_map(DEMO, tmp_path / "m.mcap", MapConfig(select=SelectionConfig(mode="paper", mt=0.99, st=0.99, et=0.99),
                                                      topics=(COMP,)), scores=all_scored)
    assert not (tmp_path / "m.mcap").exists()
    r = subprocess.run([sys.executable, "-m", "memlog", "map", str(DEMO), "-o", str(tmp_path / "m.mcap"),
                        "--scores", str(all_scored), "-t", COMP, "--et", "0.99", "--select", "paper"], capture_output=True, text=True)
    assert r.returncode == 1 and "--keep-fraction" in r.stderr and "Traceback" not in r.stderr


def test_early_exit_scores_refused_for_calibration(tmp_path: Path) -> None:
    scored = tmp_path / "s.mcap"
    score(FIXTURES / "ros1.mcap", scored, ScoreConfig())
    with pytest.raises(ConfigError, match="all-scores"):
        make_map(FIXTURES / "ros1.mcap", tmp_path / "m.mcap",
                 MapConfig(select=SelectionConfig(mode="paper", keep_fraction=0.5)), scores=scored)


def test_localize_finds_the_same_place(all_scored: Path, tmp_path: Path) -> None:
    """Map = every compressed frame; queries = the raw frames of the same images: best match = same index."""
    res = make_map(DEMO, tmp_path / "map.mcap", MapConfig(select=SelectionConfig(mode="paper", mt=0, st=0, et=0),
                                                          topics=(COMP,)), scores=all_scored)
    assert res.frames_kept == 8
    loc = localize(res.descriptors, DEMO, tmp_path / "matches.csv",  # type: ignore[arg-type]
                   LocalizeConfig(k=3, window=FrameWindow((RAW,))), annotate=tmp_path / "q.mcap")
    import pyarrow.csv as pacsv

    t = pacsv.read_csv(tmp_path / "matches.csv")
    rows = t.to_pylist()
    best = {r["query_id"]: r["ref_id"] for r in rows if r["rank"] == 0}
    assert best == {i: i for i in range(8)}
    assert loc.n_queries == 8 and loc.n_map == 8
    validator = jsonschema.Draft202012Validator(SCHEMAS["memlog.Match"])
    with open_log(tmp_path / "q.mcap") as q:
        msgs = [decode_record(MATCH, m.channel, m.data) for m in q.messages([f"{RAW}/memlog/match"])]
    assert len(msgs) == 8
    for m in msgs:
        validator.validate(m)
        assert m["matches"][0]["frame_index"] == m["frame_index"]


def test_evaluate_end_to_end(all_scored: Path, tmp_path: Path) -> None:
    out = tmp_path / "eval"
    out.mkdir()
    shutil.copyfile(all_scored, out / "reference.scored.mcap")  # reused: same settings
    truth = tmp_path / "truth.json"
    truth.write_text(json.dumps({"matches": [[i] for i in range(8)]}))
    # --compare-exact: every reference frame scored (the sweeps and the exact selection need every score)
    res = evaluate(DEMO, DEMO, out, EvaluateConfig(select=SelectionConfig(keep_fraction=0.5), reference_topic=COMP,
                                                   query_topic=RAW, seeds=5, compare_exact=True), truth=truth)
    saved = json.loads((out / "results.json").read_text())
    for name in ("full", "memorable", "uniform", "random"):
        for key in ("frames", "coverage", "auc", "recall@1", "recall@5", "recall@10", "match_seconds_per_query"):
            assert key in saved[name], (name, key)
        assert "auc" in saved[name]["paper_protocol"] and "recall@1" in saved[name]["paper_protocol"]
    # the full map holds every frame of the drive, a stop's frames once (its first: the moving index
    # steps there): its frames are found, as the same images, and only those (exact truth: coverage = its share)
    moving = pq.read_table(next(out.glob("reference.*.parquet"))).to_pydict()["moving_index"]
    n_full = len(set(moving))
    assert saved["full"]["frames"] == n_full and 0 < n_full <= 8
    assert saved["full"]["coverage"] == pytest.approx(n_full / 8)
    assert saved["full"]["recall@1"] == pytest.approx(n_full / 8)  # same images
    k = saved["memorable"]["frames"]
    assert saved["uniform"]["frames"] == saved["random"]["frames"] == k
    assert saved["memorable"]["coverage"] == pytest.approx(k / 8)  # exact truth: coverage = kept share
    assert saved["memorable"]["recall@1"] == pytest.approx(k / 8)  # a kept place is always found
    assert set(saved["memorable"]["thresholds"]) == {"mt", "st", "et"}
    assert "std" in saved["random"] and saved["random"]["seeds"] == 5
    # every k-th frame from each start offset: evenly spaced frames shifted 0, 1, 2 ... frames along the
    # drive (wrapping past the last of the 8), as many offsets as the spacing, each map of k frames and,
    # under exact truth, R@1 k/8; the spread's mean, std, min and max are those of the maps
    ph = saved["uniform_phases"]
    first = sorted(ph["maps"][0]["kept_indices"])
    assert len(first) == k and len(ph["maps"]) == int(np.ceil(7 / (k - 1) - 1e-9))
    for d, p in enumerate(ph["maps"]):
        assert sorted(p["kept_indices"]) == sorted((i + d) % 8 for i in first)
        assert p["recall@1"] == pytest.approx(k / 8)
    assert ph["maps"][0]["recall@1"] == saved["uniform"]["recall@1"]
    for name in ("uniform_phases", "random"):
        vals = [p["recall@1"] for p in saved[name]["maps"]]
        assert saved[name]["recall@1"] == pytest.approx(np.mean(vals))
        assert saved[name]["std"]["recall@1"] == pytest.approx(np.std(vals))
        assert (saved[name]["min"]["recall@1"], saved[name]["max"]["recall@1"]) == (min(vals), max(vals))
        among = saved["memorable"]["among"][name]
        assert among["below"] == pytest.approx(np.mean([v < saved["memorable"]["recall@1"] - 1e-12 for v in vals]))
        assert among["below"] + among["tied"] + among["above"] == pytest.approx(1.0)
    assert [r["threshold"] for r in saved["sweeps"]["mt"]] == [round(0.1 * i, 1) for i in range(11)]
    assert saved["sweeps"]["st"][0]["frames"] == 8
    report = (out / "report.html").read_text()
    assert report.count("<svg") >= 7
    # the spread drawn: one dot per baseline map, the memorable map's line and where it lies among them
    spread = report[report.index(f"R@1 of maps of {k} frames"):]
    spread = spread[: spread.index("</svg>")]
    assert spread.count("<circle") == len(saved["uniform_phases"]["maps"]) + len(saved["random"]["maps"])
    assert f"memorable {saved['memorable']['recall@1']:.3f}" in spread
    assert (out / "map.mcap").is_file() and (out / "map.parquet").is_file()
    assert res["memorable"]["frames"] == k


def test_config_files_and_overrides(tmp_path: Path) -> None:
    toml = tmp_path / "c.toml"
    toml.write_text("[score]\nmt = 0.45\nst = 0.55\n")
    assert load_config(path=toml, et=0.3) == ScoreConfig(mt=0.45, st=0.55, et=0.3)
    yaml = tmp_path / "c.yaml"
    yaml.write_text("mt: 0.4\nnormalize: static\n")
    assert load_config(path=yaml).normalize == "static"
    assert load_config("st-lucia") == ScoreConfig(mt=0.45, st=0.55, et=0.35)
    bad = tmp_path / "bad.toml"
    bad.write_text("mtt = 0.4\n")
    with pytest.raises(ConfigError, match="unknown setting"):
        load_config(path=bad)
    with pytest.raises(ConfigError, match="within"):
        ScoreConfig(mt=1.5)


def test_positions_interpolated_to_frames() -> None:
    with open_log(DEMO) as log:
        track = read_track(log)
        assert track is not None and track.kind == "gnss" and track.topic == "/gps/fix"
        t = [f.log_time_ns for f in log.frames([COMP])]
        xyz = track.at(t)
    north = xyz[:, 1]
    assert np.all(np.diff(north) >= -1e-9)  # the drive goes north, with a stop
    assert north[4] == pytest.approx(north[3], abs=0.5)  # frames 3..5 stand still
    assert north[2] - north[1] == pytest.approx(5.0, abs=0.05)  # 5 m per frame (both between fixes)


def test_evaluate_quick_trials_several_descriptors(all_scored: Path, tmp_path: Path) -> None:
    out = tmp_path / "eval"
    out.mkdir()
    shutil.copyfile(all_scored, out / "reference.scored.mcap")
    truth = tmp_path / "truth.json"
    truth.write_text(json.dumps({"matches": [[i] for i in range(8)]}))
    cfg = EvaluateConfig(select=SelectionConfig(keep_fraction=0.5), reference_topic=COMP, query_topic=RAW, seeds=3,
                         descriptor="auto,thumbnail,dinov2-gem", window=FrameWindow(stride=2), max_frames=3,
                         report=False)
    res = evaluate(DEMO, DEMO, out, cfg, truth=truth)
    kinds = res["descriptors"]
    assert list(kinds) == ["thumbnail", "dinov2-gem"]  # auto chose the thumbnail (96x72 frames): described once
    assert kinds["thumbnail"]["descriptor"]["requested"] == "auto" and kinds["thumbnail"]["requested_as"] == ["thumbnail"]
    for kind in kinds:
        assert (out / f"reference.{kind}.parquet").is_file() and (out / f"map.{kind}.mcap").is_file()
        t = read_descriptors(out / f"reference.{kind}.parquet")
        assert list(t.frame_index) == [0, 2, 4]  # stride 2, first 3 frames
        assert kinds[kind]["full"]["frames"] == 3 and kinds[kind]["full"]["recall@1"] == 1.0
    assert res["full"] == kinds["thumbnail"]["full"]
    stamp = (out / "query.dinov2-gem.parquet").stat().st_mtime_ns
    evaluate(DEMO, DEMO, out, cfg, truth=truth)  # described once: the second run reuses the cache
    assert (out / "query.dinov2-gem.parquet").stat().st_mtime_ns == stamp
    with pytest.raises(ConfigError, match="descriptor"):
        EvaluateConfig(descriptor="thumbnail,nope")
    with pytest.raises(ConfigError, match="max_frames"):
        EvaluateConfig(max_frames=0)
    r = subprocess.run([sys.executable, "-m", "memlog", "evaluate", "--reference", str(DEMO), "--query", str(DEMO),
                        "--truth", str(truth), "-o", str(out), "--reference-topic", COMP, "--query-topic", RAW,
                        "--keep-fraction", "0.5", "--descriptor", "thumbnail,dinov2-gem", "--stride", "2",
                        "--max-frames", "3", "--seeds", "2", "--no-report"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    lines = [ln for ln in r.stdout.splitlines() if ln.startswith(("thumbnail", "dinov2-gem"))]
    assert len(lines) == 12 and "Traceback" not in r.stderr  # 6 maps per descriptor (exact: --compare-exact), one table
    maps: dict[str, list[str]] = {}
    for ln in lines:  # the map column: full, memorable (written), its exact selection, and the four baselines
        m = re.match(r"^(\S+)\s+(?:raw|whitened)\s+(.+?)\s{2,}\d", ln)
        assert m, ln
        maps.setdefault(m.group(1), []).append(m.group(2))
    assert all(m == ["full", "memorable", "every k-th", "every k-th, its start offsets", "uniform by distance",
                     "random"] for m in maps.values()), maps  # 2 of 3 frames: two offsets; the demo has GPS

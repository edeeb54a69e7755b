"""The staged scorer and the annotated MCAP, with the real models."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import jsonschema
import numpy as np
import pytest
from mcap.reader import make_reader

from memlog.io import FrameWindow, open_log
from memlog.outputs.annotated import read_scores, run_config
from memlog.outputs.schemas import SCHEMAS, schema_bytes
from tests.ecosystem import FAMILY, decoded, plain
from memlog.scoring.config import ScoreConfig
from memlog.scoring.scorer import Scorer, resize_frame
from memlog.steps.score import score
from tests.conftest import FIXTURE_LOGS, FIXTURES


@pytest.fixture(scope="session")
def scorer() -> Scorer:
    return Scorer(ScoreConfig()).load()


@pytest.fixture(scope="session")
def all_scorer() -> Scorer:
    return Scorer(ScoreConfig(all_scores=True)).load()


def _records(path: Path) -> list[tuple]:
    with open(path, "rb") as fh:
        r = make_reader(fh, validate_crcs=True)
        return sorted((ch.topic, m.log_time, m.publish_time, m.sequence, bytes(m.data)) for _, ch, m in r.iter_messages())


@pytest.mark.parametrize("name", FIXTURE_LOGS)
def test_annotated_mcap_keeps_input_and_validates(name: str, tmp_path: Path, scorer: Scorer) -> None:
    out = tmp_path / "scored.mcap"
    stride = 3 if name == "demo.mcap" else 1
    run = score(FIXTURES / name, out, scorer.config, FrameWindow(stride=stride), scorer=scorer)
    with open_log(FIXTURES / name) as log:
        cams = log.camera_topics()
        want = sorted((m.channel.topic, m.log_time, m.publish_time, m.sequence, m.data) for m in log.messages())
    got = _records(out)  # CRCs validated while reading
    assert [r for r in got if "/memlog/" not in r[0]] == want, "input messages must survive byte for byte"
    validator = jsonschema.Draft202012Validator(SCHEMAS["memlog.FrameScores"])
    ann_validator = jsonschema.Draft202012Validator(json.loads(schema_bytes("foxglove.ImageAnnotations")))
    scores = read_scores(out)
    assert set(scores) == set(cams)
    for topic, recs in scores.items():
        with open_log(FIXTURES / name) as log:
            n = sum(1 for _ in log.messages([topic]))
        assert [r["frame_index"] for r in recs] == list(range(0, n, stride))
        for rec in recs:
            validator.validate(rec)
            if rec["rejected_by"] == "undecodable":
                assert rec["error"] and rec["ms"] is None
                continue
            assert rec["ss"] is not None and 0.0 <= rec["ss"] <= 1.0
            assert rec["selected"] == (rec["rejected_by"] is None)
            if rec["rejected_by"] == "staticity":
                assert rec["ss"] < 0.6 and rec["es"] is None and rec["ms"] is None
            if rec["rejected_by"] == "entropy":
                assert rec["es"] < 0.4 and rec["ms"] is None
            if rec["selected"]:
                assert rec["ss"] >= 0.6 and rec["es"] >= 0.4 and rec["ms_low"] >= 0.5
    for _, ch, _m, ann in decoded(out, FAMILY[name], {f"{t}/memlog/annotations" for t in cams}):
        ann_validator.validate(plain(ann))  # the official schema, in the input's encoding family
    with open(out, "rb") as fh:
        meta = {m.name: m.metadata for m in make_reader(fh).iter_metadata()}
    assert json.loads(meta["memlog_run"]["config"])["mt"] == 0.5
    summary = json.loads(meta["memlog_summary"]["topics"])
    for topic, s in summary.items():
        assert s["scored"] + s["undecodable"] == s["frames_seen"] == len(scores[topic])
        assert s["selected"] + sum(s["rejected"].values()) == s["scored"]
    assert run_config(out) == scorer.config
    if name == "encodings.mcap":  # the garbage jpeg and the compressedDepth frame are reported, not fatal
        assert run.report.undecodable_frames == 2


def test_textureless_wall_is_rejected_by_entropy(scorer: Scorer) -> None:
    wall = np.full((480, 640, 3), 180, np.uint8)
    wall[:, :, 1] = np.linspace(150, 190, 640).astype(np.uint8)  # a smooth lighting gradient
    s = scorer.score(wall)
    assert s.ss == 1.0 and s.rejected_by == "entropy" and s.es is not None and s.es < 0.05
    assert s.ms is None and s.crops_scored == 0  # memorability skipped


def test_person_frame_rejected_by_staticity(scorer: Scorer) -> None:
    import skimage.data

    person = cv2.cvtColor(skimage.data.astronaut(), cv2.COLOR_RGB2BGR)
    s = scorer.score(person)
    assert s.rejected_by == "staticity" and s.ss < 0.6
    assert any(d.class_name == "person" for d in s.detections)
    assert s.es is None and s.ms is None


def test_exact_mode_equals_paper_literal(scorer: Scorer, source_frames: list) -> None:
    """Exact mode: same decisions as the literal pipeline; values equal where both computed them."""
    paper = Scorer(ScoreConfig(mode="paper"), memorability=scorer.memorability, staticity=scorer.staticity)
    for img in source_frames[2:5]:
        a, b = scorer.score(img), paper.score(img)
        assert a.selected == b.selected and a.rejected_by == b.rejected_by
        assert a.ss == b.ss
        if a.es is not None:
            assert a.es == pytest.approx(b.es, abs=1e-9)  # fast entropy == scikit-image
        if a.ms is not None:
            assert b.ms is not None and b.ms_exact and b.crops_scored == 25
            assert a.ms_low - 1e-6 <= b.ms <= a.ms_high + 1e-6  # bounds bracket the value


def test_all_scores_computes_every_stage(all_scorer: Scorer) -> None:
    import skimage.data

    person = cv2.cvtColor(skimage.data.astronaut(), cv2.COLOR_RGB2BGR)
    s = all_scorer.score(person)
    assert s.rejected_by == "staticity"
    assert s.es is not None and s.ms is not None and s.ms_exact and s.crops_scored > 0
    # MS is masked by S: crops entirely covered by the person have weight 0 and are not scored
    assert s.crops_scored <= 25


def test_resize_frame_follows_spec() -> None:
    grey = np.arange(12, dtype=np.uint8).reshape(3, 4) * 20
    f = resize_frame(grey)
    assert f.shape == (1135, 1135, 3) and np.array_equal(f[..., 0], f[..., 2])
    want = cv2.resize(cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR), (1135, 1135), interpolation=cv2.INTER_LINEAR)
    assert np.array_equal(f, want)
    with pytest.raises(Exception, match="uint8"):
        resize_frame(np.zeros((4, 4, 3), np.float32))


def test_maps_channels(tmp_path: Path, scorer: Scorer) -> None:
    cfg = ScoreConfig(maps=True)
    sc = Scorer(cfg, memorability=scorer.memorability, staticity=scorer.staticity)
    out = tmp_path / "maps.mcap"
    score(FIXTURES / "ros2idl.mcap", out, cfg, scorer=sc)
    with open_log(out) as log:
        topics = set(log.topics())
        assert {"/camera/image_raw/memlog/maps/staticity", "/camera/image_raw/memlog/maps/entropy"} <= topics
        for f in log.frames(["/camera/image_raw/memlog/maps/entropy"]):
            img = f.decode_gray()
            assert img.shape == (72, 96)

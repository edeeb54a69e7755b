"""Every output memlog writes, from every fixture profile, opens in the ROS/Foxglove ecosystem.

For each fixture log: ``memlog score`` (with a stand-in scorer: the models are not under test
here), ``memlog map`` reusing that scoring run, and ``memlog localize --annotate``. Each output must

* keep the input's profile and write memlog's channels in the input's encoding family;
* open with rosbags' AnyReader where rosbags reads that kind of file (a ros2 MCAP directly; a ros1
  MCAP converted to a ROS 1 bag, which checks definitions and md5sums), and decode message by
  message with the mcap reader's decoder for its encoding (mcap_ros2, mcap_ros1, mcap_protobuf, json);
* hold score messages that decode (by the documented conventions) to exactly what ``read_scores``
  returns, and to the values the scorer produced;
* carry Foxglove's official ImageAnnotations definition, every annotation valid against its JSON Schema.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any, TypeVar

import cv2
import jsonschema
import numpy as np
import pyarrow.parquet as pq
import pytest
from mcap.reader import make_reader

from memlog.errors import ImageDecodeError
from memlog.io import FrameWindow, open_log
from memlog.io.frame import Frame
from memlog.io.mcap import McapLogWriter
from memlog.outputs.annotated import read_scores
from memlog.outputs.channels import IMAGE, MATCH, SCORES, ANNOTATIONS, MemlogChannels, canonical_scores, decode_record
from memlog.outputs.schemas import FRAME_SCORES, MATCH as MATCH_SCHEMA, foxglove_definition
from memlog.scoring.config import ScoreConfig
from memlog.scoring.scorer import FrameScore, Scorer
from memlog.scoring.staticity import Detection
from memlog.selection.config import SelectionConfig
from memlog.steps.localize import LocalizeConfig, localize
from memlog.steps.map import MapConfig, make_map
from memlog.steps.score import score
from tests.conftest import FIXTURE_LOGS, FIXTURES
from tests.ecosystem import (ENCODINGS, FAMILY, anyreader_opens, anyreader_read_all, copy_topics, decoded, plain,
                             record_of_match, record_of_scores, ros1_bag_of)

T = TypeVar("T")
ROS_LOGS = [n for n in FIXTURE_LOGS if FAMILY[n] in ("ros1", "ros2")]
ANNOTATIONS_SCHEMA = jsonschema.Draft202012Validator(
    __import__("json").loads(foxglove_definition("foxglove.ImageAnnotations", "jsonschema")))


# -- a stand-in scorer: fixed, varied scores, no models ------------------------------------------------

def fake_score(img: np.ndarray, index: int) -> FrameScore:
    """Scores from the pixels and the frame index: every record shape memlog writes."""
    h, w = img.shape[:2]
    mean = round(float(img.mean()) / 255.0, 4)
    dets = [Detection(1, "person", 0.9, 0.1, 0.2, 0.4, 0.8, True), Detection(3, "car", 0.3, 0.5, 0.5, 0.9, 0.9, True)]
    timing = {"decode": 1.25, "resize": 0.5, "staticity": 2.0}
    k = index % 4
    if k == 1:  # rejected by staticity: no ES, no MS
        return FrameScore(ms=None, ss=0.25 + mean / 10, es=None, selected=False, rejected_by="staticity",
                          detections=dets, timing_ms=timing, width=w, height=h,
                          maps={"staticity": np.full((h, w), 0.25)})
    if k == 3:  # rejected by entropy
        return FrameScore(ms=None, ss=0.9, es=0.05 + mean / 10, selected=False, rejected_by="entropy",
                          timing_ms={**timing, "entropy": 3.5}, width=w, height=h,
                          maps={"staticity": np.ones((h, w)), "entropy": np.full((h, w), 2.0)})
    m = np.full((5, 5), np.nan, np.float32)
    m[0, :3] = [0.5, 0.625, 0.75]
    m[4, 4] = 0.875
    return FrameScore(ms=0.6 + mean / 10, ss=1.0, es=0.5 + mean / 10, selected=True, rejected_by=None,
                      memorability=m, ms_low=0.55, ms_high=0.7 + mean / 10, ms_exact=k == 0, crops_scored=4,
                      crops_surrogate=0 if k == 0 else 21, detections=dets[1:],
                      timing_ms={**timing, "entropy": 3.5, "memorability": 40.0}, width=w, height=h,
                      maps={"staticity": np.ones((h, w)), "entropy": np.full((h, w), 4.0),
                            "memorability": np.full((h, w), 0.6)})


class FakeScorer(Scorer):
    def load(self) -> "FakeScorer":
        return self

    def provenance(self) -> dict[str, Any]:
        return {"models": {"stand-in": "0" * 64}, "devices": {"stand-in": "cpu"}}

    def score_stream(self, items: Iterable[T], decode: Callable[[T], np.ndarray],  # type: ignore[override]
                     prefetch: int = 2, **_: Any) -> Iterator[tuple[T, FrameScore | Exception]]:
        for item in items:
            try:
                img = decode(item)
            except ImageDecodeError as exc:
                yield item, exc
                continue
            assert isinstance(item, Frame)
            yield item, fake_score(img, item.index)


# -- the outputs, once per fixture -------------------------------------------------------------------

_OUTPUTS: dict[str, dict[str, Path]] = {}


def outputs(name: str, base: Path) -> dict[str, Path]:
    if name not in _OUTPUTS:
        d = base / name.replace(".", "_")
        d.mkdir()
        cfg = ScoreConfig(maps=True)
        score(FIXTURES / name, d / "scored.mcap", cfg, scorer=FakeScorer(cfg))
        res = make_map(FIXTURES / name, d / "map.mcap",
                       MapConfig(select=SelectionConfig(mode="paper", mt=0, st=0, et=0)), scores=d / "scored.mcap")
        assert res.frames_kept > 0 and res.descriptors is not None
        localize(res.descriptors, FIXTURES / name, d / "matches.parquet", LocalizeConfig(k=3),
                 annotate=d / "matched.mcap")
        _OUTPUTS[name] = {"scored": d / "scored.mcap", "map": d / "map.mcap", "matched": d / "matched.mcap",
                          "matches": d / "matches.parquet"}
    return _OUTPUTS[name]


@pytest.fixture(scope="module")
def out_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("ecosystem")


def _input_topics(name: str) -> set[str]:
    with open_log(FIXTURES / name) as log:
        return set(log.topics())


def _memlog_topics(path: Path, name: str) -> set[str]:
    with open_log(path) as log:
        return set(log.topics()) - _input_topics(name)


LOGS = ("scored", "map", "matched")


# -- tests ------------------------------------------------------------------------------------------

@pytest.mark.parametrize("name", FIXTURE_LOGS)
def test_channels_follow_the_input_family(name: str, out_dir: Path) -> None:
    outs = outputs(name, out_dir)
    msg_enc, schema_enc = ENCODINGS[FAMILY[name]]
    with open_log(FIXTURES / name) as src:
        profile = src.profile
    for kind in LOGS:
        with open(outs[kind], "rb") as fh:
            r = make_reader(fh)
            assert r.get_header().profile == profile, f"{kind}: the output keeps the input's profile"
            summary = r.get_summary()
            assert summary is not None
        ours = _memlog_topics(outs[kind], name)
        assert ours, kind
        for ch in summary.channels.values():
            if ch.topic not in ours:
                continue
            schema = summary.schemas[ch.schema_id]
            assert (ch.message_encoding, schema.encoding) == (msg_enc, schema_enc), f"{kind}: {ch.topic}"
            if FAMILY[name] == "ros1":  # ROS 1 tools check the md5sum of the definition
                from rosbags.typesys import Stores, get_types_from_msg, get_typestore

                pkg, short = schema.name.split("/")
                store = get_typestore(Stores.EMPTY)
                store.register(get_types_from_msg(schema.data.decode(), f"{pkg}/msg/{short}"))
                assert ch.metadata["md5sum"] == store.generate_msgdef(f"{pkg}/msg/{short}", ros_version=1)[1]


@pytest.mark.parametrize("name", ROS_LOGS)
def test_rosbags_anyreader_opens_every_output(name: str, out_dir: Path, tmp_path: Path) -> None:
    outs = outputs(name, out_dir)
    for kind in LOGS:
        path = outs[kind]
        ours = _memlog_topics(path, name)
        if FAMILY[name] == "ros1":  # rosbags reads ROS 1 data from .bag files only
            bag = tmp_path / f"{kind}.bag"
            ros1_bag_of(path, bag)
            counts = anyreader_read_all([bag])  # checks every connection's md5sum against its definition
        elif anyreader_opens(FIXTURES / name):  # rosbags reads ros2 MCAP files directly
            counts = anyreader_read_all([path])
        else:  # rosbags cannot read the input's own schemas (ros2idl.mcap): check memlog's channels alone
            alone = tmp_path / f"{kind}.memlog.mcap"
            copy_topics(path, alone, ours)
            counts = anyreader_read_all([alone])
        with open_log(path) as log:
            want = {t: sum(1 for _ in log.messages([t])) for t in ours}
        assert {t: counts.get(t, 0) for t in ours} == want, kind


@pytest.mark.parametrize("name", FIXTURE_LOGS)
def test_the_mcap_decoder_of_the_family_reads_every_message(name: str, out_dir: Path) -> None:
    """A user reads a ros2 MCAP with mcap_ros2, a ros1 MCAP with mcap_ros1, ...: every message of
    the output decodes with that one decoder (the input's own channels too, where the decoder
    reads their schema encoding: mcap_ros2 does not read ros2idl)."""
    outs = outputs(name, out_dir)
    for kind in LOGS:
        with open_log(outs[kind]) as log:
            topics = {c.topic for c in log.channels() if c.schema is None or c.schema.encoding != "ros2idl"}
            want = sum(1 for _ in log.messages(sorted(topics)))
        assert _memlog_topics(outs[kind], name) <= topics
        assert sum(1 for _ in decoded(outs[kind], FAMILY[name], topics)) == want > 0


@pytest.mark.parametrize("name", FIXTURE_LOGS)
def test_score_messages_decode_to_read_scores(name: str, out_dir: Path) -> None:
    outs = outputs(name, out_dir)
    validator = jsonschema.Draft202012Validator(FRAME_SCORES)
    by_file = {}
    for kind in ("scored", "map"):
        got = read_scores(outs[kind])
        external: dict[str, list[dict[str, Any]]] = {}
        for _s, ch, _m, msg in decoded(outs[kind], FAMILY[name], {t for t in _memlog_topics(outs[kind], name)
                                                    if t.endswith("/memlog/scores")}):
            external.setdefault(ch.topic.removesuffix("/memlog/scores"), []).append(
                record_of_scores(plain(msg), ch.message_encoding))
        for recs in external.values():
            recs.sort(key=lambda r: r["frame_index"])
        assert external == got, f"{kind}: the decoders and read_scores disagree"
        for recs in got.values():
            for rec in recs:
                validator.validate(rec)
        by_file[kind] = got
    # the scoring run holds what the scorer produced, frame by frame
    with open_log(FIXTURES / name) as src:
        frames = {(f.topic, f.index): f for f in src.frames()}
    for topic, recs in by_file["scored"].items():
        assert [r["frame_index"] for r in recs] == sorted(i for t, i in frames if t == topic)
        for rec in recs:
            f = frames[(topic, rec["frame_index"])]
            assert (rec["log_time"], rec["topic"]) == (f.log_time_ns, topic)
            try:
                s = fake_score(f.decode_bgr(), f.index)
            except ImageDecodeError:
                assert rec["rejected_by"] == "undecodable" and rec["error"] and rec["ss"] is None
                continue
            for k in ("ms", "ms_low", "ms_high", "ss", "es"):
                v = getattr(s, k)
                assert rec[k] == (None if v is None else round(v, 6)), k
            assert (rec["rejected_by"], rec["selected"], rec["ms_exact"]) == (s.rejected_by, s.selected, s.ms_exact)
            assert (rec["crops_surrogate"], rec["detections"]) == (s.crops_surrogate, len(s.detections))
            assert rec["timing_ms"] == s.timing_ms
            if s.memorability is None:
                assert rec["memorability"] is None
            else:
                assert [[None if math.isnan(v) else v for v in row] for row in s.memorability.tolist()] == rec["memorability"]
    # the map log carries the scoring run's records of the kept frames, unchanged
    for topic, recs in by_file["map"].items():
        scored = {r["frame_index"]: r for r in by_file["scored"][topic]}
        assert recs and all(r == scored[r["frame_index"]] for r in recs)


@pytest.mark.parametrize("name", FIXTURE_LOGS)
def test_annotations_use_the_official_foxglove_definition(name: str, out_dir: Path) -> None:
    path = outputs(name, out_dir)["scored"]
    family = FAMILY[name]
    official = foxglove_definition("foxglove.ImageAnnotations",
                                   {"ros2": "ros2msg", "ros1": "ros1msg"}.get(family, ENCODINGS[family][1]))
    scores = read_scores(path)
    n = 0
    for schema, ch, _m, msg in decoded(path, family, {t for t in _memlog_topics(path, name) if t.endswith("/memlog/annotations")}):
        assert schema is not None and bytes(schema.data) == official
        assert schema.name == {"ros2": "foxglove_msgs/msg/ImageAnnotations",
                               "ros1": "foxglove_msgs/ImageAnnotations"}.get(family, "foxglove.ImageAnnotations")
        ann = plain(msg)
        ANNOTATIONS_SCHEMA.validate(ann)
        rec = next(r for r in scores[ch.topic.removesuffix("/memlog/annotations")] if r["timestamp"] == ann["timestamp"])
        assert len(ann["points"]) == rec["detections"] and len(ann["texts"]) == rec["detections"] + 1
        assert ann["texts"][-1]["text"].startswith("MS ") and all(p["type"] == 2 for p in ann["points"])
        n += 1
    assert n == sum(1 for recs in scores.values() for r in recs if r["rejected_by"] != "undecodable") > 0


@pytest.mark.parametrize("name", FIXTURE_LOGS)
def test_maps_are_compressed_images(name: str, out_dir: Path) -> None:
    path = outputs(name, out_dir)["scored"]
    topics = {t for t in _memlog_topics(path, name) if "/memlog/maps/" in t}
    n = 0
    for schema, _ch, _m, msg in decoded(path, FAMILY[name], topics):
        assert schema is not None and schema.name in ("sensor_msgs/msg/CompressedImage", "sensor_msgs/CompressedImage",
                                                      "foxglove.CompressedImage")
        img = plain(msg)
        data = img["data"]
        if isinstance(data, str):
            import base64

            jsonschema.Draft202012Validator(__import__("json").loads(schema.data)).validate(img)
            data = base64.b64decode(data)
        assert img["format"] == "png" and cv2.imdecode(np.frombuffer(bytes(data), np.uint8), cv2.IMREAD_UNCHANGED) is not None
        n += 1
    assert n > 0
    with open_log(path) as log:  # memlog reads them back as camera frames too
        assert sum(1 for _ in log.frames(sorted(topics))) == n


@pytest.mark.parametrize("name", FIXTURE_LOGS)
def test_match_messages_agree_with_the_match_table(name: str, out_dir: Path) -> None:
    outs = outputs(name, out_dir)
    rows = pq.read_table(outs["matches"]).to_pylist()
    table: dict[tuple[str, int], list[tuple[str, int]]] = {}
    for r in sorted(rows, key=lambda r: (r["query_row"], r["rank"])):
        table.setdefault((r["query_topic"], r["query_id"]), []).append((r["ref_topic"], r["ref_id"]))
    validator = jsonschema.Draft202012Validator(MATCH_SCHEMA)
    got: dict[tuple[str, int], list[tuple[str, int]]] = {}
    for _s, ch, _m, msg in decoded(outs["matched"], FAMILY[name], {t for t in _memlog_topics(outs["matched"], name)}):
        m = plain(msg)
        validator.validate(m)
        got[(ch.topic.removesuffix("/memlog/match"), m["frame_index"])] = [(x["topic"], x["frame_index"])
                                                                          for x in m["matches"]]
    assert got == table and got


# -- the record <-> message conventions, every family --------------------------------------------------

RECORD_EMPTY_MATRIX = {  # not written by memlog (the matrix is 5x5 or null), but an empty one must survive too
    "timestamp": {"sec": 5, "nsec": 6}, "log_time": 11, "topic": "/c", "frame_index": 2, "ms": 0.5, "ms_low": 0.5,
    "ms_high": 0.5, "ms_exact": True, "ss": 0.5, "es": 0.5, "memorability": [], "crops_scored": 0,
    "crops_surrogate": 0, "selected": True, "rejected_by": None, "thresholds": {"mt": 0.5, "st": 0.5, "et": 0.5},
    "detections": 0, "timing_ms": {}, "error": None, "shared": False, "shared_from": 2}
RECORDS = [
    {"timestamp": {"sec": 12, "nsec": 999_999_999}, "log_time": 2**62 + 5, "topic": "/cam/ä", "frame_index": 7,
     "ms": 0.612345, "ms_low": 0.5, "ms_high": 0.75, "ms_exact": False, "ss": 1.0, "es": 0.0,
     "memorability": [[0.5, None, 0.25, 0.0, 1.0]] + [[None] * 5] * 4, "crops_scored": 3, "crops_surrogate": 22,
     "selected": True, "rejected_by": None, "thresholds": {"mt": 0.5, "st": 0.6, "et": 0.4}, "detections": 0,
     "timing_ms": {"decode": 1.5, "memorability": 4000.125}, "error": None, "shared": True, "shared_from": 5},
    {"timestamp": {"sec": 0, "nsec": 0}, "log_time": 0, "topic": "/c", "frame_index": 0, "ms": None, "ms_low": None,
     "ms_high": None, "ms_exact": True, "ss": None, "es": None, "memorability": None, "crops_scored": 0,
     "crops_surrogate": 0, "selected": False, "rejected_by": "undecodable", "thresholds": {"mt": 0, "st": 1, "et": 0.25},
     "detections": 0, "timing_ms": {}, "error": "image does not decode: truncated JPEG", "shared": False,
     "shared_from": 0},
    {"timestamp": {"sec": 3, "nsec": 4}, "log_time": 9, "topic": "/c", "frame_index": 1, "ms": None, "ms_low": None,
     "ms_high": None, "ms_exact": True, "ss": 0.125, "es": None, "memorability": None, "crops_scored": 0,
     "crops_surrogate": 0, "selected": False, "rejected_by": "staticity", "thresholds": {"mt": 0.5, "st": 0.6, "et": 0.4},
     "detections": 4, "timing_ms": {"staticity": 2.0}, "error": None, "shared": False, "shared_from": 1},
    {**RECORD_EMPTY_MATRIX},
]
MATCHES = [
    {"timestamp": {"sec": 1, "nsec": 2}, "frame_index": 3, "confidence": 0.875,
     "matches": [{"topic": "/map", "frame_index": 4, "similarity": 0.875}, {"topic": "/m2", "frame_index": 0, "similarity": -0.5}],
     "matched_by": "sequence", "sequence_score": 12.5, "speed": 0.75},
    {"timestamp": {"sec": 0, "nsec": 0}, "frame_index": 0, "confidence": 0.0, "matches": [],
     "matched_by": "single frame", "sequence_score": None, "speed": None},
]


@pytest.mark.parametrize("family", ["ros2", "ros1", "json", "protobuf"])
def test_records_survive_every_family(family: str, tmp_path: Path) -> None:
    """Score and match records come back identical, through memlog and through the mcap decoders."""
    path = tmp_path / f"{family}.mcap"
    with McapLogWriter(path, profile=family if family in ("ros1", "ros2") else "") as w:
        out = MemlogChannels(w, family)
        s, m = out.add("/c/memlog/scores", SCORES), out.add("/c/memlog/match", MATCH)
        for i, rec in enumerate(RECORDS):
            out.write(s, i, rec)
        for i, rec in enumerate(MATCHES):
            out.write(m, i, rec)
        ann = out.add("/c/memlog/annotations", ANNOTATIONS)
        out.write(ann, 0, {"timestamp": {"sec": 1, "nsec": 2}, "circles": [], "points": [], "texts": [], "metadata": []})
        img = out.add("/c/memlog/maps/entropy", IMAGE)
        out.write(img, 0, {"timestamp": {"sec": 1, "nsec": 2}, "frame_id": "cam", "format": "png", "data": b"\x89PNG"})
    assert [canonical_scores(r) for r in RECORDS] == RECORDS  # the test records are complete
    with open_log(path) as log:
        got = {t: [decode_record(SCORES if t.endswith("scores") else MATCH, x.channel, x.data)
                   for x in log.messages([t])] for t in ("/c/memlog/scores", "/c/memlog/match")}
    assert got == {"/c/memlog/scores": RECORDS, "/c/memlog/match": MATCHES}
    assert read_scores(path) == {"/c": sorted(RECORDS, key=lambda r: r["frame_index"])}
    ext: dict[str, list[Any]] = {}
    for _s, ch, _m, msg in decoded(path, family):
        ext.setdefault(ch.topic, []).append(plain(msg))
    assert [record_of_scores(x, ENCODINGS[family][0]) for x in ext["/c/memlog/scores"]] == RECORDS
    assert [record_of_match(x, ENCODINGS[family][0]) for x in ext["/c/memlog/match"]] == MATCHES
    img_msg = ext["/c/memlog/maps/entropy"][0]
    assert img_msg["format"] == "png"
    if family in ("ros1", "ros2"):
        assert img_msg["header"]["stamp"] == {"sec": 1, "nsec": 2} and bytes(img_msg["data"]) == b"\x89PNG"


def test_a_damaged_score_message_is_reported_and_skipped(tmp_path: Path) -> None:
    path = tmp_path / "d.mcap"
    with McapLogWriter(path, profile="ros2") as w:
        out = MemlogChannels(w, "ros2")
        s = out.add("/c/memlog/scores", SCORES)
        out.write(s, 0, RECORDS[0])
        w.write(s, 1, b"\x00\x01\x00\x00\x07")  # a CDR header and a few bytes: not a FrameScores
        out.write(s, 2, RECORDS[2])
    from memlog.io.records import ReadReport

    report = ReadReport(str(path))
    assert read_scores(path, report=report) == {"/c": sorted([RECORDS[0], RECORDS[2]], key=lambda r: r["frame_index"])}
    assert report.bad_messages == 1 and "message 1" in report.warnings[0] and "/c/memlog/scores" in report.warnings[0]


def test_old_json_scoring_runs_still_read(tmp_path: Path) -> None:
    """A scoring run of an older memlog (JSON scores in a ros2 log, an undecodable record without
    ms_low/ms_high) reads into the same records."""
    import json

    path = tmp_path / "old.mcap"
    old = {k: v for k, v in RECORDS[1].items() if k not in ("ms_low", "ms_high")}
    with McapLogWriter(path, profile="ros2") as w:
        cid = w.add_json_channel("/c/memlog/scores", "memlog.FrameScores", FRAME_SCORES)
        w.write(cid, 0, json.dumps(old).encode())
    assert read_scores(path) == {"/c": [RECORDS[1]]}


def test_window_with_stride_keeps_the_family(out_dir: Path, tmp_path: Path) -> None:
    """A strided scoring run of a ROS 2 log is still readable by rosbags and read back whole."""
    cfg = ScoreConfig()
    out = tmp_path / "s.mcap"
    score(FIXTURES / "demo.mcap", out, cfg, FrameWindow(stride=3), scorer=FakeScorer(cfg))
    counts = anyreader_read_all([out])
    recs = read_scores(out)
    assert {t: len(r) for t, r in recs.items()} == {t.removesuffix("/memlog/scores"): n for t, n in counts.items()
                                                    if t.endswith("/memlog/scores")}

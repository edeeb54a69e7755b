"""Whitening: the fit against a direct PCA, storage with the map (hash checked), the identical
transform on queries, and refusal of queries described without it."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from memlog.descriptors.auto import AUTO_LEARNED, AUTO_SMALL, choose_descriptor, resolve_descriptor
from memlog.descriptors.base import DescriptorMeta, check_compatible, l2_normalize
from memlog.descriptors.registry import make_describer
from memlog.matching import SequenceConfig
from memlog.descriptors.table import DescriptorTable
from memlog.descriptors.whitening import (
    WhitenedDescriber,
    Whitening,
    WhiteningFitter,
    fit_whitening,
    whitening_dim,
)
from memlog.errors import DescriptorError
from memlog.io import FrameWindow, open_log
from memlog.outputs.descriptor_table import read_descriptors, write_descriptors
from memlog.selection.config import SelectionConfig
from memlog.steps.localize import LocalizeConfig, localize
from memlog.steps.map import MapConfig, make_map
from tests.conftest import FIXTURES, shared

EUROC = "euroc_micro_ros2.mcap"
EUROC_TOPIC = "/cam0/image_raw"


def _data(n: int = 300, d: int = 20, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    scales = np.linspace(3.0, 0.2, d)
    x = rng.normal(size=(n, d)) * scales @ np.linalg.qr(rng.normal(size=(d, d)))[0] + 0.5
    return l2_normalize(x)


def test_whitened_coordinates_have_unit_covariance() -> None:
    x = _data()
    w = fit_whitening(x, max_dim=8, eps=0.0)
    assert w.dim_in == 20 and w.dim_out == 8 and w.n_fit == 300
    y = (x.astype(np.float64) - x.mean(axis=0)) @ w.proj.astype(np.float64)  # before the final normalisation
    np.testing.assert_allclose(np.cov(y, rowvar=False, bias=True), np.eye(8), atol=1e-4)
    # the kept directions are the top principal directions (compare the spanned subspaces)
    _, _, vt = np.linalg.svd(x - x.mean(axis=0), full_matrices=False)
    q_w, _ = np.linalg.qr(w.proj.astype(np.float64))
    np.testing.assert_allclose(np.linalg.svd(vt[:8] @ q_w, compute_uv=False), np.ones(8), atol=1e-4)
    out = w.apply(x)
    assert out.shape == (300, 8) and np.allclose(np.linalg.norm(out, axis=1), 1.0, atol=1e-5)


def test_streaming_fit_equals_one_shot_and_dimension_rule() -> None:
    x = _data(n=120)
    f = WhiteningFitter(20)
    for start in range(0, 120, 17):
        f.add(x[start : start + 17])
    a, b = f.fit(), fit_whitening(x)
    assert a.sha256 == b.sha256 or np.allclose(a.proj, b.proj, atol=1e-5)
    assert a.dim_out == whitening_dim(120, 20) == min(512, 20, 120 // 2) == 20
    assert whitening_dim(100, 384) == 50 and whitening_dim(10_000, 384) == 384 and whitening_dim(10_000, 384, 32) == 32
    assert whitening_dim(10_000, 2048) == 512
    with pytest.raises(DescriptorError, match="at least"):
        fit_whitening(x[:5])


def test_transform_round_trip_and_tampering_refused() -> None:
    w = fit_whitening(_data(), max_dim=6)
    d = json.loads(w.to_json())
    back = Whitening.from_dict(d)
    assert back.sha256 == w.sha256 and np.array_equal(back.proj, w.proj) and np.array_equal(back.mean, w.mean)
    proj = np.frombuffer(__import__("base64").b64decode(d["proj"]), "<f4").copy()
    proj[0] += 1e-3
    d["proj"] = __import__("base64").b64encode(proj.tobytes()).decode()
    with pytest.raises(DescriptorError, match="sha256"):
        Whitening.from_dict(d)


def _table(desc: np.ndarray, meta: DescriptorMeta, whitening: Whitening | None = None) -> DescriptorTable:
    n = len(desc)
    return DescriptorTable(topic=["/c"] * n, frame_index=np.arange(n), log_time_ns=np.arange(n),
                           stamp_ns=np.arange(n), descriptors=desc, meta=meta, whitening=whitening)


def test_parquet_stores_the_transform_with_its_hash(tmp_path: Path) -> None:
    x = _data()
    w = fit_whitening(x, max_dim=6)
    meta = DescriptorMeta("thumbnail", "1", 6, None, {"width": 64}, whitening=w.sha256)
    path = write_descriptors(tmp_path / "map.parquet", _table(w.apply(x), meta, w))
    back = read_descriptors(path)
    assert back.meta == meta and back.whitening is not None and back.whitening.sha256 == w.sha256
    np.testing.assert_array_equal(back.whitening.apply(x), w.apply(x))
    # a transform edited in the file is refused when read
    t = pq.read_table(path)
    md = dict(t.schema.metadata)
    wd = json.loads(md[b"memlog.whitening"])
    wd["eps"] = wd["eps"] * 2
    md[b"memlog.whitening"] = json.dumps(wd).encode()
    pq.write_table(t.replace_schema_metadata(md), tmp_path / "edited.parquet")
    with pytest.raises(DescriptorError, match="sha256"):
        read_descriptors(tmp_path / "edited.parquet")


def test_unwhitened_or_differently_whitened_query_refused() -> None:
    w1, w2 = fit_whitening(_data(seed=1), max_dim=6), fit_whitening(_data(seed=2), max_dim=6)
    base = DescriptorMeta("thumbnail", "1", 20, None, {})
    m1 = DescriptorMeta("thumbnail", "1", 6, None, {}, whitening=w1.sha256)
    with pytest.raises(DescriptorError, match="described without whitening"):
        check_compatible(m1, base)
    with pytest.raises(DescriptorError, match="whitened with transform"):
        check_compatible(m1, DescriptorMeta("thumbnail", "1", 6, None, {}, whitening=w2.sha256))
    with pytest.raises(DescriptorError, match="map's are not"):
        check_compatible(base, m1)
    check_compatible(m1, DescriptorMeta("thumbnail", "1", 6, None, {}, whitening=w1.sha256))


def test_auto_rule_by_frame_size() -> None:
    assert choose_descriptor("auto", (64, 32)).chosen == AUTO_SMALL
    assert choose_descriptor("auto", (376, 240)).chosen == AUTO_LEARNED
    assert choose_descriptor("auto", (960, 540)).chosen == AUTO_LEARNED
    assert choose_descriptor("auto", (200, 111)).chosen == AUTO_SMALL  # the short side decides
    assert choose_descriptor("thumbnail", (960, 540)).chosen == "thumbnail"  # a named kind is kept
    with open_log(FIXTURES / "demo.mcap") as r:  # 96 x 72 frames
        c = resolve_descriptor("auto", r, "/camera/image/compressed")
    assert c.chosen == AUTO_SMALL and c.frame_size == (96, 72) and c.rule and "112" in c.rule


def _records(log: Path, topic: str) -> dict[str, list[dict]]:
    """Score records (the map step's input) giving every frame the same passing scores."""
    with open_log(log) as r:
        return {topic: [{"frame_index": f.index, "log_time": f.log_time_ns, "ms": 0.9, "ss": 1.0, "es": 0.9}
                        for f in r.frames([topic])]}


def test_map_whitens_by_default_and_localize_applies_the_same_transform(tmp_path: Path) -> None:
    log = shared(EUROC)
    recs = _records(log, EUROC_TOPIC)
    res = make_map(log, tmp_path / "map.mcap", MapConfig(select=SelectionConfig(mode="paper", mt=0, st=0, et=0),
                                                         topics=(EUROC_TOPIC,), descriptor="thumbnail"),
                   scores=recs)
    table = read_descriptors(res.descriptors)  # type: ignore[arg-type]
    w = table.whitening
    assert w is not None and table.meta.whitening == w.sha256 and w.n_fit == 95
    assert w.dim_in == 2048 and w.dim_out == table.meta.dim == whitening_dim(95, 2048)
    assert res.whitening is not None and res.whitening["sha256"] == w.sha256
    with open_log(res.output) as m:
        meta = dict(m.metadata())["memlog_map"]
        assert json.loads(meta["whitening"])["sha256"] == w.sha256
        assert json.loads(meta["descriptor"])["chosen"] == "thumbnail"
    # the stored descriptors are the raw describer's output through the stored transform
    with open_log(log) as r:
        imgs = [f.decode_bgr() for f in r.frames([EUROC_TOPIC])]
    raw = make_describer("thumbnail").describe(imgs)
    np.testing.assert_allclose(table.descriptors, w.apply(raw), atol=1e-5)
    # localize describes the query with the same transform: each frame finds itself
    qcache = tmp_path / "q.parquet"
    loc = localize(res.descriptors, log, tmp_path / "m.csv", LocalizeConfig(k=1, window=FrameWindow((EUROC_TOPIC,))),
                   query_descriptors=qcache)
    assert loc.n_queries == 95 and not loc.query_descriptors_reused
    qt = read_descriptors(qcache)
    assert qt.meta.whitening == w.sha256 and qt.whitening is None  # a query records the hash, not the transform
    np.testing.assert_allclose(qt.descriptors, w.apply(raw), atol=1e-5)
    import pyarrow.csv as pacsv

    rows = pacsv.read_csv(tmp_path / "m.csv").to_pylist()
    # the EuRoC slice is a MAV standing on the floor (median optical flow under a pixel over its
    # 4.7 s): nearly all one stop, so with stops left out (the default) a standing frame takes its
    # stop's first frame's match, which is that frame itself
    mi = qt.moving_index
    assert mi is not None and (mi == 0).sum() >= 80
    first_of_stop = {int(v): int(np.flatnonzero(mi == v)[0]) for v in np.unique(mi)}
    assert [r["ref_id"] for r in rows] == [first_of_stop[int(v)] for v in mi]
    # with the stops kept each frame finds itself
    kept = localize(res.descriptors, log, tmp_path / "m_kept.csv",
                    LocalizeConfig(k=1, window=FrameWindow((EUROC_TOPIC,)), sequence=SequenceConfig(stops=False)),
                    query_descriptors=qcache)
    assert kept.query_descriptors_reused
    rows = pacsv.read_csv(tmp_path / "m_kept.csv").to_pylist()
    assert len(rows) == 95 and all(r["ref_id"] == r["query_id"] for r in rows)
    # query descriptors described without the transform are refused (and described again)
    unwhite = DescriptorTable(topic=qt.topic, frame_index=qt.frame_index, log_time_ns=qt.log_time_ns,
                              stamp_ns=qt.stamp_ns, descriptors=raw, meta=make_describer("thumbnail").meta(),
                              extra=qt.extra)
    write_descriptors(qcache, unwhite)
    loc2 = localize(res.descriptors, log, tmp_path / "m2.csv",
                    LocalizeConfig(k=1, window=FrameWindow((EUROC_TOPIC,))), query_descriptors=qcache)
    assert not loc2.query_descriptors_reused and read_descriptors(qcache).meta.whitening == w.sha256
    # and matching unwhitened query descriptors against the map directly is refused
    with pytest.raises(DescriptorError, match="without whitening"):
        check_compatible(table.meta, unwhite.meta)


def test_map_without_whitening_and_with_auto(tmp_path: Path) -> None:
    log = shared(EUROC)
    recs = _records(log, EUROC_TOPIC)
    res = make_map(log, tmp_path / "m.mcap", MapConfig(select=SelectionConfig(mode="paper", mt=0, st=0, et=0),
                                                       topics=(EUROC_TOPIC,), descriptor="thumbnail", whiten=False),
                   scores=recs)
    t = read_descriptors(res.descriptors)  # type: ignore[arg-type]
    assert t.whitening is None and t.meta.whitening is None and t.meta.dim == 2048
    assert MapConfig().descriptor == "auto" and MapConfig().whiten
    res2 = make_map(log, tmp_path / "a.mcap", MapConfig(select=SelectionConfig(mode="paper", mt=0, st=0, et=0),
                                                        topics=(EUROC_TOPIC,)), scores=recs)
    t2 = read_descriptors(res2.descriptors)  # type: ignore[arg-type]
    assert t2.meta.kind == AUTO_LEARNED and t2.extra["descriptor_choice"]["frame_size"] == [376, 240]
    assert t2.whitening is not None and t2.whitening.dim_in == 384


def test_whitened_describer_metadata() -> None:
    x = _data(n=64, d=2048, seed=3)
    w = fit_whitening(x)
    d = WhitenedDescriber(make_describer("thumbnail"), w)
    assert d.meta().whitening == w.sha256 and d.dim == w.dim_out == 32 and d.meta().kind == "thumbnail"
    with pytest.raises(DescriptorError, match="expects"):
        WhitenedDescriber(make_describer("thumbnail", width=32, height=16), w)


def _resized_copy(src: Path, dst: Path, scale: float) -> None:
    """A Foxglove-JSON MCAP of ``src``'s frames resized by ``scale`` (the rule's mechanics on
    upscaled / downscaled EuRoC copies; same schema, channel and stamps)."""
    import base64

    import cv2
    from mcap.reader import make_reader
    from mcap.writer import Writer

    with open(src, "rb") as f, open(dst, "wb") as out:
        r = make_reader(f)
        summary = r.get_summary()
        assert summary is not None
        w = Writer(out)
        w.start()
        ids: dict[int, int] = {}
        for sc in summary.schemas.values():
            ids[sc.id] = w.register_schema(sc.name, sc.encoding, sc.data)
        chans = {c.id: w.register_channel(c.topic, c.message_encoding, ids[c.schema_id]) for c in summary.channels.values()}
        for _s, ch, m in r.iter_messages():
            msg = json.loads(m.data)
            img = cv2.imdecode(np.frombuffer(base64.b64decode(msg["data"]), np.uint8), cv2.IMREAD_UNCHANGED)
            img = cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR)
            msg["data"] = base64.b64encode(cv2.imencode(".jpg", img)[1].tobytes()).decode()
            w.add_message(chans[ch.id], m.log_time, json.dumps(msg).encode(), m.publish_time)
        w.finish()


@pytest.mark.parametrize(("scale", "size", "kind"), [(0.25, (94, 60), AUTO_SMALL), (0.5, (188, 120), AUTO_LEARNED),
                                                     (2.0, (752, 480), AUTO_LEARNED)])
def test_auto_rule_on_resized_euroc(tmp_path: Path, scale: float, size: tuple[int, int], kind: str) -> None:
    copy = tmp_path / "euroc.mcap"
    _resized_copy(shared("euroc_micro_foxglove.mcap"), copy, scale)
    with open_log(copy) as r:
        c = resolve_descriptor("auto", r, "/camera/image/compressed")
    assert c.frame_size == size and c.chosen == kind


def test_blank_frames_stay_zero_after_whitening() -> None:
    """The describers' rule: a frame with no information is the zero vector, which matches nothing in
    particular (similarity 0 with every map frame). Whitening keeps it: a zero row stays a zero row,
    as do rows with NaN (both are the rows the fit leaves out), instead of all becoming the one unit
    vector normalize(-mean @ proj) that would match every blank map frame with similarity 1."""
    from memlog.descriptors.search import match

    x = _data()  # mean far from 0 (the data are offset), as real descriptors' is
    w = fit_whitening(x, max_dim=8)
    blank = np.zeros((3, 20), dtype=np.float32)
    refs = w.apply(np.concatenate([x[:10], blank, x[10:20]]))  # a map with three blank frames
    assert np.all(refs[10:13] == 0.0)
    assert np.allclose(np.linalg.norm(np.delete(refs, [10, 11, 12], axis=0), axis=1), 1.0, atol=1e-5)
    nan_row = np.full((1, 20), np.nan, dtype=np.float32)
    part_nan = x[:1].copy()
    part_nan[0, 3] = np.nan
    with np.errstate(all="raise"):
        q = w.apply(np.concatenate([blank[:1], nan_row, part_nan, x[20:21]]))
    assert np.all(q[:3] == 0.0) and np.linalg.norm(q[3]) == pytest.approx(1.0, abs=1e-5)
    _, sims = match(q[:1], refs, k=len(refs))
    np.testing.assert_array_equal(sims, np.zeros((1, len(refs)), dtype=np.float32))
    idx, sims = match(q[3:], refs, k=len(refs))
    assert sims[0][np.isin(idx[0], [10, 11, 12])].tolist() == [0.0, 0.0, 0.0]  # a real query: blank refs 0
    # the describer: a black frame gives the zero vector before and after whitening
    base = make_describer("thumbnail", width=32, height=16)  # 512-d: a quick fit
    wd = WhitenedDescriber(base, fit_whitening(_data(n=64, d=512, seed=3)))
    rng = np.random.default_rng(0)
    black = np.zeros((48, 64, 3), dtype=np.uint8)
    textured = rng.integers(0, 256, size=(48, 64, 3), dtype=np.uint8)
    assert np.all(base.describe([black]) == 0.0)
    out = wd.describe([black, textured])
    assert out.shape == (2, wd.dim) and np.all(out[0] == 0.0)
    assert np.linalg.norm(out[1]) == pytest.approx(1.0, abs=1e-5)

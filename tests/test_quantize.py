"""Fast-mode (int8) ResMem: agreement with the fp32 model on real frames, files, errors.

The session fixture prepares the fp32 model and the int8 model (both no-ops when cached; the int8
calibration takes ~5 min on 2 cores when it is not), so these tests are never skipped.

Tolerances come from measurements on 80 frames (40 EuRoC, 40 Nordland; 2000 crops) with 7-bit
weights on an AVX2 CPU: per-crop |int8 - fp32| max 0.108, mean 0.016, p99 0.057; frame score MS
max 0.018, mean 0.007 (8-bit weights on an AVX-512 VNNI CPU: crop max 0.046 on 8 frames). The
limits below leave about a factor 2 of margin. Fast mode's decisions are checked against exact
mode's with the bounds the model's sidecar records.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt
import onnx
import onnxruntime as ort
import pytest

from memlog.errors import ModelError
from memlog.io import open_log
from memlog.models import quantize
from memlog.models.fetch import sha256_file
from memlog.runtime import current, use
from memlog.models.quantize import (
    CALIBRATION_IMAGES,
    QUANTIZER_VERSION,
    SETTINGS,
    calibration_crops,
    prepare_fast_models,
    quantize_resmem,
    resmem_int8_bounds,
    resmem_int8_path,
    validation_crops,
)
from memlog.models.resmem import FEATURES_NAME, FRAME, INPUT_NAME, OUTPUT_NAME, crops_from_frame, prepare_resmem
from memlog.scoring.memorability import FastMemorability, Memorability, memorability_score
from tests.conftest import shared

Array = npt.NDArray[Any]

pytestmark = pytest.mark.shared

CROP_MAX_TOL = 0.2
CROP_MEAN_TOL = 0.04
MS_TOL = 0.04
POOL_COS_MIN = 0.8


def _frames(name: str, topic: str, indices: set[int]) -> list[Array]:
    """Frames ``indices`` of ``topic``, decoded to BGR and resized to 1135 x 1135."""
    out: dict[int, Array] = {}
    with open_log(shared(name)) as log:
        for frame in log.frames([topic]):
            if frame.index in indices:
                bgr = np.asarray(frame.decode_bgr())
                out[frame.index] = cv2.resize(bgr, (FRAME, FRAME), interpolation=cv2.INTER_LINEAR)
                if len(out) == len(indices):
                    break
    assert sorted(out) == sorted(indices)
    return [out[i] for i in sorted(out)]


@pytest.fixture(scope="session")
def frames() -> list[Array]:
    """Two EuRoC frames (376x240 mono JPEG) and two Nordland frames (64x32 PNG)."""
    return (_frames("euroc_micro_ros2.mcap", "/cam0/image_raw/compressed", {10, 60})
            + _frames("nordland_dev_summer.mcap", "/camera/image_raw/compressed", {150, 550}))


@pytest.fixture(scope="session")
def fp32_path() -> Path:
    return prepare_resmem(progress=False)


@pytest.fixture(scope="session")
def int8_path(fp32_path: Path) -> Path:
    return prepare_fast_models(quiet=True)


def _session(path: Path) -> ort.InferenceSession:
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 2
    opts.inter_op_num_threads = 1
    return ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])


@pytest.fixture(scope="session")
def outputs(fp32_path: Path, int8_path: Path, frames: list[Array]) -> dict[str, list[Array]]:
    """(memorability [100], resnet_pool [100,2048]) of both models on the 100 crops of 4 frames."""
    crops = np.concatenate([crops_from_frame(f) for f in frames])
    res: dict[str, list[Array]] = {}
    for key, path in (("fp32", fp32_path), ("int8", int8_path)):
        sess = _session(path)
        parts = [sess.run([OUTPUT_NAME, FEATURES_NAME], {INPUT_NAME: crops[i:i + 25]}) for i in range(0, len(crops), 25)]
        res[key] = [np.concatenate([p[0] for p in parts]).reshape(-1), np.concatenate([p[1] for p in parts])]
    return res


# ---------------------------------------------------------------------------------------------
# the prepared model


def test_int8_path_is_prepared_model(int8_path: Path) -> None:
    assert resmem_int8_path() == int8_path
    assert int8_path.name == "resmem-1.1.6-int8.onnx"


def test_same_io_names_and_shapes(fp32_path: Path, int8_path: Path) -> None:
    def io(path: Path) -> tuple[list[tuple[str, list[int | str]]], list[tuple[str, list[int | str]]]]:
        g = onnx.load(str(path), load_external_data=False).graph

        def dims(v: onnx.ValueInfoProto) -> list[int | str]:
            return [d.dim_param or d.dim_value for d in v.type.tensor_type.shape.dim]

        return [(v.name, dims(v)) for v in g.input], [(v.name, dims(v)) for v in g.output]

    ins, outs = io(int8_path)
    assert (ins, outs) == io(fp32_path)
    assert ins == [(INPUT_NAME, ["N", 3, 227, 227])]
    assert outs == [(OUTPUT_NAME, ["N", 1]), (FEATURES_NAME, ["N", 2048])]
    sess = _session(int8_path)
    x = np.zeros((3, 3, 227, 227), np.float32)
    mem, pool = sess.run([OUTPUT_NAME, FEATURES_NAME], {INPUT_NAME: x})
    assert mem.shape == (3, 1) and mem.dtype == np.float32
    assert pool.shape == (3, 2048) and pool.dtype == np.float32


def test_int8_graph_is_quantised(int8_path: Path) -> None:
    """The ResNet trunk convs carry int8 weights; the head stays float."""
    g = onnx.load(str(int8_path), load_external_data=False).graph
    ops = [n.op_type for n in g.node]
    assert ops.count("QuantizeLinear") > 100 and ops.count("DequantizeLinear") > 300
    int8_weights = {i.name for i in g.initializer if i.data_type == onnx.TensorProto.INT8}
    assert "features.layer3.20.conv2.weight_quantized" in int8_weights
    assert not any(name.startswith("fc") for name in int8_weights)
    assert int8_path.stat().st_size < 0.8 * (int8_path.parent / "resmem-1.1.6.onnx").stat().st_size


def test_outputs_close_to_fp32(outputs: dict[str, list[Array]]) -> None:
    a, b = outputs["fp32"][0], outputs["int8"][0]
    assert np.all((b >= 0) & (b <= 1))
    diff = np.abs(a - b)
    print(f"\n[int8] |crop diff| max {diff.max():.4f} mean {diff.mean():.4f}")
    assert diff.max() <= CROP_MAX_TOL
    assert diff.mean() <= CROP_MEAN_TOL


def test_frame_scores_close_to_fp32(outputs: dict[str, list[Array]]) -> None:
    ms = {k: [memorability_score(v[0][i:i + 25].reshape(5, 5).astype(np.float64)) for i in range(0, 100, 25)]
          for k, v in outputs.items()}
    diff = np.abs(np.subtract(ms["fp32"], ms["int8"]))
    print(f"\n[int8] |MS diff| {np.round(diff, 4).tolist()}")
    assert diff.max() <= MS_TOL
    # decisions at the paper's thresholds agree on these frames (MS is far from them)
    for mt in (0.45, 0.5, 0.55):
        assert [m >= mt for m in ms["fp32"]] == [m >= mt for m in ms["int8"]]


def test_pooled_features_close_to_fp32(outputs: dict[str, list[Array]]) -> None:
    a, b = outputs["fp32"][1].astype(np.float64), outputs["int8"][1].astype(np.float64)
    cos = np.sum(a * b, axis=1) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1))
    print(f"\n[int8] resnet_pool cosine min {cos.min():.3f} median {np.median(cos):.3f}")
    assert cos.min() >= POOL_COS_MIN


def test_memorability_scorer_runs_int8(int8_path: Path, frames: list[Array]) -> None:
    res = Memorability(int8_path, threads=2, batch=25)(frames[0], threshold=0.5)
    assert res.passed is not None
    full = Memorability(int8_path, threads=2, batch=25)(frames[0])
    assert full.exact and full.ms is not None and 0.0 <= full.ms <= 1.0


# ---------------------------------------------------------------------------------------------
# sidecar


def test_sidecar_hashes_match_files(fp32_path: Path, int8_path: Path) -> None:
    side = json.loads(int8_path.with_name(int8_path.name + ".json").read_text())
    assert side["quantizer_version"] == QUANTIZER_VERSION
    assert side["source_onnx_sha256"] == sha256_file(fp32_path)
    assert side["sha256"] == sha256_file(int8_path)
    assert side["bytes"] == int8_path.stat().st_size
    assert side["settings"] == json.loads(json.dumps(SETTINGS))
    cal = side["calibration"]
    assert cal["images"] == list(CALIBRATION_IMAGES[:len(cal["images"])])
    assert cal["n_crops"] == 25 * len(cal["images"]) <= 500


def test_sidecar_records_error_bounds(int8_path: Path, fp32_path: Path) -> None:
    """The bounds are the measured maxima on held-out crops times the factor, and those crops
    are what validation_crops produces here, none of them a calibration crop."""
    side = json.loads(int8_path.with_name(int8_path.name + ".json").read_text())
    err = side["crop_error"]
    assert 0.0 < err["mean"] <= err["p99"] <= err["max"] < 0.5
    assert 0.0 < err["frame_mean"] <= err["frame_max"] <= err["max"]
    f = SETTINGS["bound_factor"]
    assert side["epsilon"] == pytest.approx(min(1.0, f * err["max"]))
    assert side["delta"] == pytest.approx(min(1.0, f * err["frame_max"]))
    assert resmem_int8_bounds(int8_path) == (side["epsilon"], side["delta"], err["bias"])
    assert abs(err["bias"]) < err["max"]
    val = validation_crops()
    assert side["validation"]["crops_sha256"] == quantize._crops_sha256(val)
    assert err["n"] == len(val) == 25 * err["frames"]
    cal = calibration_crops(len(side["calibration"]["images"]))
    assert not {c.tobytes() for c in val} & {c.tobytes() for c in cal}


def test_fast_scorer_agrees_with_exact(int8_path: Path, fp32_path: Path, frames: list[Array]) -> None:
    """Fast mode makes exact mode's decision at thresholds far from and close to each frame's
    MS; beyond twice the frame bound the fp32 model is never run."""
    eps, delta, bias = resmem_int8_bounds(int8_path)
    fp32 = Memorability(fp32_path, threads=2, batch=5)
    fast = FastMemorability(int8_path, fp32, eps, delta, bias, threads=2)
    for frame in frames:
        ms = fp32(frame).ms
        assert ms is not None
        est = fast(frame)
        assert est.n_scored == 0 and est.n_surrogate == 25 and est.ms is not None
        assert est.ms_low <= ms <= est.ms_high and abs(est.ms - ms) <= delta
        for t in (ms - 2.5 * delta, ms - 0.01, ms + 0.01, ms + 2.5 * delta):
            r = fast(frame, threshold=t)
            assert r.passed == (ms >= t), (t, ms, r)
            if abs(ms - t) > 2 * delta:
                assert r.n_scored == 0


def test_fast_mode_scorer_records(int8_path: Path, frames: list[Array]) -> None:
    """Scorer(mode='fast'): same decision as exact mode, surrogate crops recorded."""
    from memlog.scoring.config import ScoreConfig
    from memlog.scoring.scorer import Scorer

    exact = Scorer(ScoreConfig(mt=0.0, st=0.0, et=0.0, all_scores=True)).score(frames[2])
    assert exact.ms is not None
    cfg = dict(mt=round(exact.ms, 3), st=0.0, et=0.0)
    a = Scorer(ScoreConfig(**cfg)).score(frames[2])
    b = Scorer(ScoreConfig(mode="fast", **cfg)).score(frames[2])
    assert a.selected == b.selected == (exact.ms >= cfg["mt"])
    assert b.crops_surrogate == 25 and a.crops_surrogate == 0
    rec = b.to_json()
    assert rec["crops_surrogate"] == 25
    assert 0 < rec["crops_scored"] <= 25  # MT within the surrogate's error: refined with fp32
    assert rec["ms_exact"] == (rec["crops_scored"] == 25)


def test_calibration_set_matches_sidecar(int8_path: Path) -> None:
    """The cached model was calibrated on exactly what calibration_crops produces here."""
    cal = json.loads(int8_path.with_name(int8_path.name + ".json").read_text())["calibration"]
    crops = calibration_crops(len(cal["images"]))
    assert quantize._crops_sha256(crops) == cal["crops_sha256"]


# ---------------------------------------------------------------------------------------------
# calibration set


def test_calibration_crops_deterministic() -> None:
    a = calibration_crops(2)
    b = calibration_crops(2)
    assert a.shape == (50, 3, 227, 227) and a.dtype == np.float32 and a.flags.c_contiguous
    assert np.array_equal(a, b)
    assert 0.0 <= float(a.min()) and float(a.max()) <= 1.0
    assert float(a.std()) > 0.05  # real photographs, not blank
    # crop k of image 0 is the row-major grid cell of the rescaled astronaut photo (RGB)
    import skimage.data

    photo = np.asarray(skimage.data.astronaut())  # type: ignore[no-untyped-call]
    rgb = cv2.resize(photo, (FRAME, FRAME), interpolation=cv2.INTER_LINEAR)
    cell = rgb[227:454, 454:681].transpose(2, 0, 1).astype(np.float32) / np.float32(255.0)
    np.testing.assert_array_equal(a[7], cell)


def test_all_calibration_images_load() -> None:
    crops = calibration_crops(len(CALIBRATION_IMAGES))
    assert crops.shape[0] == 25 * len(CALIBRATION_IMAGES)


def test_calibration_crops_rejects_bad_count() -> None:
    with pytest.raises(ModelError, match="n_images"):
        calibration_crops(0)
    with pytest.raises(ModelError, match="n_images"):
        calibration_crops(len(CALIBRATION_IMAGES) + 1)


def test_quantize_rejects_bad_crops(tmp_path: Path, fp32_path: Path) -> None:
    with pytest.raises(ModelError, match="calibration crops"):
        quantize_resmem(fp32_path, tmp_path / "x.onnx", np.zeros((2, 3, 224, 224), np.float32))
    with pytest.raises(ModelError, match="calibration crops"):
        quantize_resmem(fp32_path, tmp_path / "x.onnx", np.zeros((2, 3, 227, 227), np.float64))
    with pytest.raises(ModelError, match="memlog models prepare"):
        quantize_resmem(tmp_path / "missing.onnx", tmp_path / "x.onnx", np.zeros((2, 3, 227, 227), np.float32))
    assert not (tmp_path / "x.onnx").exists()


# ---------------------------------------------------------------------------------------------
# missing / stale model


def test_missing_model_raises(tmp_path: Path) -> None:
    with use(current().replace(cache_dir=str(tmp_path))), pytest.raises(ModelError, match="memlog models prepare"):
        resmem_int8_path()


def test_stale_model_raises(tmp_path: Path, fp32_path: Path) -> None:
    """A cached int8 file whose sidecar does not match (version, source, size, CPU) is not used."""
    models = tmp_path / "models"
    models.mkdir()
    # the fp32 model "prepared" in the temporary cache: a link plus its real sidecar
    side = fp32_path.with_name(fp32_path.name + ".json")
    (models / fp32_path.name).symlink_to(fp32_path)
    (models / side.name).write_text(side.read_text())
    src_sha = json.loads(side.read_text())["sha256"]
    target = models / "resmem-1.1.6-int8.onnx"
    target.write_bytes(b"not a model but the right size")
    target_side = target.with_name(target.name + ".json")
    good = {"format": 2, "quantizer_version": QUANTIZER_VERSION, "source_onnx_sha256": src_sha,
            "bytes": target.stat().st_size, "cpu_vnni": quantize.cpu_has_vnni()}
    with use(current().replace(cache_dir=str(tmp_path))):
        target_side.write_text(json.dumps(good))
        assert resmem_int8_path() == target  # the cheap check accepts a matching sidecar
        for key, bad in (("quantizer_version", "0"), ("source_onnx_sha256", "0" * 64), ("bytes", 1), ("format", 1),
                         ("cpu_vnni", not quantize.cpu_has_vnni())):  # built for another kind of CPU
            target_side.write_text(json.dumps({**good, key: bad}))
            with pytest.raises(ModelError, match="memlog models prepare"):
                resmem_int8_path()
        target_side.unlink()
        with pytest.raises(ModelError, match="memlog models prepare"):
            resmem_int8_path()


def test_whole_frame_fit_bounds_held_out_frames(int8_path: Path, fp32_path: Path) -> None:
    """The whole-frame estimate's recorded error covers held-out frames recomputed here, and fast
    mode's first tier uses exactly that fit."""
    import json

    from memlog.models import cache
    from memlog.models.quantize import FRAME_FIT_FILE, _frames, frame_crop, frame_fit
    from memlog.models.resmem import crop_weights, run_crops
    from memlog.models.runtime import make_session

    side = json.loads(cache.model_path(FRAME_FIT_FILE).read_text())
    fit = frame_fit()
    assert fit == {"a": side["a"], "b": side["b"], "delta": side["delta"]}
    worst = max(side["held_out_max_error"], side["fit_max_error"])
    assert side["delta"] == pytest.approx(min(1.0, 1.5 * worst)) and side["n_held_out"] >= 10
    s32, s8 = make_session(fp32_path, device="cpu"), make_session(int8_path, device="cpu")
    w = crop_weights(None).reshape(-1)
    for f in _frames(12, held_out=True)[:3]:
        f1135 = cv2.resize(f, (FRAME, FRAME), interpolation=cv2.INTER_LINEAR)
        ms = float(np.dot(w, run_crops(s32, crops_from_frame(f1135)).astype(np.float64)))
        est = fit["a"] * float(run_crops(s8, frame_crop(f1135))[0]) + fit["b"]
        assert abs(est - ms) <= side["held_out_max_error"] + 1e-6

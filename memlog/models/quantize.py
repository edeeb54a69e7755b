"""Fast-mode ResMem: static int8 (QDQ) quantisation of the prepared ResMem ONNX model.

``memlog models prepare resmem-int8`` calls :func:`prepare_resmem_int8`, which calibrates and
quantises the prepared fp32 model (:func:`memlog.models.resmem.resmem_onnx_path`) with
:mod:`onnxruntime.quantization` and caches it as ``cache_dir()/models/resmem-1.1.6-int8.onnx``
with its cache sidecar (:mod:`memlog.models.cache`) (hashes, settings, calibration set, measured error bounds).
:func:`resmem_int8_path` returns the cached model, or raises :class:`ModelError` when it is
missing or stale. The int8 model has the fp32 model's input and outputs, so
:class:`memlog.scoring.memorability.Memorability` runs it as is.

Calibration data: crops of the real photographs that ship inside scikit-image (no network, no
extra files), each rescaled to 1135 x 1135 with ``cv2.INTER_LINEAR`` and cut into the 25 crops
of :func:`memlog.models.resmem.crops_from_frame`, exactly as a camera frame would be.

Error bounds: after quantising, both models score held-out frames (:func:`validation_crops`:
the photos not calibrated on, and every photo as a low-resolution camera would see it). The
sidecar records the int8 model's mean error (``bias``, subtracted in fast mode) and, after
that, the largest per-crop and per-frame errors times ``bound_factor``: ``epsilon`` and
``delta``, which :class:`memlog.scoring.memorability.FastMemorability` uses to decide when the
int8 score settles a frame and when the fp32 model must look.

What is quantised (see :data:`SETTINGS`): the ResNet-152 trunk (~94 % of the compute):
per-channel int8 weights (7-bit range on CPUs without VNNI), uint8 activations, Percentile
calibration. The AlexNet-like branch, the pooled features, the fully connected head and the
sigmoid stay float32.

Speed is bounded by the hardware: without VNNI (AVX2 only) the u8 x s8 kernels are about twice as
fast as fp32 (the int8 model ~1.85x faster); with AVX-512 VNNI about 3x.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import io
import json
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from memlog.errors import ModelError
from memlog.models import cache
from memlog.models.fetch import sha256_file
from memlog.models.resmem import (
    CROP,
    FEATURES_NAME,
    INPUT_NAME,
    OUTPUT_NAME,
    RESMEM_FILE,
    RESMEM_VERSION,
    crop_weights,
    crops_from_frame,
    resmem_onnx_path,
    run_crops,
)
from memlog.models.runtime import make_session
from memlog.progress import info

__all__ = [
    "QUANTIZER_VERSION",
    "CALIBRATION_IMAGES",
    "SETTINGS",
    "calibration_crops",
    "sample_photo",
    "small_cameras",
    "quantize_resmem",
    "prepare_resmem_int8",
    "resmem_int8_path",
    "resmem_int8_bounds",
    "validation_crops",
    "crop_error",
]

#: Bump when the quantisation settings or the calibration set change: cached models are rebuilt.
QUANTIZER_VERSION = "4"

#: scikit-image sample photographs used for calibration, in order (bundled with the wheel).
CALIBRATION_IMAGES: tuple[str, ...] = (
    "astronaut",
    "coffee",
    "chelsea",
    "rocket",
    "camera",
    "brick",
    "grass",
    "gravel",
    "coins",
    "moon",
    "hubble_deep_field",
    "immunohistochemistry",
    "retina",
    "clock",
    "cell",
    "page",
    "text",
)
#: Default number of calibration images (25 crops each).
DEFAULT_N_IMAGES = 12

#: Quantisation settings (recorded in the sidecar). Chosen by measurement on 2-core CPUs: U8S8
#: is the only int8 pair with a fast kernel on AVX2 (S8S8 ran at fp32 speed, U8U8 at 1.3x).
#: ``reduce_range`` "auto": 7-bit weights on CPUs without VNNI, where they avoid the int16
#: saturation of AVX2's u8*s8 multiply-add (8-bit weights there: max crop error 0.25 instead
#: of 0.08), full 8-bit weights where VNNI accumulates in int32 (max crop error 0.046; 3x
#: faster than fp32 on an AVX-512 VNNI EPYC). The model is built on the machine that runs it,
#: and the sidecar records what was used. Percentile calibration (99.999) clips rare
#: activation outliers that MinMax stretched the ranges for (mean crop error 0.044 -> 0.016).
SETTINGS: dict[str, Any] = {
    "format": "QDQ",
    "activation_type": "QUInt8",
    "weight_type": "QInt8",
    "per_channel": True,
    "reduce_range": "auto",
    "calibrate_method": "Percentile",
    "percentile": 99.999,
    "quantized": "ResNet-152 trunk: stem conv, maxpool and all bottleneck convs/adds (features.conv1 .. features.layer4)",
    "float32": "AlexNet-like branch (conv1..conv5, LRN, pools), global average pool (resnet_pool output), "
    "features.fc, fc6..fc12, sigmoid",
    "pre_process": "onnxruntime.quantization.quant_pre_process(skip_symbolic_shape=True)",
    "calibration_batch": 5,
    "bound_factor": 1.5,
}

_FRAME = CROP * 5
_CAL_BATCH = int(SETTINGS["calibration_batch"])

F32 = npt.NDArray[np.float32]


@functools.lru_cache(maxsize=1)
def cpu_has_vnni() -> bool:
    """Whether this CPU has VNNI int8 dot products (AVX-512 VNNI, AVX-VNNI or AMX), from /proc/cpuinfo."""
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return False
    flags = set()
    for line in text.splitlines():
        if line.startswith(("flags", "Features")):
            flags.update(line.split(":", 1)[-1].split())
    return bool(flags & {"avx512_vnni", "avx_vnni", "amx_int8"})


def _reduce_range() -> bool:
    rr = SETTINGS["reduce_range"]
    return (not cpu_has_vnni()) if rr == "auto" else bool(rr)


INT8_FILE = f"resmem-{RESMEM_VERSION}-int8.onnx"


# ---------------------------------------------------------------------------------------------
# calibration data


def sample_photo(name: str) -> npt.NDArray[np.uint8]:
    """A scikit-image sample image as HxWx3 uint8 BGR (grey replicated)."""
    import cv2
    import skimage.data

    try:
        img = np.asarray(getattr(skimage.data, name)())
    except (OSError, ImportError, ValueError) as exc:  # missing file, downloader (pooch) absent
        raise ModelError(f"scikit-image sample image {name!r} is not available: {exc}") from None
    if img.dtype != np.uint8:
        raise ModelError(f"scikit-image sample image {name!r} is {img.dtype}, expected uint8")
    if img.ndim == 2:
        return np.asarray(cv2.cvtColor(img, cv2.COLOR_GRAY2BGR), dtype=np.uint8)
    if img.ndim == 3 and img.shape[2] in (3, 4):
        return np.ascontiguousarray(img[:, :, 2::-1])
    raise ModelError(f"scikit-image sample image {name!r} has unexpected shape {img.shape}")


def small_cameras(img: npt.NDArray[Any], widths: tuple[int, ...] = (160, 64)) -> list[npt.NDArray[Any]]:
    """``img`` as low-resolution cameras see it: shrunk to each width of ``widths`` pixels (aspect
    kept) with ``INTER_AREA``, like the 376 x 240 EuRoC or 64 x 32 Nordland frames."""
    import cv2

    h, w = img.shape[:2]
    return [cv2.resize(img, (wd, max(1, round(h * wd / w))), interpolation=cv2.INTER_AREA) for wd in widths]


def calibration_crops(n_images: int = DEFAULT_N_IMAGES) -> F32:
    """Calibration crops [25 * n_images, 3, 227, 227] float32 (RGB 0..1), deterministic.

    The first ``n_images`` of :data:`CALIBRATION_IMAGES` are rescaled to 1135 x 1135 with
    ``cv2.INTER_LINEAR`` and cut with :func:`~memlog.models.resmem.crops_from_frame`.
    """
    import cv2

    if not 1 <= n_images <= len(CALIBRATION_IMAGES):
        raise ModelError(f"n_images must be in 1..{len(CALIBRATION_IMAGES)}, got {n_images}")
    parts = []
    for name in CALIBRATION_IMAGES[:n_images]:
        frame = cv2.resize(sample_photo(name), (_FRAME, _FRAME), interpolation=cv2.INTER_LINEAR)
        parts.append(crops_from_frame(frame))
    return np.ascontiguousarray(np.concatenate(parts, axis=0), dtype=np.float32)


def validation_crops(n_calibration: int = DEFAULT_N_IMAGES, widths: tuple[int, ...] = (160, 64)) -> F32:
    """Held-out frames for the surrogate's error bounds, 25 crops each.

    The sample photos not used for calibration, at full resolution and as low-resolution
    cameras give them, plus the calibration photos at low resolution only (crops that were
    not calibrated on): each shrunk to every width of ``widths`` pixels with ``INTER_AREA``
    first, like the 376 x 240 EuRoC or 64 x 32 Nordland frames memlog upscales to 1135 x 1135.
    """
    import cv2

    if not 1 <= n_calibration < len(CALIBRATION_IMAGES):
        raise ModelError(f"n_calibration must be in 1..{len(CALIBRATION_IMAGES) - 1}, got {n_calibration}")
    parts = []
    for i, name in enumerate(CALIBRATION_IMAGES):
        img = sample_photo(name)
        versions: list[npt.NDArray[Any]] = ([] if i < n_calibration else [img]) + small_cameras(img, widths)
        for src in versions:
            frame = cv2.resize(src, (_FRAME, _FRAME), interpolation=cv2.INTER_LINEAR)
            parts.append(crops_from_frame(frame))
    return np.ascontiguousarray(np.concatenate(parts, axis=0), dtype=np.float32)


def crop_error(fp32_path: Path, int8_path: Path, crops: F32, batch: int = 25) -> dict[str, float]:
    """Errors of the int8 model against fp32 over ``crops`` (frames of 25 crops each).

    ``bias``: mean of int8 - fp32 over all crops (int8 runs slightly low); the rest is after
    subtracting it: per-crop |int8 - bias - fp32| (``max``, ``p99``, ``mean``) and per-frame
    |MS(int8 - bias) - MS(fp32)| with every pixel static (``frame_max``, ``frame_mean``);
    ``n`` crops, ``frames``."""
    if len(crops) == 0 or len(crops) % 25:
        raise ModelError(f"validation crops must be whole frames of 25 crops, got {len(crops)}")
    outs = []
    for path in (fp32_path, int8_path):
        session = make_session(path, device="cpu", what="ResMem")
        outs.append(np.concatenate([run_crops(session, crops[i:i + batch])
                                    for i in range(0, len(crops), batch)]).astype(np.float64))
    bias = float(np.mean(outs[1] - outs[0]))
    diff = outs[1] - bias - outs[0]
    d = np.abs(diff)
    frame = np.abs(diff.reshape(-1, 25) @ crop_weights(None).reshape(-1))
    return {"bias": bias, "max": float(d.max()), "p99": float(np.percentile(d, 99)), "mean": float(d.mean()),
            "frame_max": float(frame.max()), "frame_mean": float(frame.mean()),
            "n": int(d.size), "frames": int(frame.size)}


class _CropReader:
    """onnxruntime CalibrationDataReader over a crop array, in batches.

    Implements ``__len__``/``set_range`` so histogram calibrators can collect batch by batch
    (``CalibStridedMinMax``) instead of holding every activation of every batch in memory.
    """

    def __init__(self, crops: F32, batch: int) -> None:
        self.crops = crops
        self.batch = batch
        self.pos = 0
        self.end = len(crops)

    def get_next(self) -> dict[str, F32] | None:
        if self.pos >= self.end:
            return None
        chunk = self.crops[self.pos:min(self.pos + self.batch, self.end)]
        self.pos += self.batch
        return {INPUT_NAME: np.ascontiguousarray(chunk)}

    def rewind(self) -> None:
        self.pos = 0
        self.end = len(self.crops)

    def __len__(self) -> int:
        return (len(self.crops) + self.batch - 1) // self.batch

    def set_range(self, start_index: int, end_index: int) -> None:
        self.pos = start_index * self.batch
        self.end = min(end_index * self.batch, len(self.crops))

    def __iter__(self) -> Iterator[dict[str, F32]]:
        while (item := self.get_next()) is not None:
            yield item


# ---------------------------------------------------------------------------------------------
# quantisation


#: Node-name prefixes of the ResNet trunk that are quantised; every other node stays float32.
_QUANTISED_PREFIXES = ("features.conv1", "features.relu", "features.maxpool", "features.layer")


def _nodes_to_exclude(model_path: Path) -> list[str]:
    """Names of the nodes kept in float32: everything outside the ResNet-152 trunk."""
    import onnx

    model = onnx.load(str(model_path), load_external_data=False)
    return [n.name for n in model.graph.node if not n.name.startswith(_QUANTISED_PREFIXES)]


def _crops_sha256(crops: F32) -> str:
    return hashlib.sha256(np.ascontiguousarray(crops, dtype=np.float32).tobytes()).hexdigest()


def _check_quantize_inputs(fp32_path: Path, crops: F32) -> None:
    """Raise :class:`ModelError` unless ``crops`` are non-empty float32 [N,3,227,227] and the
    fp32 model exists."""
    if not isinstance(crops, np.ndarray) or crops.ndim != 4 or crops.shape[1:] != (3, CROP, CROP):
        raise ModelError(f"calibration crops must be [N,3,{CROP},{CROP}], got {getattr(crops, 'shape', None)}")
    if crops.dtype != np.float32 or len(crops) == 0:
        raise ModelError(f"calibration crops must be a non-empty float32 array, got {crops.dtype} x {len(crops)}")
    if not fp32_path.is_file():
        raise ModelError(f"ResMem ONNX model {fp32_path} not found; run `memlog models prepare`")


def _quantize_static(fp32_path: Path, pre: Path, qtmp: Path, crops: F32, exclude: list[str],
                     reduce_range: bool) -> None:
    """Run onnxruntime's static quantisation of the pre-processed model ``pre`` to ``qtmp`` with
    :data:`SETTINGS`, calibrated on ``crops``, keeping the ``exclude`` nodes in float32;
    :class:`ModelError` naming ``fp32_path`` when it fails."""
    from onnxruntime.quantization import CalibrationMethod, QuantFormat, QuantType, quantize_static

    reader = _CropReader(np.ascontiguousarray(crops), _CAL_BATCH)
    try:
        # onnxruntime's histogram calibrators print a line per batch on stdout
        with contextlib.redirect_stdout(io.StringIO()):
            quantize_static(
                str(pre),
                str(qtmp),
                reader,
                quant_format=QuantFormat.QDQ,
                per_channel=bool(SETTINGS["per_channel"]),
                reduce_range=reduce_range,
                activation_type=QuantType.QUInt8,
                weight_type=QuantType.QInt8,
                nodes_to_exclude=exclude,
                calibrate_method=CalibrationMethod.Percentile,
                extra_options={
                    "CalibPercentile": float(SETTINGS["percentile"]),
                    # one batch per collection round: bounded memory. (Not
                    # CalibMaxIntermediateOutputs: with MinMax it drops every range but the
                    # last round's, onnxruntime issue #18893.)
                    "CalibStridedMinMax": 1,
                },
            )
    except Exception as exc:  # onnxruntime raises many exception types
        raise ModelError(f"int8 quantisation of {fp32_path} failed: {exc}") from exc


def _int8_sidecar(fp32_path: Path, src_sha: str, reduce_range: bool, n_excluded: int, crops: F32,
                  calibration: dict[str, Any] | None, val: F32, val_from_caller: bool,
                  err: dict[str, float], seconds: float) -> dict[str, Any]:
    """The int8 model's cache sidecar: its source, settings, calibration and validation sets, the
    measured errors and the error bounds fast mode uses."""
    import onnxruntime

    return {
        "description": f"ResMem {RESMEM_VERSION} int8 (memlog fast mode)",
        "quantizer_version": QUANTIZER_VERSION,
        "source_onnx": fp32_path.name,
        "source_onnx_sha256": src_sha,
        "onnxruntime_version": onnxruntime.__version__,
        "settings": SETTINGS,
        "reduce_range_used": reduce_range,
        "cpu_vnni": cpu_has_vnni(),
        "n_nodes_excluded": n_excluded,
        "calibration": {
            **(calibration or {}),
            "n_crops": len(crops),
            "crops_sha256": _crops_sha256(crops),
        },
        "validation": {"n_crops": len(val), "crops_sha256": _crops_sha256(val),
                       "source": "caller" if val_from_caller else "validation_crops()"},
        "crop_error": err,
        "epsilon": min(1.0, float(SETTINGS["bound_factor"]) * err["max"]),
        "delta": min(1.0, float(SETTINGS["bound_factor"]) * err["frame_max"]),
        "seconds": seconds,
        "inputs": {INPUT_NAME: ["N", 3, CROP, CROP]},
        "outputs": {OUTPUT_NAME: ["N", 1], FEATURES_NAME: ["N", 2048]},
    }


def quantize_resmem(
    fp32_path: Path,
    out_path: Path,
    crops: F32,
    *,
    calibration: dict[str, Any] | None = None,
    validation: F32 | None = None,
    quiet: bool = True,
) -> Path:
    """Statically quantise the ResMem ONNX model at ``fp32_path`` to ``out_path`` (+ JSON sidecar).

    ``crops`` [N,3,227,227] float32 are the calibration inputs; ``calibration`` (JSON-able)
    describes them in the sidecar. ``validation`` (held-out crops, default
    :func:`validation_crops`) measures the error of the result (:func:`crop_error`): fast
    mode subtracts its mean ``bias``, and its per-crop bound ``epsilon`` and per-frame bound
    ``delta`` are ``SETTINGS["bound_factor"]`` times the largest crop and frame errors left.
    The model and its cache sidecar (:func:`memlog.models.cache.write_model`)
    are written atomically; intermediate files live in a temporary directory beside
    ``out_path``. Returns ``out_path``.
    """
    from onnxruntime.quantization import quant_pre_process

    fp32_path, out_path = Path(fp32_path), Path(out_path)
    _check_quantize_inputs(fp32_path, crops)
    src_sha = cache.recorded_sha256(fp32_path) or sha256_file(fp32_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix=".memlog-quant-", dir=out_path.parent) as tmpdir:
        tmp = Path(tmpdir)
        pre = tmp / "pre.onnx"
        quant_pre_process(str(fp32_path), str(pre), skip_symbolic_shape=True)
        exclude = _nodes_to_exclude(pre)
        qtmp = tmp / "int8.onnx"
        reduce_range = _reduce_range()
        _quantize_static(fp32_path, pre, qtmp, crops, exclude, reduce_range)
        val = validation_crops() if validation is None else validation
        err = crop_error(fp32_path, qtmp, val)
        data = qtmp.read_bytes()
    side = _int8_sidecar(fp32_path, src_sha, reduce_range, len(exclude), crops, calibration, val,
                         validation is not None, err, round(time.perf_counter() - t0, 1))
    cache.write_model(out_path, data, side)
    if not quiet:
        info(f"wrote {out_path} ({side['seconds']} s)")
    return out_path


# ---------------------------------------------------------------------------------------------
# prepared-model cache


def int8_pins() -> dict[str, Any]:
    """What a cached int8 model must have been made with: this quantizer version, from the
    current fp32 model, for this kind of CPU (VNNI or not)."""
    fp32 = cache.model_path(RESMEM_FILE)
    return {"quantizer_version": QUANTIZER_VERSION, "source_onnx_sha256": cache.recorded_sha256(fp32) or "missing",
            "cpu_vnni": cpu_has_vnni()}


def resmem_int8_path() -> Path:
    """Path of the prepared fast-mode (int8) ResMem model; :class:`ModelError` if missing or stale."""
    resmem_onnx_path()  # the int8 model is made from the fp32 one
    return cache.require(cache.model_path(INT8_FILE), int8_pins(), "the fast-mode (int8) ResMem model",
                         "memlog models prepare resmem-int8")


def resmem_int8_bounds(path: Path | None = None) -> tuple[float, float, float]:
    """Fast mode's error model of the int8 model: (per-crop bound ``epsilon``, per-frame
    bound ``delta``, ``bias`` to subtract from its crop scores), from the sidecar."""
    p = resmem_int8_path() if path is None else Path(path)
    try:
        side = cache.read_sidecar(p)
        if side is None:
            raise ValueError("no sidecar")
        eps, delta, bias = side["epsilon"], side["delta"], side["crop_error"]["bias"]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ModelError(f"{p}: sidecar has no error bounds ({exc}); run `memlog models prepare resmem-int8 --force`") from None
    for b in (eps, delta):
        if not isinstance(b, (int, float)) or not 0.0 <= float(b) <= 1.0:
            raise ModelError(f"{p}: invalid error bound {b!r} in its sidecar")
    if not isinstance(bias, (int, float)) or not abs(float(bias)) <= 1.0:
        raise ModelError(f"{p}: invalid bias {bias!r} in its sidecar")
    return float(eps), float(delta), float(bias)


def calibration_description(n_images: int = DEFAULT_N_IMAGES) -> dict[str, Any]:
    """JSON-able description of :func:`calibration_crops` ``(n_images)`` for the sidecar."""
    import skimage

    return {
        "source": f"scikit-image {getattr(skimage, '__version__', '?')} skimage.data sample photographs",
        "images": list(CALIBRATION_IMAGES[:n_images]),
        "frame": "BGR (grey replicated), cv2.resize to 1135x1135 INTER_LINEAR, crops_from_frame (25 crops each)",
    }


def prepare_resmem_int8(force: bool = False, quiet: bool = False, n_images: int = DEFAULT_N_IMAGES) -> Path:
    """Quantise the prepared fp32 ResMem model into the cache unless an up-to-date one exists.

    Needs the fp32 model (:func:`~memlog.models.resmem.resmem_onnx_path`). Returns the int8 path.
    """
    out = cache.model_path(INT8_FILE)
    if not force and cache.is_ready(out, int8_pins()):
        return out
    fp32 = resmem_onnx_path()
    if not quiet:
        info(f"quantising {fp32} to int8 (fast mode) ...")
    crops = calibration_crops(n_images)
    return quantize_resmem(fp32, out, crops, calibration=calibration_description(n_images), quiet=quiet)


def prepare_fast_models(force: bool = False, quiet: bool = False) -> Path:
    """Everything fast mode needs: the int8 model and its whole-frame fit; returns the int8 path."""
    out = prepare_resmem_int8(force=force, quiet=quiet)
    prepare_frame_fit(force=force, quiet=quiet)
    return out




# ---------------------------------------------------------------------------------------------
# the whole-frame estimate (fast mode's first tier)

#: Bump when the fit below changes: cached fits are redone.
FRAME_FIT_VERSION = "2"
FRAME_FIT_FILE = f"resmem-{RESMEM_VERSION}-int8-frame.json"


def frame_crop(bgr: npt.NDArray[Any]) -> F32:
    """The whole frame as one ResMem input: [1,3,227,227] RGB /255 (``cv2.INTER_AREA``)."""
    import cv2

    small = cv2.resize(bgr, (CROP, CROP), interpolation=cv2.INTER_AREA)[:, :, ::-1]
    return np.ascontiguousarray(small.transpose(2, 0, 1)[None], dtype=np.float32) / np.float32(255.0)


def _frames(n_calibration: int, held_out: bool, widths: tuple[int, ...] = (160, 64)) -> list[npt.NDArray[Any]]:
    """The photos used for the fit (the calibration photos at full and low resolution) or held
    out from it (the others), as camera frames."""
    out: list[npt.NDArray[Any]] = []
    for i, name in enumerate(CALIBRATION_IMAGES):
        if (i >= n_calibration) != held_out:
            continue
        img = sample_photo(name)
        out.append(img)
        out += small_cameras(img, widths)
    return out


def frame_fit_pins() -> dict[str, Any]:
    """What a cached whole-frame fit must have been made from: this fit version and the int8 model."""
    return {"fit_version": FRAME_FIT_VERSION,
            "int8_sha256": cache.recorded_sha256(cache.model_path(INT8_FILE)) or "missing"}


def prepare_frame_fit(force: bool = False, quiet: bool = False, n_calibration: int = DEFAULT_N_IMAGES) -> Path:
    """Fit fast mode's whole-frame estimate and cache it (JSON, with its cache sidecar).

    The int8 model scores the whole frame shrunk to one 227 x 227 input (:func:`frame_crop`);
    MS of an all-static frame is predicted as ``a * score + b``, fitted by least squares on the
    calibration photos (at full resolution and shrunk like low-resolution cameras) against their
    fp32 MS. ``delta`` is ``SETTINGS["bound_factor"]`` times the largest error on the fitted or
    the held-out photos, whichever is larger: fast mode lets the estimate decide only frames whose estimate is further than
    ``delta`` from MT, so one inference instead of 25 settles frames far from the threshold.
    """
    out = cache.model_path(FRAME_FIT_FILE)
    if not force and cache.is_ready(out, frame_fit_pins()):
        return out
    fp32, int8 = resmem_onnx_path(), resmem_int8_path()
    if not quiet:
        info("fitting fast mode's whole-frame estimate ...")
    s32 = make_session(fp32, device="cpu", what="ResMem")
    s8 = make_session(int8, device="cpu", what="int8 ResMem")
    w = crop_weights(None).reshape(-1)

    def measure(frames: list[npt.NDArray[Any]]) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        import cv2

        ms, est = [], []
        for f in frames:
            f1135 = cv2.resize(f, (CROP * 5, CROP * 5), interpolation=cv2.INTER_LINEAR)
            ms.append(float(np.dot(w, run_crops(s32, crops_from_frame(f1135)).astype(np.float64))))
            est.append(float(run_crops(s8, frame_crop(f1135))[0]))
        return np.asarray(ms), np.asarray(est)

    fit_ms, fit_est = measure(_frames(n_calibration, held_out=False))
    a, b = (float(v) for v in np.polyfit(fit_est, fit_ms, 1))
    val_ms, val_est = measure(_frames(n_calibration, held_out=True))
    err = np.abs(a * val_est + b - val_ms)
    fit_err = np.abs(a * fit_est + b - fit_ms)
    worst = max(float(err.max()), float(fit_err.max()))  # the larger of the two: a held-out set can be easy
    fit = {"a": a, "b": b, "delta": min(1.0, float(SETTINGS["bound_factor"]) * worst),
           "held_out_max_error": float(err.max()), "held_out_mean_error": float(err.mean()),
           "fit_max_error": float(fit_err.max()),
           "n_fit": int(len(fit_ms)), "n_held_out": int(len(val_ms))}
    meta = {**frame_fit_pins(), "description": "fast mode's whole-frame estimate: MS ~ a * int8(frame) + b",
            "calibration": calibration_description(n_calibration)}
    cache.write_model(out, (json.dumps(fit, indent=2, sort_keys=True) + "\n").encode(), meta)
    if not quiet:
        info(f"whole-frame estimate fitted (delta {fit['delta']:.3f})")
    return out


def frame_fit() -> dict[str, float]:
    """The cached whole-frame fit (a, b, delta); :class:`ModelError` naming the command when missing."""
    p = cache.require(cache.model_path(FRAME_FIT_FILE), frame_fit_pins(), "fast mode's whole-frame estimate",
                      "memlog models prepare resmem-int8")
    try:
        fit = json.loads(p.read_text())
        return {"a": float(fit["a"]), "b": float(fit["b"]), "delta": float(fit["delta"])}
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ModelError(f"{p} is not a whole-frame fit ({exc}); run `memlog models prepare resmem-int8 --force`") \
            from None

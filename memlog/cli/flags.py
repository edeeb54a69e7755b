"""Command-line flags: value checks (so a bad value is a usage error naming the flag, before any
work), the flag groups several subcommands share, and the builders that turn flags plus a
``--config`` file into memlog's typed configs."""

from __future__ import annotations

import argparse
import math
import re
from collections.abc import Callable
from typing import Any

from memlog.configfile import build, config_section, read_config_file
from memlog.errors import ConfigError
from memlog.io.base import FrameWindow
from memlog.progress import info
from memlog.scoring.config import CONFIGS, ScoreConfig, load_config
from memlog.selection.config import SelectionConfig

__all__ = [
    "unit_interval", "fraction", "positive_float", "nonneg_float", "positive_int", "nonneg_int", "int_range",
    "cosine_distance", "speed_range", "log_time", "ray_address", "GROUPS", "FlagGroups", "add_config_flag",
    "add_score_flags", "add_max_pixels", "add_window_flags", "add_select_flags", "add_selection_flags",
    "score_config", "selection_config", "frame_window", "file_section", "setting_names_to_flags",
]


# -- value checks (argparse ``type=`` functions: argparse names the flag in the message) ----------
def _number(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return v


def _integer(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None


def unit_interval(text: str) -> float:
    """A number in [0, 1] (thresholds)."""
    v = _number(text)
    if not 0.0 <= v <= 1.0:
        raise argparse.ArgumentTypeError(f"must be within [0, 1], got {text}")
    return v


def open_unit_interval(text: str) -> float:
    """A number in (0, 1) (distances that must neither be 0 nor cover everything)."""
    v = _number(text)
    if not 0.0 < v < 1.0:
        raise argparse.ArgumentTypeError(f"must be in (0, 1), got {text}")
    return v


def fraction(text: str) -> float:
    """A number in (0, 1] (keep fractions)."""
    v = _number(text)
    if not 0.0 < v <= 1.0:
        raise argparse.ArgumentTypeError(f"must be in (0, 1], got {text}")
    return v


def positive_float(text: str) -> float:
    v = _number(text)
    if v <= 0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {text}")
    return v


def nonneg_float(text: str) -> float:
    v = _number(text)
    if v < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {text}")
    return v


def positive_int(text: str) -> int:
    v = _integer(text)
    if v < 1:
        raise argparse.ArgumentTypeError(f"must be a whole number >= 1, got {text}")
    return v


def count_or_all(text: str) -> int | str:
    """A whole number >= 1, or ``all``."""
    if text.strip().lower() == "all":
        return "all"
    return positive_int(text)


def nonneg_int(text: str) -> int:
    v = _integer(text)
    if v < 0:
        raise argparse.ArgumentTypeError(f"must be a whole number >= 0, got {text}")
    return v


def int_range(low: int, high: int) -> Callable[[str], int]:
    """A whole number in [low, high]."""
    def check(text: str) -> int:
        v = _integer(text)
        if not low <= v <= high:
            raise argparse.ArgumentTypeError(f"must be a whole number in {low}..{high}, got {text}")
        return v

    return check


def speed_range(text: str) -> tuple[float, float]:
    """``MIN:MAX`` relative speeds, 0 <= MIN <= MAX (one number: that speed only)."""
    parts = text.split(":")
    if len(parts) > 2:
        raise argparse.ArgumentTypeError(f"expected MIN:MAX (e.g. 0:3), got {text!r}")
    lo, hi = (_number(parts[0]), _number(parts[-1]))
    if lo < 0 or hi < lo:
        raise argparse.ArgumentTypeError(f"must be MIN:MAX with 0 <= MIN <= MAX, got {text!r}")
    return lo, hi


def cosine_distance(text: str) -> float:
    """A cosine distance in (0, 2]."""
    v = _number(text)
    if not 0.0 < v <= 2.0:
        raise argparse.ArgumentTypeError(f"must be a cosine distance in (0, 2], got {text}")
    return v


_RAY_ADDRESS = re.compile(r"^(auto|local|ray://\S+|[\w.-]+:\d+|\[[0-9A-Fa-f:]+\]:\d+)$")


def ray_address(text: str) -> str:
    """A Ray cluster address: ``auto``, ``ray://HOST:PORT``, ``HOST:PORT`` (``local``: a new
    local instance)."""
    if not _RAY_ADDRESS.match(text):
        raise argparse.ArgumentTypeError(
            f"expected auto, ray://HOST:PORT or HOST:PORT, got {text!r} (for a local Ray instance, put --ray after "
            "the logs or before another flag)")
    return text


_TIME = re.compile(r"^\+?\d+(\.\d*)?$|^\+?\.\d+$")


def log_time(text: str) -> str:
    """``SECONDS`` since the epoch, or ``+SECONDS`` after the log's first message (resolved
    against the log by :func:`frame_window`)."""
    if not _TIME.match(text.strip()):
        raise argparse.ArgumentTypeError(
            f"expected seconds since the epoch (1403715273.5) or +seconds after the log starts (+30), got {text!r}")
    return text.strip()


def _resolve_time(text: str | None, log_start_ns: Callable[[], int | None], flag: str) -> int | None:
    if text is None:
        return None
    if text.startswith("+"):
        start = log_start_ns()
        if start is None:
            raise ConfigError(f"{flag} {text}: the log's start time is unknown (an empty log?)")
        return start + round(float(text[1:]) * 1e9)
    return round(float(text) * 1e9)


# -- flag groups ----------------------------------------------------------------------------------
#: The named groups of a command's --help, in the order every command shows them: first the flags most
#: runs need (argparse's "options", with -h and -q), then what is read and written, then how.
GROUPS: dict[str, str] = {
    "inputs": "which topics and frames are read",
    "outputs": "what is written besides -o",
    "comparisons": "what the memorable map is compared with",
    "selection": "which frames the map keeps",
    "sequence matching": "on by default: the query is matched as a drive, not frame by frame",
    "scoring": "the three criteria and their thresholds; defaults: the paper's",
    "performance": "speed and resources; a flag that may change the result says so",
    "experimental": "for experiments and benchmarks (reproducing measurements); ordinary runs do not need them",
}


class FlagGroups:
    """A command's flag groups: :attr:`common` (the flags most runs need, shown first) and the named
    groups of :data:`GROUPS` it uses, created in that order; ``descriptions`` replaces the one-line
    description of a group for this command."""

    def __init__(self, parser: argparse.ArgumentParser, *names: str, descriptions: dict[str, str] | None = None):
        unknown = set(names) - set(GROUPS)
        if unknown:
            raise ValueError(f"unknown flag group(s) {sorted(unknown)}")
        self.common = parser
        descriptions = {**GROUPS, **(descriptions or {})}
        self._groups = {name: parser.add_argument_group(name, descriptions[name]) for name in GROUPS if name in names}

    def __getitem__(self, name: str) -> argparse._ArgumentGroup:
        return self._groups[name]

    def exclusive(self, *actions: argparse.Action) -> None:
        """``actions`` are mutually exclusive, each shown in its own group."""
        group = self.common.add_mutually_exclusive_group()
        group._group_actions.extend(actions)


class _MaxPixels(argparse.Action):
    """--max-pixels N: sets the decoded-pixel cap for this run and its worker processes."""

    def __call__(self, parser: argparse.ArgumentParser, ns: argparse.Namespace, values: Any,
                 option: str | None = None) -> None:
        from memlog.io.image import set_max_pixels

        set_max_pixels(int(values))
        setattr(ns, self.dest, values)


def add_max_pixels(g: argparse._ActionsContainer) -> None:
    """``--max-pixels``: frames larger than this are reported and skipped before decoding."""
    g.add_argument("--max-pixels", type=positive_int, action=_MaxPixels, metavar="N",
                   help="skip (and report) frames of more than N pixels, checked from the image header before "
                        "decoding (default 100000000)")


def add_config_flag(g: argparse._ActionsContainer) -> None:
    """``--config``: settings from a file, which flags override."""
    g.add_argument("--config", metavar="FILE",
                   help="TOML/YAML/JSON settings file: [score], [select], [map], [evaluate], [batch] tables; "
                        "flags override it")


def add_score_flags(groups: FlagGroups, workers: Callable[[argparse._ActionsContainer], None] | None = None) -> None:
    """The scoring flags: thresholds (scoring), speed (performance; ``workers`` adds the command's
    --workers first), reference switches (experimental)."""
    g = groups["scoring"]
    g.add_argument("--preset", choices=sorted(CONFIGS),
                   help="named scoring config (st-lucia: the paper's lowered thresholds)")
    g.add_argument("--mt", type=unit_interval, help="memorability threshold MT (default 0.5)")
    g.add_argument("--st", type=unit_interval, help="staticity threshold ST (default 0.6)")
    g.add_argument("--et", type=unit_interval, help="entropy threshold ET (default 0.4)")
    g.add_argument("--all-scores", action="store_true", default=None,
                   help="compute every score of every frame, even after it fails (for sweeps and reports)")
    perf = groups["performance"]
    if workers is not None:
        workers(perf)
    fast = perf.add_argument("--fast", dest="mode", action="store_const", const="fast",
                             help="int8 memorability surrogate, fp32 only for frames near MT: exact mode's decisions "
                                  "within the surrogate's measured error (needs `memlog models prepare resmem-int8`)")
    perf.add_argument("--no-refine", dest="fast_refine", action="store_false", default=None,
                      help="with --fast: the int8 estimate decides every frame alone (faster near MT; decisions "
                           "within its error of MT may differ from exact mode)")
    perf.add_argument("--duplicates", choices=["identical", "near", "off"],
                      help="frames that repeat the previous one share its scoring (the record names the frame it "
                           "copies): identical = pixel-identical frames only (default, exact); near = also frames "
                           "within --near-distance on the thumbnail (approximate, only with --fast); off")
    perf.add_argument("--near-distance", type=open_unit_interval, metavar="D",
                      help="--duplicates near: largest cosine distance between the 64x32 thumbnails of a frame and "
                           "the previous one (default 0.01)")
    perf.add_argument("--threads", type=nonneg_int, metavar="N",
                      help="ONNX Runtime threads per process (default 0: every core)")
    perf.add_argument("--device", choices=["auto", "cpu", "cuda"],
                      help="where the models run (default auto: a CUDA GPU when onnxruntime-gpu sees one, else the "
                           "CPU)")
    add_max_pixels(perf)
    exp = groups["experimental"]
    literal = exp.add_argument("--paper-literal", dest="mode", action="store_const", const="paper",
                               help="(experimental) the literal pipeline: scikit-image entropy, all crops, no early "
                                    "exit (slow; a reference for measurements; not with --fast)")
    exp.add_argument("--normalize", choices=["all", "static"],
                     help="(experimental) divide MS/ES by all pixels (the paper, default) or by static pixels only")
    groups.exclusive(fast, literal)


def add_window_flags(g: argparse._ActionsContainer, what: str = "score") -> None:
    """-t, --start, --end, --stride: the frames a command reads."""
    g.add_argument("-t", "--topic", action="append", dest="topics", metavar="TOPIC",
                   help=f"camera topic to {what} (repeatable; default: every camera topic)")
    g.add_argument("--start", type=log_time, metavar="TIME",
                   help="first log time: seconds since the epoch, or +seconds after the log starts")
    g.add_argument("--end", type=log_time, metavar="TIME", help="end of the window (exclusive), same forms")
    g.add_argument("--stride", type=positive_int, default=1, metavar="N",
                   help="every n-th frame of each topic (default 1)")


def add_select_flags(g: argparse._ActionsContainer) -> None:
    """--select and --keep-fraction: how much of the drive the map keeps (shown first by ``map``)."""
    g.add_argument("--select", choices=["paper", "segment"],
                   help="segment (default): the best frame of each place segment by the three scores, so no "
                        "stretch of the drive is lost; paper: the frames passing MT/ST/ET")
    g.add_argument("--keep-fraction", type=fraction, metavar="F",
                   help="keep about this fraction of the frames: segment size (segment, default 0.25) or "
                        "thresholds (paper)")


def add_selection_flags(groups: FlagGroups) -> None:
    """The rest of frame selection (selection), and distinctiveness (experimental)."""
    g = groups["selection"]
    g.add_argument("--spacing-m", type=positive_float, metavar="M",
                   help="segment: one frame per this many metres travelled")
    g.add_argument("--spacing-s", type=positive_float, metavar="S", help="segment: one frame per this many seconds")
    g.add_argument("--segment-by", choices=["auto", "distance", "time", "count", "view"], help="segment boundaries")
    g.add_argument("--dedup", type=cosine_distance, metavar="DIST",
                   help="drop kept frames within this cosine distance (thumbnail descriptor) of an already kept one "
                        "(loops, stops)")
    exp = groups["experimental"]
    exp.add_argument("--dt", type=unit_interval,
                     help="(experimental) paper mode: also keep only frames whose distinctiveness (rank in the "
                          "drive, 0..1) is >= DT (computed from the reference drive's descriptors; off: it did not "
                          "beat uniform maps)")
    exp.add_argument("--distinct-weight", type=nonneg_float, metavar="W",
                     help="(experimental) segment mode: weight of distinctiveness in the combined score (0 = off; "
                          "with weights = [0, 0, 0] in the --config file's [select] table it selects by "
                          "distinctiveness alone)")


# -- builders -------------------------------------------------------------------------------------
_FLAG_OF = {
    "keep_fraction": "--keep-fraction", "spacing_m": "--spacing-m", "spacing_s": "--spacing-s",
    "segment_by": "--segment-by", "dedup": "--dedup", "select mode": "--select", "segment selection mode":
    "--select segment", "stride": "--stride", "jpeg_quality": "--jpeg-quality", "threads": "--threads",
    "image_format": "--image-format", "tolerance": "--tolerance", "seeds": "--seeds", "dt": "--dt",
    "distinct_weight": "--distinct-weight", "near_distance": "--near-distance", "duplicates": "--duplicates",
    "max_frames": "--max-frames", "whiten_dim": "--whiten-dim", "whiten_on": "--whiten-on",
}


def setting_names_to_flags(message: str) -> str:
    """A config error message with setting names replaced by the flags that set them."""
    for name, flag in sorted(_FLAG_OF.items(), key=lambda kv: -len(kv[0])):
        message = re.sub(rf"(?<![\w-]){re.escape(name)}(?![\w-])", flag, message)
    return message


def file_section(args: argparse.Namespace, name: str) -> dict[str, Any]:
    """The ``[name]`` table of ``--config`` (empty without a file)."""
    path = getattr(args, "config", None)
    if not path:
        return {}
    return config_section(read_config_file(path), name, str(path))


def score_config(args: argparse.Namespace) -> ScoreConfig:
    """The scoring config: preset, then the file's [score] table, then flags."""
    return load_config(
        getattr(args, "preset", None), getattr(args, "config", None), mt=args.mt, st=args.st, et=args.et,
        all_scores=args.all_scores, mode=getattr(args, "mode", None), normalize=args.normalize,
        threads=args.threads, fast_refine=getattr(args, "fast_refine", None), device=getattr(args, "device", None),
        maps=getattr(args, "maps", None) or None, duplicates=getattr(args, "duplicates", None),
        near_distance=getattr(args, "near_distance", None),
    )


def selection_config(args: argparse.Namespace, score: ScoreConfig) -> SelectionConfig:
    """The selection config: the paper thresholds of ``score``, then the file's [select] table,
    then flags; built once and passed down."""
    base = SelectionConfig(mt=score.mt, st=score.st, et=score.et)
    where = f"{args.config}: [select]" if getattr(args, "config", None) else "[select]"
    cfg = build(SelectionConfig, file_section(args, "select"), where, base)
    flags: dict[str, Any] = {}
    for key, dest in (("mode", "select"), ("keep_fraction", "keep_fraction"), ("spacing_m", "spacing_m"),
                      ("spacing_s", "spacing_s"), ("segment_by", "segment_by"), ("dedup", "dedup"), ("dt", "dt"),
                      ("distinct_weight", "distinct_weight")):
        v = getattr(args, dest, None)
        if v is not None:
            flags[key] = v
    if flags.get("spacing_m") is not None or flags.get("spacing_s") is not None:
        flags.setdefault("keep_fraction", None)  # a spacing flag replaces a keep fraction from the file
    try:
        cfg = build(SelectionConfig, flags, "flags", cfg) if flags else cfg
    except ConfigError as exc:
        raise ConfigError(setting_names_to_flags(str(exc).removeprefix("flags: "))) from None
    if cfg.mode == "segment" and any(getattr(args, k, None) is not None for k in ("mt", "st", "et")):
        info("note: --select segment keeps the best frame of each place segment; --mt/--st/--et only set "
             "the paper rule recorded with each frame's scores (use --select paper to select by them)")
    return cfg


def frame_window(args: argparse.Namespace, log: str | None) -> FrameWindow:
    """The frames to read: -t, --start/--end (``+S`` resolved against ``log``'s start), --stride."""
    def start_of_log() -> int | None:
        if log is None:
            return None
        from memlog.io.open import open_log

        with open_log(log) as reader:
            return reader.info().start_ns

    start = _resolve_time(getattr(args, "start", None), start_of_log, "--start")
    end = _resolve_time(getattr(args, "end", None), start_of_log, "--end")
    topics = tuple(args.topics) if getattr(args, "topics", None) else None
    try:
        return FrameWindow(topics, start, end, args.stride)
    except ConfigError as exc:
        raise ConfigError(f"--start/--end/--stride: {exc}") from None

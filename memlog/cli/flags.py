"""Command-line flags: value checks (so a bad value is a usage error naming the flag, before any
work), the flag groups several subcommands share, and the builders that turn flags plus a
``--config`` file into memlog's typed configs."""

from __future__ import annotations

import argparse
import re
from collections.abc import Callable, Collection
from typing import Any, TypeVar

from memlog.configfile import build, config_section, read_config_file
from memlog.errors import ConfigError
from memlog.io.base import FrameWindow
from memlog.progress import info
from memlog.scoring.config import ScoreConfig, load_config
from memlog.selection.config import SIZES, SelectionConfig
from memlog.settings import (
    count_or_all,
    cosine_distance,
    fraction,
    int_range,
    log_time,
    nonneg_float,
    nonneg_int,
    open_unit_interval,
    positive_float,
    positive_int,
    ray_address,
    setting_flags,
    speed_range,
    unit_interval,
)

T = TypeVar("T")

__all__ = [
    "unit_interval", "open_unit_interval", "fraction", "positive_float", "nonneg_float", "positive_int",
    "nonneg_int", "count_or_all", "int_range", "cosine_distance", "speed_range", "log_time", "ray_address", "GROUPS",
    "FlagGroups", "add_config_flag", "add_max_pixels", "add_window_flags", "add_setting_flags", "setting_values",
    "with_flags", "score_config", "selection_config", "frame_window", "file_section", "setting_names_to_flags",
]


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


def add_window_flags(g: argparse._ActionsContainer, what: str = "score") -> None:
    """-t, --start, --end, --stride: the frames a command reads."""
    g.add_argument("-t", "--topic", action="append", dest="topics", metavar="TOPIC",
                   help=f"camera topic to {what} (repeatable; default: every camera topic)")
    g.add_argument("--start", type=log_time, metavar="TIME",
                   help="first log time: seconds since the epoch, or +seconds after the log starts")
    g.add_argument("--end", type=log_time, metavar="TIME", help="end of the window (exclusive), same forms")
    g.add_argument("--stride", type=positive_int, default=1, metavar="N",
                   help="every n-th frame of each topic (default 1)")


def add_setting_flags(groups: FlagGroups, cls: type[Any], *, skip: Collection[str] = ()) -> None:
    """The flags of the config dataclass ``cls``'s settings (:mod:`memlog.settings`), each in its group;
    ``skip``: settings this command does not take from the command line. Two flags that set one
    setting to different constants (``--fast``, ``--paper-literal``) exclude each other."""
    consts: dict[str, list[argparse.Action]] = {}
    for name, flag in setting_flags(cls):
        if name in skip:
            continue
        where = groups.common if flag.group == "common" else groups[flag.group]
        action = where.add_argument(*flag.names, **flag.argparse_kwargs())
        if flag.action == "store_const":
            consts.setdefault(name, []).append(action)
    for actions in consts.values():
        if len(actions) > 1:
            groups.exclusive(*actions)


def setting_values(args: argparse.Namespace, cls: type[Any], *, skip: Collection[str] = ()) -> dict[str, Any]:
    """The settings of ``cls`` the command line gave, as the config's keywords (each flag's
    :attr:`~memlog.settings.Flag.value` applied, its :attr:`~memlog.settings.Flag.also` added)."""
    out: dict[str, Any] = {}
    for name, flag in setting_flags(cls):
        if name in skip:
            continue
        v = getattr(args, flag.key, None)
        if flag.given(v):
            out[name] = flag.setting(v)
            out.update(flag.also or {})
    return out


# -- builders -------------------------------------------------------------------------------------
def _flag_names() -> dict[str, str]:
    """Setting name -> the flag that sets it, over every config the CLI builds (a name two configs give
    different flags is left out: ambiguous), and the phrases selection errors use."""
    from memlog.descriptors.approx import SearchConfig
    from memlog.matching import SequenceConfig
    from memlog.steps.batch import BatchConfig
    from memlog.steps.evaluate import EvaluateConfig
    from memlog.steps.localize import LocalizeConfig
    from memlog.steps.map import MapConfig

    names: dict[str, set[str]] = {}
    for cls in (ScoreConfig, SelectionConfig, MapConfig, EvaluateConfig, LocalizeConfig, SearchConfig, SequenceConfig,
                BatchConfig):
        for name, flag in setting_flags(cls):
            if flag.action != "store_const":
                names.setdefault(name, set()).add(flag.name)
    out = {name: next(iter(flags)) for name, flags in names.items() if len(flags) == 1}
    out.update({"select mode": "--select", "segment selection mode": "--select segment"})
    return out


def setting_names_to_flags(message: str) -> str:
    """A config error message with setting names replaced by the flags that set them."""
    for name, flag in sorted(_flag_names().items(), key=lambda kv: -len(kv[0])):
        message = re.sub(rf"(?<![\w-]){re.escape(name)}(?![\w-])", flag, message)
    return message


def file_section(args: argparse.Namespace, name: str) -> dict[str, Any]:
    """The ``[name]`` table of ``--config`` (empty without a file)."""
    path = getattr(args, "config", None)
    if not path:
        return {}
    return config_section(read_config_file(path), name, str(path))


def with_flags(cls: type[T], values: dict[str, Any], base: T) -> T:
    """``base`` (a config of ``cls``) with the settings the command line gave (``values``,
    :func:`setting_values`); a value the config refuses is a usage error naming its flag."""
    try:
        return build(cls, values, "flags", base) if values else base
    except ConfigError as exc:
        raise ConfigError(setting_names_to_flags(str(exc).removeprefix("flags: "))) from None


def score_config(args: argparse.Namespace) -> ScoreConfig:
    """The scoring config: preset, then the file's [score] table, then flags."""
    return load_config(getattr(args, "preset", None), getattr(args, "config", None),
                       **setting_values(args, ScoreConfig))


def selection_config(args: argparse.Namespace, score: ScoreConfig) -> SelectionConfig:
    """The selection config: the paper thresholds of ``score``, then the file's [select] table,
    then flags; built once and passed down."""
    base = SelectionConfig(mt=score.mt, st=score.st, et=score.et)
    where = f"{args.config}: [select]" if getattr(args, "config", None) else "[select]"
    cfg = build(SelectionConfig, file_section(args, "select"), where, base)
    flags = setting_values(args, SelectionConfig)
    if any(flags.get(k) is not None for k in SIZES):
        for k in SIZES:  # a size flag replaces the size the file gives
            flags.setdefault(k, None)
    cfg = with_flags(SelectionConfig, flags, cfg)
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

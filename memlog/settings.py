"""Settings declared once: each field of a config dataclass carries its command-line flag(s), help
text, help group and value check as metadata (:func:`setting`), and the CLI is generated from them
(:func:`memlog.cli.flags.add_setting_flags` adds the flags, :func:`memlog.cli.flags.setting_values`
copies what the user gave into the config's keywords, the error messages name the flags).

The value checks (:func:`unit_interval`, :func:`positive_int`, ...) are argparse ``type=`` functions:
a bad value is a usage error naming the flag, before any work. A config file's values go through
:func:`memlog.configfile.build` (the field's type) and the dataclass's own checks instead.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import re
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from typing import Any

__all__ = [
    "Flag", "setting", "flags_of", "setting_flags", "unit_interval", "open_unit_interval", "fraction",
    "positive_float", "nonneg_float", "positive_int", "nonneg_int", "count_or_all", "int_range", "speed_range",
    "cosine_distance", "ray_address", "log_time",
]

_UNSET: Any = object()


@dataclass(frozen=True)
class Flag:
    """One command-line flag of a setting.

    ``names``: its option strings; ``help``: its help text; ``group``: the help group it is shown
    in (a key of :data:`memlog.cli.flags.GROUPS`, or ``"common"``: the flags most runs need, shown
    first); ``check``: the value check (argparse ``type=``); ``action``, ``choices``, ``metavar``,
    ``dest``, ``const``, ``nargs`` and ``default`` as argparse takes them (``default`` is the
    parser's, left out when not given); ``value``: turns the parsed value into the setting's
    (``--no-whiten`` -> ``whiten=False``); ``also``: other settings of the same config the flag
    sets when given (``--ray`` sets ``ray=True`` besides the address)."""

    names: tuple[str, ...]
    help: str
    group: str = "common"
    check: Callable[[str], Any] | None = None
    action: str | None = None
    choices: tuple[Any, ...] | None = None
    metavar: str | None = None
    dest: str | None = None
    const: Any = None
    nargs: str | None = None
    default: Any = _UNSET
    value: Callable[[Any], Any] | None = None
    also: Mapping[str, Any] | None = None

    @property
    def name(self) -> str:
        """The flag's long name (``--keep-fraction``)."""
        return next((n for n in self.names if n.startswith("--")), self.names[0])

    @property
    def key(self) -> str:
        """The attribute argparse stores the flag's value under."""
        return self.dest or self.name.lstrip("-").replace("-", "_")

    def argparse_kwargs(self) -> dict[str, Any]:
        """The keywords of ``add_argument``."""
        kw: dict[str, Any] = {"help": self.help}
        for name in ("action", "choices", "metavar", "dest", "nargs"):
            v = getattr(self, name)
            if v is not None:
                kw[name] = list(v) if name == "choices" else v
        if self.check is not None:
            kw["type"] = self.check
        if self.action == "store_const" or self.nargs == "?":
            kw["const"] = self.const
        if self.default is not _UNSET:
            kw["default"] = self.default
        return kw

    def given(self, parsed: Any) -> bool:
        """Whether the user gave the flag (its parsed value differs from "not given")."""
        if parsed is None:
            return False
        return not (self.action == "store_true" and parsed is False)

    def setting(self, parsed: Any) -> Any:
        """The setting's value for the parsed value."""
        return self.value(parsed) if self.value is not None else parsed


def setting(default: Any = dataclasses.MISSING, *flags: Flag,
            default_factory: Callable[[], Any] | Any = dataclasses.MISSING) -> Any:
    """A config dataclass field with its default and its command-line ``flags`` (none: the setting
    is set by a config file or the Python API only)."""
    meta = {"flags": tuple(flags)}
    if default_factory is not dataclasses.MISSING:
        return dataclasses.field(default_factory=default_factory, metadata=meta)
    return dataclasses.field(default=default, metadata=meta)


def flags_of(field: dataclasses.Field[Any]) -> tuple[Flag, ...]:
    """The flags declared on a config field."""
    flags: tuple[Flag, ...] = field.metadata.get("flags", ())
    return flags


def setting_flags(cls: type[Any]) -> Iterator[tuple[str, Flag]]:
    """Every (field name, flag) of the config dataclass ``cls``, in field order."""
    for f in dataclasses.fields(cls):
        for flag in flags_of(f):
            yield f.name, flag


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
    against the log by :func:`memlog.cli.flags.frame_window`)."""
    if not _TIME.match(text.strip()):
        raise argparse.ArgumentTypeError(
            f"expected seconds since the epoch (1403715273.5) or +seconds after the log starts (+30), got {text!r}")
    return text.strip()

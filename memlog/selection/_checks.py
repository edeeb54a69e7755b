"""Small validation helpers shared by the selection configs (private)."""

from __future__ import annotations

import math
import numbers
from typing import Any

from memlog.errors import ConfigError

__all__ = ["finite_number", "fraction", "positive_number", "positive_int"]


def finite_number(where: str, value: Any) -> float:
    """``value`` as a float; ConfigError unless it is a finite real number (not a bool)."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value):
        raise ConfigError(f"{where} must be a finite number, got {value!r}")
    return float(value)


def positive_number(where: str, value: Any) -> float:
    """``value`` as a float; ConfigError unless finite and > 0."""
    v = finite_number(where, value)
    if v <= 0:
        raise ConfigError(f"{where} must be > 0, got {value!r}")
    return v


def fraction(where: str, value: Any) -> float:
    """``value`` as a float; ConfigError unless in (0, 1]."""
    v = finite_number(where, value)
    if not 0.0 < v <= 1.0:
        raise ConfigError(f"{where} must be in (0, 1], got {value!r}")
    return v


def positive_int(where: str, value: Any) -> int:
    """``value`` as an int; ConfigError unless an integer >= 1 (not a bool)."""
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < 1:
        raise ConfigError(f"{where} must be an integer >= 1, got {value!r}")
    return int(value)

"""``results.json`` of ``memlog evaluate``: one object per map variant, sweeps, settings (atomic)."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from memlog.io.atomic import write_bytes_atomic

__all__ = ["write_results"]


def _json_default(o: Any) -> Any:
    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, np.floating):
        return float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    if hasattr(o, "to_dict"):
        return o.to_dict()
    raise TypeError(f"{type(o).__name__} is not JSON serialisable")


def write_results(path: str | os.PathLike[str], results: dict[str, Any]) -> Path:
    """Write ``results`` as indented JSON, atomically."""
    text = json.dumps(results, indent=2, default=_json_default, allow_nan=True)
    return write_bytes_atomic(path, (text + "\n").encode())

"""The prepared-model cache: one file layout, one sidecar format, one readiness rule.

Every model memlog converts or edits (ResMem fp32, ResMem int8, the DINOv2 backbone) lives in
``cache_dir()/models/<file>`` next to a JSON sidecar ``<file>.json``::

    {"format": 2, "model": "<file>", "sha256": "...", "bytes": N, ...what made it...}

A cached model is *ready* when the file and its sidecar exist, the sidecar has this format, the
file has the recorded size and every key the caller pins (converter version, source hash, CPU
kind...) has the expected value; ``verify_hash=True`` also re-hashes the file. The same rule
serves ``memlog models`` (what it lists as ready, with the sidecar's sha256) and the code that
loads the model (which refuses a stale one with a message naming the command that fixes it).
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from memlog.errors import ModelError
from memlog.io.atomic import write_bytes_atomic
from memlog.models.fetch import cache_dir, sha256_file

__all__ = [
    "SIDECAR_FORMAT",
    "model_path",
    "sidecar_path",
    "read_sidecar",
    "write_model",
    "is_ready",
    "require",
    "recorded_sha256",
]

SIDECAR_FORMAT = 2


def model_path(file_name: str) -> Path:
    """Where a prepared model named ``file_name`` lives in the cache (it may not exist)."""
    return cache_dir() / "models" / file_name


def sidecar_path(model: Path) -> Path:
    """The sidecar of ``model``: ``<model file name>.json`` beside it."""
    return model.with_name(model.name + ".json")


def read_sidecar(model: Path) -> dict[str, Any] | None:
    """The sidecar of ``model`` as a dict, or None when it is missing or not a JSON object."""
    try:
        data = json.loads(sidecar_path(model).read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def write_model(
    model: Path, data: bytes, meta: Mapping[str, Any], *, check: Callable[[Path], None] | None = None
) -> Path:
    """Write ``data`` to ``model`` and its sidecar (``meta`` plus format, sha256, bytes), both
    atomically; ``check`` may test the model file before it gets its final name. The old sidecar
    is removed first, so a crash in between leaves a model that is not ready (never a stale pair)."""
    model.parent.mkdir(parents=True, exist_ok=True)
    sidecar_path(model).unlink(missing_ok=True)
    write_bytes_atomic(model, data, check=check)
    side = {"format": SIDECAR_FORMAT, "model": model.name, "sha256": hashlib.sha256(data).hexdigest(),
            "bytes": len(data), **dict(meta)}
    write_bytes_atomic(sidecar_path(model), (json.dumps(side, indent=2, sort_keys=True) + "\n").encode())
    return model


def is_ready(model: Path, pins: Mapping[str, Any], *, verify_hash: bool = False) -> bool:
    """Whether ``model`` is a complete cached model made with the pinned settings ``pins``."""
    side = read_sidecar(model)
    if side is None or side.get("format") != SIDECAR_FORMAT:
        return False
    try:
        if side.get("bytes") != model.stat().st_size:
            return False
    except OSError:
        return False
    if any(side.get(k) != v for k, v in pins.items()):
        return False
    return not verify_hash or side.get("sha256") == sha256_file(model)


def require(model: Path, pins: Mapping[str, Any], what: str, command: str) -> Path:
    """``model`` if it is ready, else :class:`ModelError` saying what is missing and ``command``."""
    if not model.is_file():
        raise ModelError(f"{what} is not prepared ({model} is missing): run `{command}`")
    if not is_ready(model, pins):
        raise ModelError(f"{what} at {model} is stale or incomplete (its sidecar does not match): run `{command}`")
    return model


def recorded_sha256(model: Path) -> str | None:
    """The sha256 the sidecar records for ``model`` (None without a sidecar)."""
    side = read_sidecar(model)
    sha = side.get("sha256") if side else None
    return sha if isinstance(sha, str) else None

"""memlog: memorable maps from recorded robot drives.

The Python API (for notebooks) is the pipeline steps with their typed configs::

    import memlog
    run = memlog.score("drive.bag", "drive.scored.mcap", memlog.ScoreConfig(all_scores=True))
    res = memlog.make_map("drive.bag", "map.mcap", memlog.MapConfig(), scores="drive.scored.mcap")
    fleet = memlog.batch(["a.mcap", "b.bag"], "out", memlog.BatchConfig(ray=True))  # memlog[ray]
    loc = memlog.localize("map.parquet", "query.bag", "matches.parquet")

Names load on first use, so ``import memlog`` is cheap.

Importing memlog reads the environment once (``MEMLOG_MAX_PIXELS``, ``MEMLOG_ENTROPY_KERNEL``,
``MEMLOG_CACHE_DIR``, ``XDG_CACHE_HOME``, ``MEMLOG_DEBUG``, ``RAY_ADDRESS``) and installs the
runtime context it asks for (:mod:`memlog.runtime`); a bad value is warned about and its default
used. No other memlog module reads the environment: change a setting with
``memlog.runtime.install(memlog.runtime.current().replace(...))`` or ``with memlog.runtime.use(...)``.
"""

from __future__ import annotations

import importlib
import os
from typing import TYPE_CHECKING, Any

from memlog._version import __version__
from memlog.errors import MemlogError as _MemlogError
from memlog.runtime import Runtime as _Runtime, install as _install

if TYPE_CHECKING:
    from memlog.io.base import FrameWindow as FrameWindow
    from memlog.io.open import open_log as open_log
    from memlog.scoring.config import ScoreConfig as ScoreConfig
    from memlog.selection.config import SelectionConfig as SelectionConfig
    from memlog.steps.batch import BatchConfig as BatchConfig, batch as batch
    from memlog.steps.convert import ConvertConfig as ConvertConfig, convert as convert
    from memlog.steps.evaluate import EvaluateConfig as EvaluateConfig, evaluate as evaluate
    from memlog.steps.localize import LocalizeConfig as LocalizeConfig, localize as localize
    from memlog.steps.map import MapConfig as MapConfig, make_map as make_map
    from memlog.steps.score import score as score


def _started_as_the_command() -> bool:
    """Whether this process is the ``memlog`` command (``memlog ...`` or ``python -m memlog``): it
    reads the environment itself and calls a bad value a usage error, so the import says nothing."""
    import sys

    orig = list(getattr(sys, "orig_argv", []))  # (the interpreter's own command line: python -m memlog ...)
    as_module = any(a == "-m" and b in ("memlog", "memlog.cli.app") for a, b in zip(orig, orig[1:]))
    return as_module or os.path.basename(sys.argv[0] if sys.argv else "") == "memlog"


def _bad_setting(exc: _MemlogError) -> None:
    if _started_as_the_command():
        return
    from memlog.progress import warning

    warning(f"{exc}; the default is used")


_install(_Runtime.from_environment(os.environ, on_error=_bad_setting))

_WHERE = {
    "open_log": "memlog.io.open",
    "FrameWindow": "memlog.io.base",
    "ScoreConfig": "memlog.scoring.config",
    "SelectionConfig": "memlog.selection.config",
    "convert": "memlog.steps.convert",
    "ConvertConfig": "memlog.steps.convert",
    "score": "memlog.steps.score",
    "make_map": "memlog.steps.map",
    "MapConfig": "memlog.steps.map",
    "localize": "memlog.steps.localize",
    "LocalizeConfig": "memlog.steps.localize",
    "evaluate": "memlog.steps.evaluate",
    "batch": "memlog.steps.batch",
    "BatchConfig": "memlog.steps.batch",
    "EvaluateConfig": "memlog.steps.evaluate",
}

__all__ = ["__version__", *sorted(_WHERE)]


def __getattr__(name: str) -> Any:
    module = _WHERE.get(name)
    if module is None:
        raise AttributeError(f"module 'memlog' has no attribute {name!r}")
    return getattr(importlib.import_module(module), name)

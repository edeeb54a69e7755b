"""The staged scores of a reference log, kept so that a rerun does not score again.

``memlog evaluate`` scores its reference as ``memlog map`` does (:func:`memlog.steps.map.staged_scores_and_looks`:
the entropy and view of every frame, the detector and ResMem only where they can change the map) for
the memorable map. :func:`cached_staged_scores` keeps the result —
the score records and the frames' looks (thumbnail and view vector) — in one ``.npz`` file in the
output directory, named by a hash of what made it: the log's identity (path, size, modification
time), memlog's version, the scoring and selection settings and the window. A file whose key does not
match is not read; a file that does not read is scored again (and said so). No pickles: the records
are stored as JSON, the looks as plain arrays.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
from pathlib import Path

import numpy as np

from memlog._version import __version__
from memlog.io.atomic import write_bytes_atomic
from memlog.io.base import FrameWindow
from memlog.io.identity import log_identity
from memlog.io.records import ReadReport
from memlog.progress import info
from memlog.steps.map import Looks, MapConfig, Records, staged_scores_and_looks

__all__ = ["cached_staged_scores", "cache_key"]


def cache_key(log: str | os.PathLike[str], config: MapConfig, window: FrameWindow) -> str:
    """Hash of what the staged scores of ``log`` depend on."""
    what = {"log": log_identity(log), "memlog": __version__, "score": config.score.to_dict(),
            "select": config.select.to_dict(), "candidates": config.candidates, "topics": config.topics,
            "stride": config.stride, "position_topic": config.position_topic, "window": window.to_dict()}
    return hashlib.sha256(json.dumps(what, sort_keys=True, default=str).encode()).hexdigest()


def _pack(recs: Records, looks: Looks | None) -> bytes:
    arrays: dict[str, np.ndarray] = {"records": np.frombuffer(json.dumps(recs).encode(), dtype=np.uint8)}
    looks = looks or {}
    topics = sorted(looks)
    arrays["topics"] = np.frombuffer(json.dumps(topics).encode(), dtype=np.uint8)
    for n, t in enumerate(topics):
        idx = sorted(looks[t])
        arrays[f"index{n}"] = np.array(idx, dtype=np.int64)
        for k, name in enumerate(("thumb", "view")):
            have = [looks[t][i][k] for i in idx]
            if idx and all(v is not None for v in have):
                arrays[f"{name}{n}"] = np.stack([np.asarray(v) for v in have])
    buf = io.BytesIO()
    np.savez(buf, **arrays)  # type: ignore[arg-type]
    return buf.getvalue()


def _unpack(path: Path) -> tuple[Records, Looks | None]:
    with np.load(path, allow_pickle=False) as z:
        recs: Records = json.loads(z["records"].tobytes().decode())
        topics: list[str] = json.loads(z["topics"].tobytes().decode())
        looks: Looks = {}
        for n, t in enumerate(topics):
            idx = z[f"index{n}"].tolist()
            thumbs = z[f"thumb{n}"] if f"thumb{n}" in z else None
            views = z[f"view{n}"] if f"view{n}" in z else None
            looks[t] = {int(i): (None if thumbs is None else thumbs[r], None if views is None else views[r])
                        for r, i in enumerate(idx)}
    return recs, (looks if topics else None)


def cached_staged_scores(out_dir: Path, name: str, log: str, config: MapConfig, window: FrameWindow
                         ) -> tuple[Records, Looks | None, ReadReport | None]:
    """The staged score records and looks of ``log`` (:func:`staged_scores_and_looks`), from
    ``out_dir/NAME.staged.KEY.npz`` when a run with the same inputs and settings wrote it, else
    computed and written there (the read report is None when they came from the file)."""
    key = cache_key(log, config, window)
    path = out_dir / f"{name}.staged.{key[:16]}.npz"
    if path.is_file():
        try:
            recs, looks = _unpack(path)
            info(f"reusing {path} (the staged scores of {log} with the same settings)")
            return recs, looks, None
        except (OSError, ValueError, KeyError) as exc:
            info(f"not reusing {path}: it does not read ({exc}); scoring again")
    recs, looks, report = staged_scores_and_looks(log, config, window)
    write_bytes_atomic(path, _pack(recs, looks))
    for old in out_dir.glob(f"{name}.staged.*.npz"):  # one cache per name: an older run's is stale
        if old != path:
            old.unlink(missing_ok=True)
    return recs, looks, report


"""The annotated MCAP of ``memlog score``: every input record plus memlog's channels.

For each scored camera topic ``T``:

* ``T/memlog/scores`` (json, schema ``memlog.FrameScores``): MS, SS, ES, the 5x5 matrix,
  the decision, the rejecting criterion, per-stage timing;
* ``T/memlog/annotations`` (``foxglove.ImageAnnotations``): dynamic-object boxes with class
  and confidence, and the three scores as text, drawn by Foxglove over the image;
* with ``maps``: ``T/memlog/maps/{memorability,staticity,entropy}`` as
  ``foxglove.CompressedImage`` PNGs;

and metadata ``memlog_run`` (version, config, model hashes) and ``memlog_summary``.
:func:`read_scores` and :func:`run_config` read them back, so later steps reuse a scoring run.
"""

from __future__ import annotations

import base64
import json
import os
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from types import TracebackType
from typing import Any

import cv2
import numpy as np

from memlog.errors import ConfigError
from memlog.io.base import LogReader
from memlog.io.frame import Frame
from memlog.io.mcap import CopyStats, McapLogWriter, copy_log
from memlog.io.open import open_log
from memlog.io.records import RawMessage
from memlog.outputs.schemas import schema_bytes
from memlog.scoring.config import ScoreConfig, config_from_json
from memlog.scoring.scorer import STAGES, FrameScore

__all__ = [
    "AnnotatedLogWriter",
    "annotations_message",
    "scores_message",
    "read_scores",
    "run_config",
    "run_input_identity",
    "SCORES_SUFFIX",
]

SCORES_SUFFIX = "/memlog/scores"
_MAP_SCALE = {"memorability": 1.0, "staticity": 1.0, "entropy": 8.0}


def fmt3(v: float | None) -> str:
    """A score with three decimals, or '-' when missing."""
    return "-" if v is None else f"{v:.3f}"


def _stamp(ns: int) -> dict[str, int]:
    return {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000}


def _color(r: float, g: float, b: float, a: float = 1.0) -> dict[str, float]:
    return {"r": r, "g": g, "b": b, "a": a}


def annotations_message(frame: Frame, s: FrameScore, config: ScoreConfig) -> dict[str, Any]:
    """foxglove.ImageAnnotations: boxes of kept dynamic objects (red) and others seen (grey), plus scores."""
    ts = _stamp(frame.stamp_ns)
    w, h = s.width, s.height
    points = []
    texts = []
    for d in s.detections:
        kept = bool(getattr(d, "dynamic", False)) and d.confidence >= config.det_conf
        col = _color(1.0, 0.2, 0.2) if kept else _color(0.7, 0.7, 0.7, 0.8)
        x0, y0, x1, y1 = d.x0 * w, d.y0 * h, d.x1 * w, d.y1 * h
        points.append({
            "timestamp": ts, "type": 2, "points": [{"x": x0, "y": y0}, {"x": x1, "y": y0}, {"x": x1, "y": y1}, {"x": x0, "y": y1}],
            "outline_color": col, "outline_colors": [], "fill_color": _color(0, 0, 0, 0), "thickness": 2.0,
        })
        texts.append({
            "timestamp": ts, "position": {"x": x0 + 2, "y": y0 + 2}, "text": f"{d.class_name} {d.confidence:.2f}",
            "font_size": max(10.0, h / 30), "text_color": col, "background_color": _color(0, 0, 0, 0.5),
        })
    f = fmt3
    verdict = "KEEP" if s.selected else f"drop ({s.rejected_by})"
    bound = "" if s.ms_exact or s.ms is None else ("≥" if s.selected or s.rejected_by != "memorability" else "<")
    texts.append({
        "timestamp": ts, "position": {"x": 4.0, "y": 4.0},
        "text": f"MS {bound}{f(s.ms)}  SS {f(s.ss)}  ES {f(s.es)}  {verdict}",
        "font_size": max(10.0, h / 24), "text_color": _color(0.2, 1.0, 0.2) if s.selected else _color(1.0, 0.6, 0.2),
        "background_color": _color(0, 0, 0, 0.6),
    })
    return {"circles": [], "points": points, "texts": texts}


def scores_message(frame: Frame, s: FrameScore | None, config: ScoreConfig, error: str | None = None) -> dict[str, Any]:
    base = {
        "timestamp": _stamp(frame.stamp_ns), "log_time": frame.log_time_ns, "topic": frame.topic,
        "frame_index": frame.index, "thresholds": {"mt": config.mt, "st": config.st, "et": config.et},
    }
    if s is None:
        return {**base, "ms": None, "ss": None, "es": None, "selected": False, "rejected_by": "undecodable",
                "memorability": None, "ms_exact": True, "crops_scored": 0, "crops_surrogate": 0, "detections": 0,
                "timing_ms": {},
                "error": error}
    return {**base, **s.to_json(), "error": None}


def _map_png(m: np.ndarray, scale: float, w: int, h: int) -> bytes:
    img = np.clip(np.asarray(m, np.float64) * (255.0 / scale), 0, 255).astype(np.uint8)
    small = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)
    return bytes(cv2.imencode(".png", small)[1])


class AnnotatedLogWriter:
    """Writes the annotated MCAP of ``reader``: :meth:`copy_input` copies every input record,
    :meth:`write` adds one frame's score (and annotation, maps) messages, :meth:`close` adds
    the run metadata and renames the file into place (atomic; :meth:`abort` drops it)."""

    def __init__(self, path: str | os.PathLike[str], reader: LogReader, topics: list[str], config: ScoreConfig) -> None:
        self.reader = reader
        self.config = config
        self.w = McapLogWriter(path, profile=reader.profile)
        for ch in reader.channels():
            self.w.channel_for(ch)
        self._chans: dict[str, dict[str, int]] = {}
        for t in topics:
            chans = {
                "scores": self.w.add_channel(f"{t}{SCORES_SUFFIX}", "json",
                                             self.w.add_schema("memlog.FrameScores", "jsonschema",
                                                               schema_bytes("memlog.FrameScores"))),
                "annotations": self.w.add_channel(f"{t}/memlog/annotations", "json",
                                                  self.w.add_schema("foxglove.ImageAnnotations", "jsonschema",
                                                                    schema_bytes("foxglove.ImageAnnotations"))),
            }
            if config.maps:
                sid = self.w.add_schema("foxglove.CompressedImage", "jsonschema", schema_bytes("foxglove.CompressedImage"))
                for k in STAGES:
                    chans[f"map_{k}"] = self.w.add_channel(f"{t}/memlog/maps/{k}", "json", sid)
            self._chans[t] = chans

    @property
    def path(self) -> Path:
        return self.w.path

    def copy_input(self, wrap: Callable[[Iterator[RawMessage]], Iterator[RawMessage]] | None = None) -> CopyStats:
        """Copy every input record (messages, metadata, attachments) untouched."""
        return copy_log(self.reader, self.w, wrap=wrap)

    def write(self, frame: Frame, s: FrameScore | None, error: str | None = None) -> None:
        """The score message of ``frame`` (and, when scored, its annotations and maps)."""
        chans = self._chans[frame.topic]
        self.w.write_json(chans["scores"], frame.log_time_ns, scores_message(frame, s, self.config, error))
        if s is None:
            return
        self.w.write_json(chans["annotations"], frame.log_time_ns, annotations_message(frame, s, self.config))
        if self.config.maps:
            for k, m in s.maps.items():
                msg = {"timestamp": _stamp(frame.stamp_ns), "frame_id": frame.frame_id, "format": "png",
                       "data": base64.b64encode(_map_png(m, _MAP_SCALE[k], s.width, s.height)).decode()}
                self.w.write_json(chans[f"map_{k}"], frame.log_time_ns, msg)

    def close(self, run: Mapping[str, str], summary: Mapping[str, str]) -> Path:
        """Add ``memlog_run`` and ``memlog_summary`` metadata and move the file into place."""
        self.w.add_metadata("memlog_run", run)
        self.w.add_metadata("memlog_summary", summary)
        return self.w.close()

    def abort(self) -> None:
        self.w.abort()

    def __enter__(self) -> "AnnotatedLogWriter":
        return self

    def __exit__(self, et: type[BaseException] | None, ev: BaseException | None, tb: TracebackType | None) -> None:
        if et is not None:
            self.abort()


def read_scores(path: str | os.PathLike[str]) -> dict[str, list[dict[str, Any]]]:
    """Score records of an annotated MCAP, per camera topic, in frame-index order.

    Lets later steps (map, evaluate) reuse a scoring run instead of scoring again.
    """
    out: dict[str, list[dict[str, Any]]] = {}
    with open_log(path) as reader:
        topics = [c.topic for c in reader.channels() if c.topic.endswith(SCORES_SUFFIX)]
        for m in reader.messages(topics):
            rec = json.loads(m.data)
            out.setdefault(m.channel.topic.removesuffix(SCORES_SUFFIX), []).append(rec)
    for recs in out.values():
        recs.sort(key=lambda r: r["frame_index"])
    return out


def run_config(path: str | os.PathLike[str]) -> ScoreConfig | None:
    """The ScoreConfig an annotated MCAP was scored with (from its ``memlog_run`` metadata);
    None when it has none or one this memlog version does not understand."""
    with open_log(path) as reader:
        for name, data in reader.metadata():
            if name == "memlog_run" and "config" in data:
                try:
                    return config_from_json(data["config"])
                except ConfigError:
                    return None
    return None


def run_input_identity(path: str | os.PathLike[str]) -> Any:
    """The identity of the log an annotated MCAP was scored from (``memlog_run`` metadata,
    :func:`memlog.io.identity.log_identity`); None when it does not record one."""
    with open_log(path) as reader:
        for name, data in reader.metadata():
            if name == "memlog_run" and "input_identity" in data:
                try:
                    return json.loads(data["input_identity"])
                except ValueError:
                    return None
    return None

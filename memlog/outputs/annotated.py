"""The annotated MCAP of ``memlog score``: every input record plus memlog's channels.

For each scored camera topic ``T``:

* ``T/memlog/scores`` (``memlog.FrameScores``): MS, SS, ES, the 5x5 matrix, the decision, the
  rejecting criterion, per-stage timing;
* ``T/memlog/annotations`` (``foxglove.ImageAnnotations``, Foxglove's official definition):
  dynamic-object boxes with class and confidence, and the three scores as text, drawn by Foxglove
  over the image;
* with ``maps``: ``T/memlog/maps/{memorability,staticity,entropy}`` as PNG ``CompressedImage``;

all in the input's encoding family (:mod:`memlog.outputs.channels`: ROS 2 CDR, ROS 1, Foxglove
JSON or protobuf), and metadata ``memlog_run`` (version, config, model hashes) and
``memlog_summary``. :func:`read_scores` and :func:`run_config` read them back from any family, so
later steps reuse a scoring run.
"""

from __future__ import annotations

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
from memlog.io.records import RawMessage, ReadReport
from memlog.outputs.channels import (ANNOTATIONS, IMAGE, SCORES, MemlogChannels, RecordDecodeError, canonical_scores,
                                     decode_record, family_of)
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
            "metadata": [],
        })
        texts.append({
            "timestamp": ts, "position": {"x": x0 + 2, "y": y0 + 2}, "text": f"{d.class_name} {d.confidence:.2f}",
            "font_size": max(10.0, h / 30), "text_color": col, "background_color": _color(0, 0, 0, 0.5),
            "metadata": [],
        })
    f = fmt3
    verdict = "KEEP" if s.selected else f"drop ({s.rejected_by})"
    if s.ms is None and s.ms_low is not None and s.ms_high is not None:  # only bounded (stopped early)
        ms_text = f"≥{f(s.ms_low)}" if s.rejected_by != "memorability" else f"<{f(s.ms_high)}"
    else:
        ms_text = ("~" if not s.ms_exact and s.ms is not None else "") + f(s.ms)
    texts.append({
        "timestamp": ts, "position": {"x": 4.0, "y": 4.0},
        "text": f"MS {ms_text}  SS {f(s.ss)}  ES {f(s.es)}  {verdict}",
        "font_size": max(10.0, h / 24), "text_color": _color(0.2, 1.0, 0.2) if s.selected else _color(1.0, 0.6, 0.2),
        "background_color": _color(0, 0, 0, 0.6), "metadata": [],
    })
    return {"timestamp": ts, "circles": [], "points": points, "texts": texts, "metadata": []}


def scores_message(frame: Frame, s: FrameScore | None, config: ScoreConfig, error: str | None = None) -> dict[str, Any]:
    """The score record of ``frame`` (``memlog.FrameScores``; every field, null where not computed)."""
    base = {
        "timestamp": _stamp(frame.stamp_ns), "log_time": frame.log_time_ns, "topic": frame.topic,
        "frame_index": frame.index, "thresholds": {"mt": config.mt, "st": config.st, "et": config.et},
    }
    if s is None:
        return canonical_scores({**base, "ms": None, "ms_low": None, "ms_high": None, "ss": None, "es": None,
                                 "selected": False, "rejected_by": "undecodable", "memorability": None,
                                 "ms_exact": True, "crops_scored": 0, "crops_surrogate": 0, "detections": 0,
                                 "timing_ms": {}, "error": error or "frame does not decode"})
    return canonical_scores({**base, **s.to_json(), "error": None})


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
        self.w.register_input(reader)
        self.family = family_of(reader, topics)
        self.out = MemlogChannels(self.w, self.family)
        self._chans: dict[str, dict[str, int]] = {}
        for t in topics:
            chans = {"scores": self.out.add(f"{t}{SCORES_SUFFIX}", SCORES),
                     "annotations": self.out.add(f"{t}/memlog/annotations", ANNOTATIONS)}
            if config.maps:
                for k in STAGES:
                    chans[f"map_{k}"] = self.out.add(f"{t}/memlog/maps/{k}", IMAGE)
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
        self.out.write(chans["scores"], frame.log_time_ns, scores_message(frame, s, self.config, error))
        if s is None:
            return
        self.out.write(chans["annotations"], frame.log_time_ns, annotations_message(frame, s, self.config))
        if self.config.maps:
            for k, m in s.maps.items():
                self.out.write(chans[f"map_{k}"], frame.log_time_ns, {
                    "timestamp": _stamp(frame.stamp_ns), "frame_id": frame.frame_id, "format": "png",
                    "data": _map_png(m, _MAP_SCALE[k], s.width, s.height), "seq": frame.index})

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


def read_scores(path: str | os.PathLike[str], *, report: ReadReport | None = None) -> dict[str, list[dict[str, Any]]]:
    """Score records of an annotated MCAP or map log, per camera topic, in frame-index order.

    Reads every encoding memlog writes (JSON, ROS 2 CDR, ROS 1, protobuf) into the same records
    (the JSON form, :func:`~memlog.outputs.channels.canonical_scores`), so later steps (map,
    evaluate) reuse a scoring run instead of scoring again. A score message that does not decode is
    reported (file, topic, message index) and skipped; ``report`` (when given) receives the file's
    read report, so the caller can count the damage.
    """
    out: dict[str, list[dict[str, Any]]] = {}
    with open_log(path) as reader:
        topics = [c.topic for c in reader.channels() if c.topic.endswith(SCORES_SUFFIX)]
        seen: dict[str, int] = {}
        for m in reader.messages(topics):
            i = seen[m.channel.topic] = seen.get(m.channel.topic, -1) + 1
            try:
                rec = decode_record(SCORES, m.channel, m.data)
            except RecordDecodeError as exc:
                reader.report.count("bad_messages", (m.channel.topic, i))
                reader.warn(f"{reader.path}: topic {m.channel.topic}, message {i}: score record does not decode "
                            f"({exc}); skipped")
                continue
            out.setdefault(m.channel.topic.removesuffix(SCORES_SUFFIX), []).append(rec)
        if report is not None:
            report.merge(reader.report)
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

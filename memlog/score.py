"""Pipeline step: score every camera frame of a log and write the annotated MCAP.

The output holds every input record untouched plus, for each scored camera topic ``T``:

* ``T/memlog/scores`` (json, schema ``memlog.FrameScores``): MS, SS, ES, the 5x5 matrix,
  the decision, the rejecting criterion, per-stage timing;
* ``T/memlog/annotations`` (``foxglove.ImageAnnotations``): dynamic-object boxes with class
  and confidence, and the three scores as text, drawn by Foxglove over the image;
* with ``maps=True``: ``T/memlog/maps/{memorability,staticity,entropy}`` as
  ``foxglove.CompressedImage`` PNGs;

and metadata ``memlog_run`` (version, config, model hashes) and ``memlog_summary``.
"""

from __future__ import annotations

import base64
import json
import os
import platform
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from memlog import __version__
from memlog.config import ScoreConfig
from memlog.errors import ImageDecodeError, LogWriteError
from memlog.io import Frame, McapLogWriter, open_log
from memlog.io.base import FrameError, LogReader
from memlog.io.records import ReadReport
from memlog.progress import progress
from memlog.schemas import schema_bytes
from memlog.scoring.scorer import STAGES, FrameScore, Scorer

__all__ = ["score_log", "ScoreRun", "TopicSummary", "iter_scores", "annotations_message"]


@dataclass
class TopicSummary:
    frames_seen: int = 0
    scored: int = 0
    selected: int = 0
    undecodable: int = 0
    rejected: dict[str, int] = field(default_factory=lambda: {s: 0 for s in STAGES})
    time_ms: dict[str, float] = field(default_factory=dict)

    def add(self, s: FrameScore) -> None:
        self.scored += 1
        self.selected += int(s.selected)
        if s.rejected_by in self.rejected:
            self.rejected[s.rejected_by] += 1
        for k, v in s.timing_ms.items():
            self.time_ms[k] = self.time_ms.get(k, 0.0) + v

    def to_dict(self) -> dict[str, Any]:
        mean = {k: round(v / max(self.scored, 1), 3) for k, v in self.time_ms.items()}
        return {
            "frames_seen": self.frames_seen, "scored": self.scored, "selected": self.selected,
            "undecodable": self.undecodable, "rejected": dict(self.rejected), "mean_ms_per_frame": mean,
        }


@dataclass
class ScoreRun:
    output: Path
    topics: dict[str, TopicSummary]
    seconds: float
    report: ReadReport
    errors: list[FrameError]

    def to_dict(self) -> dict[str, Any]:
        return {
            "output": str(self.output), "seconds": round(self.seconds, 3),
            "topics": {t: s.to_dict() for t, s in self.topics.items()},
            "errors": [str(e) for e in self.errors],
        }


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
    from memlog.cli import fmt3 as f
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


def model_hashes(scorer: Scorer) -> dict[str, str]:
    try:
        from memlog.models.registry import model_hashes as hashes

        return hashes(scorer.config)
    except Exception:  # hashes are informative; the run itself already loaded the models
        return {}


def iter_scores(
    reader: LogReader,
    scorer: Scorer,
    *,
    topics: list[str] | None = None,
    start_ns: int | None = None,
    end_ns: int | None = None,
    stride: int = 1,
    errors: list[FrameError] | None = None,
) -> Iterator[tuple[Frame, FrameScore | None, str | None]]:
    """Score frames of a log without writing anything: yields (frame, score or None, error)."""
    frames = reader.frames(topics, start_ns, end_ns, stride, errors)
    for frame, res in scorer.score_stream(frames, lambda fr: fr.decode_bgr()):
        if isinstance(res, Exception):
            if isinstance(res, ImageDecodeError):
                err = reader.decode_error(frame, res)
            else:
                err = FrameError(reader.path, frame.topic, frame.index, frame.log_time_ns, f"scoring failed: {res}")
                reader.report.undecodable_frames += 1
                reader.warn(str(err))
            if errors is not None:
                errors.append(err)
            yield frame, None, err.reason
        else:
            yield frame, res, None


def score_log(
    log: str | os.PathLike[str],
    output: str | os.PathLike[str],
    config: ScoreConfig | None = None,
    *,
    topics: list[str] | None = None,
    start_ns: int | None = None,
    end_ns: int | None = None,
    stride: int = 1,
    scorer: Scorer | None = None,
    on_frame: Callable[[Frame, FrameScore | None], None] | None = None,
) -> ScoreRun:
    """Score ``log`` and write the annotated MCAP to ``output`` (atomically).

    Every input record is copied first-to-last in log-time order; score messages carry the
    frame's log time, so players show them with their frame.
    """
    config = config or ScoreConfig()
    scorer = scorer or Scorer(config)
    t_start = time.perf_counter()
    with open_log(log) as reader:
        if Path(output).resolve() == Path(reader.path).resolve():
            raise LogWriteError(f"{output}: output would overwrite the input log")
        cams = reader.camera_topics()
        wanted = topics or cams
        scorer.load()
        errors: list[FrameError] = []
        summaries = {t: TopicSummary() for t in wanted}
        with McapLogWriter(output, profile=reader.profile) as w:
            for ch in reader.channels():
                w.channel_for(ch)
            chans: dict[str, dict[str, int]] = {}
            for t in wanted:
                chans[t] = {
                    "scores": w.add_channel(f"{t}/memlog/scores", "json",
                                            w.add_schema("memlog.FrameScores", "jsonschema", schema_bytes("memlog.FrameScores"))),
                    "annotations": w.add_channel(f"{t}/memlog/annotations", "json",
                                                 w.add_schema("foxglove.ImageAnnotations", "jsonschema",
                                                              schema_bytes("foxglove.ImageAnnotations"))),
                }
                if config.maps:
                    sid = w.add_schema("foxglove.CompressedImage", "jsonschema", schema_bytes("foxglove.CompressedImage"))
                    for k in STAGES:
                        chans[t][f"map_{k}"] = w.add_channel(f"{t}/memlog/maps/{k}", "json", sid)
            # Pass 1 copies every record; pass 2 streams the camera frames again and scores them:
            # two sequential reads keep memory flat whatever the log size.
            copied = _copy_messages(reader, w)
            frame_iter = iter_scores(reader, scorer, topics=wanted, start_ns=start_ns, end_ns=end_ns,
                                     stride=stride, errors=errors)
            counts = reader.message_counts()
            n_frames = None
            if counts is not None:
                n_frames = sum(n for cid, n in counts.items()
                               if any(c.id == cid and c.topic in wanted for c in reader.channels())) // stride
            for frame, s, err in progress(frame_iter, total=n_frames, desc="score", unit="frame"):
                summ = summaries[frame.topic]
                summ.frames_seen += 1
                if s is None:
                    summ.undecodable += 1
                else:
                    summ.add(s)
                w.write_json(chans[frame.topic]["scores"], frame.log_time_ns, scores_message(frame, s, config, err))
                if s is not None:
                    w.write_json(chans[frame.topic]["annotations"], frame.log_time_ns, annotations_message(frame, s, config))
                    if config.maps:
                        scale = {"memorability": 1.0, "staticity": 1.0, "entropy": 8.0}
                        for k, m in s.maps.items():
                            msg = {"timestamp": _stamp(frame.stamp_ns), "frame_id": frame.frame_id, "format": "png",
                                   "data": base64.b64encode(_map_png(m, scale[k], s.width, s.height)).decode()}
                            w.write_json(chans[frame.topic][f"map_{k}"], frame.log_time_ns, msg)
                if on_frame is not None:
                    on_frame(frame, s)
            # per-topic frames that were not even deserializable
            for e in errors:
                if e.topic in summaries and "does not deserialize" in e.reason:
                    summaries[e.topic].frames_seen += 1
                    summaries[e.topic].undecodable += 1
            seconds = time.perf_counter() - t_start
            run = ScoreRun(Path(output), summaries, seconds, reader.report, errors)
            w.add_metadata("memlog_run", {
                "memlog_version": __version__, "config": config.to_json(), "input": str(reader.path),
                "models": json.dumps(model_hashes(scorer), sort_keys=True), "python": platform.python_version(),
                "messages_copied": str(copied),
            })
            w.add_metadata("memlog_summary", {k: json.dumps(v) for k, v in run.to_dict().items()})
    return run


def _copy_messages(reader: LogReader, w: McapLogWriter) -> int:
    from memlog.io import copy_log

    stats = copy_log(reader, w, wrap=lambda it: progress(it, desc="copy"))
    return stats.messages




def read_scores(path: str | os.PathLike[str]) -> dict[str, list[dict[str, Any]]]:
    """Score records of an annotated MCAP, per camera topic, in frame-index order.

    Lets later steps (map, evaluate) reuse a scoring run instead of scoring again.
    """
    out: dict[str, list[dict[str, Any]]] = {}
    with open_log(path) as reader:
        topics = [c.topic for c in reader.channels() if c.topic.endswith("/memlog/scores")]
        for m in reader.messages(topics):
            rec = json.loads(m.data)
            out.setdefault(m.channel.topic.removesuffix("/memlog/scores"), []).append(rec)
    for recs in out.values():
        recs.sort(key=lambda r: r["frame_index"])
    return out


def run_config(path: str | os.PathLike[str]) -> ScoreConfig | None:
    """The ScoreConfig an annotated MCAP was scored with (from its ``memlog_run`` metadata)."""
    with open_log(path) as reader:
        for name, data in reader.metadata():
            if name == "memlog_run" and "config" in data:
                d = json.loads(data["config"])
                d["dynamic_classes"] = tuple(d.get("dynamic_classes", ()))
                return ScoreConfig(**d)
    return None

"""Pipeline step ``score``: score every camera frame of a log and write the annotated MCAP.

:func:`score` streams the frames of a :class:`~memlog.io.base.FrameWindow`, scores them with
the staged :class:`~memlog.scoring.scorer.Scorer` and writes the annotated MCAP
(:class:`~memlog.outputs.annotated.AnnotatedLogWriter`): every input record untouched plus the
scores, the Foxglove annotations and optionally the maps. :func:`iter_scores` is the same
scoring without an output (the map step uses it).

Damage: a message that does not deserialize or an image that does not decode is reported and
skipped (the run exits 3). Anything else that fails while scoring (a model error, memory) stops
the run: it is not damage of the input.
"""

from __future__ import annotations

import json
import os
import platform
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from memlog._version import __version__
from memlog.errors import ImageDecodeError
from memlog.io.atomic import check_output
from memlog.io.base import FrameError, FrameWindow, LogReader
from memlog.io.frame import Frame
from memlog.io.identity import log_identity
from memlog.io.open import open_log
from memlog.io.records import ReadReport
from memlog.outputs.annotated import AnnotatedLogWriter
from memlog.progress import progress
from memlog.scoring.config import ScoreConfig
from memlog.scoring.scorer import STAGES, FrameScore, Scorer

__all__ = ["score", "ScoreRun", "TopicSummary", "iter_scores"]


@dataclass
class TopicSummary:
    """Counts and mean stage times of one scored topic (``memlog_summary``)."""

    frames_seen: int = 0
    scored: int = 0
    selected: int = 0
    undecodable: int = 0
    rejected: dict[str, int] = field(default_factory=lambda: {s: 0 for s in STAGES})
    time_ms: dict[str, float] = field(default_factory=dict)
    crops_run: int = 0

    def add(self, s: FrameScore | None) -> None:
        self.frames_seen += 1
        if s is None:
            self.undecodable += 1
            return
        self.scored += 1
        self.selected += int(s.selected)
        self.crops_run += s.crops_scored
        if s.rejected_by in self.rejected:
            self.rejected[s.rejected_by] += 1
        for k, v in s.timing_ms.items():
            self.time_ms[k] = self.time_ms.get(k, 0.0) + v

    def to_dict(self) -> dict[str, Any]:
        mean = {k: round(v / max(self.scored, 1), 3) for k, v in self.time_ms.items()}
        return {
            "frames_seen": self.frames_seen, "scored": self.scored, "selected": self.selected,
            "undecodable": self.undecodable, "rejected": dict(self.rejected), "resmem_crops_run": self.crops_run,
            "mean_ms_per_frame": mean,
        }


@dataclass
class ScoreRun:
    """What :func:`score` did."""

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


def iter_scores(
    reader: LogReader,
    scorer: Scorer,
    window: FrameWindow = FrameWindow(),
    *,
    errors: list[FrameError] | None = None,
) -> Iterator[tuple[Frame, FrameScore | None, str | None]]:
    """Score the frames of ``window`` without writing anything: yields (frame, score or None, error).

    A frame whose image does not decode is reported through ``reader`` (damage) and yielded
    with None; any other failure is raised.
    """
    frames = reader.frames(window.topics, window.start_ns, window.end_ns, window.stride, errors)
    for frame, res in scorer.score_stream(frames, lambda fr: fr.decode_bgr()):
        if isinstance(res, ImageDecodeError):
            err = reader.decode_error(frame, res)
            if errors is not None:
                errors.append(err)
            yield frame, None, err.reason
        elif isinstance(res, BaseException):
            raise res
        else:
            yield frame, res, None


def _run_metadata(reader: LogReader, config: ScoreConfig, scorer: Scorer, window: FrameWindow,
                  copied: int) -> dict[str, str]:
    prov = scorer.provenance()
    return {
        "memlog_version": __version__, "config": config.to_json(), "input": str(reader.path),
        "input_identity": json.dumps(log_identity(reader.path), sort_keys=True),
        "window": json.dumps(window.to_dict(), sort_keys=True),
        "models": json.dumps(prov["models"], sort_keys=True), "devices": json.dumps(prov["devices"], sort_keys=True),
        "python": platform.python_version(), "messages_copied": str(copied),
    }


def score(
    log: str | os.PathLike[str],
    output: str | os.PathLike[str],
    config: ScoreConfig | None = None,
    window: FrameWindow | None = None,
    *,
    scorer: Scorer | None = None,
    on_frame: Callable[[Frame, FrameScore | None], None] | None = None,
) -> ScoreRun:
    """Score ``log`` and write the annotated MCAP to ``output`` (atomically).

    Every input record is copied first; score messages carry their frame's log time, so players
    show them with their frame.
    """
    config = config or ScoreConfig()
    window = window or FrameWindow()
    scorer = scorer or Scorer(config)
    t_start = time.perf_counter()
    check_output(output, [log])
    with open_log(log) as reader:
        topics = reader.check_camera_topics(window.topics)
        scorer.load()
        errors: list[FrameError] = []
        summaries = {t: TopicSummary() for t in topics}
        total = reader.count_frames(window)
        counts = reader.message_counts()
        with AnnotatedLogWriter(output, reader, topics, config) as w:
            # Pass 1 copies every record; pass 2 streams the camera frames again and scores them:
            # two sequential reads keep memory flat whatever the log size.
            n_msgs = sum(counts.values()) if counts else None
            copied = w.copy_input(wrap=lambda it: progress(it, total=n_msgs, desc="copy", unit="msg")).messages
            scored = iter_scores(reader, scorer, window, errors=errors)
            for frame, s, err in progress(scored, total=total, desc="score", unit="frame"):
                summaries[frame.topic].add(s)
                w.write(frame, s, err)
                if on_frame is not None:
                    on_frame(frame, s)
            for e in errors:  # frames that did not even deserialize
                if e.topic in summaries and "does not deserialize" in e.reason:
                    summaries[e.topic].frames_seen += 1
                    summaries[e.topic].undecodable += 1
            run = ScoreRun(Path(output), summaries, time.perf_counter() - t_start, reader.report, errors)
            w.close(_run_metadata(reader, config, scorer, window, copied),
                    {k: json.dumps(v) for k, v in run.to_dict().items()})
    return run

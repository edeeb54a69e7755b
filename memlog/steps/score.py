"""Pipeline step ``score``: score every camera frame of a log and write the annotated MCAP.

:func:`score` streams the frames of a :class:`~memlog.io.base.FrameWindow`, scores them with
the staged :class:`~memlog.scoring.scorer.Scorer` and writes the annotated MCAP
(:class:`~memlog.outputs.annotated.AnnotatedLogWriter`): every input record untouched plus the
scores, the Foxglove annotations and optionally the maps.

With ``workers > 1`` the frames are cut into chunks (:func:`plan_chunks`: contiguous runs of
frames in log-time order) scored by worker processes (:func:`score_chunk`, one job per chunk,
models loaded once per process) and merged back in log-time order by the one writer, so the
output is byte-identical to a one-process run except the timing fields (``timing_ms`` of each
record, ``seconds`` and ``mean_ms_per_frame`` of ``memlog_summary``). :func:`iter_scores` is the
scoring without an output.

Damage: a message that does not deserialize or an image that does not decode is reported and
skipped (the run exits 3). Anything else that fails while scoring (a model error, memory) stops
the run: it is not damage of the input.
"""

from __future__ import annotations

import json
import os
import platform
import time
from collections.abc import Callable, Container, Hashable, Iterator, Mapping
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
from memlog.io import spool
from memlog.io.records import ReadReport
from memlog.models.runtime import choose_providers
from memlog.outputs.annotated import AnnotatedLogWriter
from memlog.progress import progress
from memlog.scoring.config import ScoreConfig
from memlog.scoring.scorer import STAGES, FrameScore, Scorer, SharedScore
from memlog.steps.parallel import Executor, InProcess, cached, job_threads, make_executor

__all__ = ["score", "ScoreRun", "TopicSummary", "iter_scores", "ScoredFrame", "ScoredChunk", "score_chunk",
           "plan_chunks", "Chunk", "scored_frames"]


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
    crops_full: int = 0
    shared: int = 0

    def add(self, s: FrameScore | None) -> None:
        self.frames_seen += 1
        if s is None:
            self.undecodable += 1
            return
        self.scored += 1
        self.selected += int(s.selected)
        self.crops_full += s.crops_needed
        if s.shared_from is None:  # a repeated frame carries its original's counts: not run again
            self.crops_run += s.crops_scored
        else:
            self.shared += 1
        if s.rejected_by in self.rejected:
            self.rejected[s.rejected_by] += 1
        for k, v in s.timing_ms.items():
            self.time_ms[k] = self.time_ms.get(k, 0.0) + v

    def to_dict(self) -> dict[str, Any]:
        mean = {k: round(v / max(self.scored, 1), 3) for k, v in self.time_ms.items()}
        return {
            "frames_seen": self.frames_seen, "scored": self.scored, "selected": self.selected,
            "undecodable": self.undecodable, "rejected": dict(self.rejected), "resmem_crops_run": self.crops_run,
            "resmem_crops_full_scoring": self.crops_full, "shared_with_previous_frame": self.shared, "mean_ms_per_frame": mean,
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
    indices: Mapping[str, Container[int]] | None = None,
    seed: dict[Hashable, tuple[int, Any]] | None = None,
) -> Iterator[tuple[Frame, FrameScore | SharedScore | None, str | None]]:
    """Score the frames of ``window`` (only ``indices`` when given) without writing anything:
    yields (frame, score or None, error).

    A frame whose image does not decode is reported through ``reader`` (damage) and yielded
    with None; any other failure is raised. A frame that repeats the previous frame of its topic
    gets that frame's scores (``shared_from``); when that frame was before this stream (``seed``)
    it is yielded as a :class:`SharedScore` for the caller to resolve.
    """
    frames = reader.frames(window.topics, window.start_ns, window.end_ns, window.stride, errors, indices=indices)
    previous: dict[str, FrameScore] = {}
    for frame, res in scorer.score_stream(frames, lambda fr: fr.decode_bgr(), identity=lambda fr: (fr.topic, fr.index),
                                          seed=seed):
        if isinstance(res, ImageDecodeError):
            err = reader.decode_error(frame, res)
            if errors is not None:
                errors.append(err)
            yield frame, None, err.reason
        elif isinstance(res, BaseException):
            raise res
        elif isinstance(res, SharedScore):
            prev = previous.get(frame.topic)  # the frame it repeats (never itself a shared one)
            yield frame, res.apply(prev) if prev is not None else res, None
        else:
            previous[frame.topic] = res
            yield frame, res, None


# -- chunks of frames, scored by workers ----------------------------------------------------------
@dataclass(frozen=True, eq=False)
class Chunk:
    """A contiguous run of frames in log-time order: their frame indices per topic and the
    log-time range [``start_ns``, ``end_ns``) that holds them (so a worker's reader seeks to it;
    the frame indices are the log's one numbering, :mod:`memlog.io.frame_table`)."""

    indices: dict[str, frozenset[int]]
    start_ns: int
    end_ns: int
    n: int
    prev: dict[str, tuple[int, int]] = field(default_factory=dict)  # topic -> (index, log time) of the frame before


@dataclass
class ScoredFrame:
    """One frame's result: the frame (pixels dropped), its score (None when it did not decode) and
    the decode error."""

    frame: Frame
    score: FrameScore | None
    error: str | None


@dataclass
class ScoredChunk:
    """The results of one chunk, in log-time order, and what its reader found (frame-level damage)."""

    frames: list[tuple[Frame, FrameScore | SharedScore | None, str | None]]
    report: ReadReport
    errors: list[FrameError]
    provenance: dict[str, Any] = field(default_factory=dict)


def plan_chunks(reader: LogReader, window: FrameWindow, size: int) -> list[Chunk]:
    """The frames of ``window`` cut into chunks of ``size`` frames, in log-time order, from the
    log's frame tables (:mod:`memlog.io.frame_table`: nothing is read beyond what opening the log
    read). Frames of one log time stay in one chunk."""
    import numpy as np

    topics = sorted(set(reader.check_camera_topics(window.topics)))
    entries: list[tuple[int, int, str, int]] = []
    containers = {}  # topic -> the container (log chunk) of each frame
    for k, t in enumerate(topics):
        table = reader.frame_table(t)
        first, last = table.window(window.start_ns, window.end_ns)
        idx = np.arange(first, last)
        idx = idx[idx % window.stride == 0]
        entries.extend((int(table.times[i]), k, t, int(i)) for i in idx)
        containers[t] = table.entries()[1]
    entries.sort()

    def place(k: int) -> int:
        return int(containers[entries[k][2]][entries[k][3]])

    chunks = []
    last_of: dict[str, tuple[int, int]] = {}
    a = 0
    while a < len(entries):
        b = min(a + size, len(entries))
        b = end_at_container(place, place, len(entries), b, size)
        while b < len(entries) and entries[b][0] == entries[b - 1][0]:
            b += 1  # frames of one log time stay in one chunk (their order is the reader's)
        part = entries[a:b]
        a = b
        ind: dict[str, set[int]] = {}
        prev = dict(last_of)
        for ts, _, t, i in part:
            ind.setdefault(t, set()).add(i)
            last_of[t] = (i, ts)
        chunks.append(Chunk({k: frozenset(v) for k, v in ind.items()}, part[0][0], part[-1][0] + 1, len(part),
                            {t: prev[t] for t in ind if t in prev}))
    return chunks


def end_at_container(first: Callable[[int], int | None], last: Callable[[int], int | None], n: int, b: int,
                     size: int) -> int:
    """Where a job that was to end before item ``b`` of ``n`` (frames, segments) ends, so that the
    next job does not read (and decompress) the log chunk it ends in again: ``b`` moved on while
    item ``b`` starts (``first``) in the container item ``b - 1`` ends in (``last``), by at most
    ``size`` items; ``b`` itself when that container goes on further, or is not known."""
    if not 0 < b < n:
        return b
    at = last(b - 1)
    end = b
    while at is not None and end < n and end - b < size and first(end) == at:
        end += 1
    return b if end < n and first(end) == at else end


def _scorer_for(config: ScoreConfig) -> Scorer:
    return cached(("scorer", config), lambda: Scorer(config).load())


def score_chunk(log: str, config: ScoreConfig, window: FrameWindow, chunk: Chunk | None) -> ScoredChunk:
    """Score one chunk of ``log`` (a worker's job; the whole window when ``chunk`` is None). The
    scorer is loaded once per process. Warnings are collected in the report, not printed."""
    scorer = _scorer_for(config)
    with open_log(log) as reader:
        reader.quiet_warnings()
        errors: list[FrameError] = []
        w = window if chunk is None else FrameWindow(window.topics, chunk.start_ns, chunk.end_ns, window.stride)
        seed = _seed(reader, scorer, chunk) if chunk is not None and config.duplicates != "off" else None
        out = [(f.stripped(), s, e) for f, s, e in
               iter_scores(reader, scorer, w, errors=errors, indices=None if chunk is None else chunk.indices,
                           seed=seed)]
        return ScoredChunk(out, reader.report, errors, scorer.provenance())


def _seed(reader: LogReader, scorer: Scorer, chunk: Chunk) -> dict[Hashable, tuple[int, Any]]:
    """The duplicate keys of the frames just before a chunk, so a chunk's first frame that
    repeats the previous one is recognised as in a one-process run."""
    seed: dict[Hashable, tuple[int, Any]] = {}
    for topic, (idx, ts) in chunk.prev.items():
        for f in reader.frames([topic], ts, ts + 1, indices={topic: {idx}}):
            try:
                seed[topic] = (idx, scorer.duplicate_key(f.decode_bgr()))
            except ImageDecodeError:
                pass
    return seed


def scored_frames(
    log: str | os.PathLike[str],
    reader: LogReader,
    config: ScoreConfig,
    window: FrameWindow,
    *,
    executor: Executor | None = None,
    scorer: Scorer | None = None,
    errors: list[FrameError] | None = None,
    provenance: dict[str, Any] | None = None,
    chunk_frames: int = 16,
) -> Iterator[ScoredFrame]:
    """Every frame of ``window`` scored, in log-time order: here through ``reader`` (one process),
    or in chunks on ``executor``'s workers. Frame-level damage found by the workers is added to
    ``reader.report`` (and reported) as if ``reader`` had found it; ``provenance`` (when given)
    receives the workers' model hashes and devices."""
    if executor is None or isinstance(executor, InProcess):
        sc = scorer or _scorer_for(config)
        for f, s, e in iter_scores(reader, sc, window, errors=errors):
            if isinstance(s, SharedScore):  # one stream resolves every repeat; cannot happen
                raise AssertionError("unresolved shared score")
            yield ScoredFrame(f.stripped(), s, e)
        return
    wcfg = config.replace(threads=job_threads(executor, config.threads))
    chunks = plan_chunks(reader, window, chunk_frames)
    last: dict[str, tuple[int, FrameScore]] = {}
    for res in executor.map_ordered(score_chunk, ((str(log), wcfg, window, c) for c in chunks)):
        reader.absorb(res.report, res.errors)
        if errors is not None:
            errors.extend(res.errors)
        if provenance is not None and not provenance:
            provenance.update(res.provenance)
        for frame, got, err in res.frames:
            if isinstance(got, SharedScore):  # repeats the last scored frame of the chunk before
                index, original = last[frame.topic]
                fs: FrameScore | None = got.apply(original, index)
            else:
                fs = got
                if fs is not None and fs.shared_from is None:
                    last[frame.topic] = (frame.index, fs)
            yield ScoredFrame(frame, fs, err)


def _run_metadata(reader: LogReader, config: ScoreConfig, prov: dict[str, Any], window: FrameWindow,
                  copied: int) -> dict[str, str]:
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
    workers: int = 1,
    executor: Executor | None = None,
    chunk_frames: int = 16,
) -> ScoreRun:
    """Score ``log`` and write the annotated MCAP to ``output`` (atomically).

    Every input record is copied first; score messages carry their frame's log time, so players
    show them with their frame. ``workers`` > 1 scores chunks of frames on that many processes
    (or on ``executor``); the output is the same as with one.
    """
    config = config or ScoreConfig()
    window = window or FrameWindow()
    t_start = time.perf_counter()
    check_output(output, [log])
    if not getattr(executor, "remote", False):  # (a cluster's workers check their own device)
        choose_providers(config.device)  # --device cuda without CUDA: said now, not after copying the log
    own = executor is None
    ex = executor or make_executor(workers)
    try:
        with spool.job(log), open_log(log) as reader:  # (each chunk read from the log once: memlog.io.spool)
            topics = reader.check_camera_topics(window.topics)
            sc = None
            if isinstance(ex, InProcess):  # with workers, the models load in the worker processes
                sc = scorer or _scorer_for(config)  # loaded once per process (evaluate scores again)
            prov: dict[str, Any] = {}
            errors: list[FrameError] = []
            summaries = {t: TopicSummary() for t in topics}
            total = reader.count_frames(window)
            counts = reader.message_counts()
            with AnnotatedLogWriter(output, reader, topics, config) as w:
                # Pass 1 copies every record; pass 2 streams the camera frames again and scores them:
                # two sequential reads keep memory flat whatever the log size.
                n_msgs = sum(counts.values()) if counts else None
                copied = w.copy_input(wrap=lambda it: progress(it, total=n_msgs, desc="copy", unit="msg")).messages
                frames = scored_frames(log, reader, config, window, executor=ex, scorer=sc, errors=errors,
                                       provenance=prov, chunk_frames=chunk_frames)
                for item in progress(frames, total=total, desc="score", unit="frame"):
                    summaries[item.frame.topic].add(item.score)
                    w.write(item.frame, item.score, item.error)
                for e in errors:  # frames that did not even deserialize
                    if e.topic in summaries and "does not deserialize" in e.reason:
                        summaries[e.topic].frames_seen += 1
                        summaries[e.topic].undecodable += 1
                run = ScoreRun(Path(output), summaries, time.perf_counter() - t_start, reader.report, errors)
                if not prov:
                    prov = (sc or Scorer(config)).provenance()
                w.close(_run_metadata(reader, config, prov, window, copied),
                        {k: json.dumps(v) for k, v in run.to_dict().items()})
    finally:
        if own:
            ex.close()
    return run

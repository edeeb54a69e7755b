"""The map step's scoring: staged segment selection (ResMem only where it can change the map).

Used by :mod:`memlog.steps.map` when frames are chosen by segment with the geometric score.
Pass 1 (:func:`cheap_chunk`, on workers in chunks) computes the cheap criteria of every frame:
staticity (the detector's boxes are kept, so S can be rebuilt), entropy, the number of crops
ResMem would have to score, and, when selection needs it, the thumbnail. The drive is cut into
segments from these; pass 2 (:func:`choose_chunk`, on workers, a group of segments per job)
runs :func:`memlog.selection.staged.choose_in_segment` on each segment, decoding only the
segment's candidate frames and running ResMem only as far as needed. The records it returns say
what was computed: ``ms`` null with bounds ``ms_low``/``ms_high`` where MS was not needed.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from memlog.descriptors.registry import make_describer
from memlog.errors import ImageDecodeError
from memlog.io.base import FrameError, FrameWindow, LogReader
from memlog.io.frame import Frame
from memlog.io.open import open_log
from memlog.io.records import ReadReport
from memlog.models.resmem import crop_weights
from memlog.outputs.annotated import scores_message
from memlog.scoring.config import ScoreConfig
from memlog.scoring.scorer import FrameScore, Scorer, resize_frame, view_vector
from memlog.scoring.staticity import static_map
from memlog.selection.staged import MSResult, MSState, choose_in_segment
from memlog.steps.parallel import Executor, InProcess, cached, job_threads
from memlog.steps.score import Chunk, plan_chunks

__all__ = ["CheapFrame", "cheap_chunk", "cheap_frames", "SegmentJob", "choose_chunk", "staged_record"]


@dataclass
class CheapFrame:
    """The cheap criteria of one frame (no pixels kept)."""

    frame: Frame
    ss: float | None = None
    es: float | None = None
    detections: list[Any] = field(default_factory=list)
    width: int = 0
    height: int = 0
    crops_needed: int = 0  # crops of non-zero weight: what scoring it fully would run
    timing_ms: dict[str, float] = field(default_factory=dict)
    thumb: npt.NDArray[np.float32] | None = None
    view: npt.NDArray[np.float32] | None = None
    error: str | None = None


def _scorer_for(config: ScoreConfig) -> Scorer:
    return cached(("scorer", config), lambda: Scorer(config))


def cheap_chunk(log: str, config: ScoreConfig, window: FrameWindow, chunk: Chunk | None,
                thumbs: bool, views: bool = False) -> tuple[list[CheapFrame], ReadReport, list[FrameError]]:
    """Pass 1 on one chunk (a worker's job): the cheap criteria of its frames."""
    scorer = _scorer_for(config)
    thumb = make_describer("thumbnail") if thumbs else None
    out: list[CheapFrame] = []
    with open_log(log) as reader:
        if chunk is not None:
            reader.quiet_warnings()
        errors: list[FrameError] = []
        w = window if chunk is None else FrameWindow(window.topics, chunk.start_ns, chunk.end_ns, window.stride)
        frames = reader.frames(w.topics, w.start_ns, w.end_ns, w.stride, errors,
                               indices=None if chunk is None else chunk.indices)
        for f in frames:
            t0 = time.perf_counter()
            try:
                bgr = f.decode_bgr()
            except ImageDecodeError as exc:
                err = reader.decode_error(f, exc)
                errors.append(err)
                out.append(CheapFrame(f.stripped(), error=err.reason))
                continue
            dt = (time.perf_counter() - t0) * 1e3
            c = scorer.cheap(bgr, keep_maps=False)
            cf = CheapFrame(f.stripped(), c.ss, c.es, c.detections, c.width, c.height,
                            int(np.count_nonzero(crop_weights(c.static_map) > 0)), {"decode": dt, **c.timing_ms})
            if thumb is not None:
                cf.thumb = thumb.describe([bgr])[0]
            if views:
                cf.view = view_vector(bgr).astype(np.float32)
            out.append(cf)
        return out, reader.report, errors


def cheap_frames(log: str, reader: LogReader, config: ScoreConfig, window: FrameWindow, executor: Executor,
                 *, thumbs: bool, views: bool = False, chunk_frames: int = 64) -> Iterator[CheapFrame]:
    """Pass 1 over ``window`` in log-time order (here, or in chunks on the executor's workers);
    workers' frame-level damage is added to ``reader.report``."""
    if isinstance(executor, InProcess):
        frames, _, _ = cheap_chunk(log, config, window, None, thumbs, views)
        yield from frames
        return
    wcfg = config.replace(threads=job_threads(executor, config.threads))
    for frames, rep, errors in executor.map_ordered(
            cheap_chunk, ((log, wcfg, window, c, thumbs, views) for c in plan_chunks(reader, window, chunk_frames))):
        reader.absorb(rep, errors)
        yield from frames


@dataclass
class SegmentJob:
    """One segment of one topic: its candidate frames with their cheap scores."""

    topic: str
    indices: list[int]
    ss: list[float]
    es: list[float]
    detections: list[list[Any]]
    start_ns: int
    end_ns: int
    coord: list[float] | None = None  # each candidate's segment coordinate (the shortlist's centre rule)


@dataclass
class SegmentResult:
    """The winner of a segment (position in the job's ``indices``, or None) and every candidate's MS state."""

    winner: int | None
    states: list[MSState]


class _Loader:
    """Decoded, resized candidate frames of one segment, read in batches along the order the
    staged choice will ask for them (bounded memory for long segments: a robot standing still)."""

    BATCH = 64

    def __init__(self, reader: LogReader, job: SegmentJob, stride: int) -> None:
        self.reader, self.job, self.stride = reader, job, stride
        self.order: list[int] = list(range(len(job.indices)))
        self.frames: dict[int, Frame] = {}
        self.ready: dict[int, tuple[npt.NDArray[np.uint8], npt.NDArray[np.uint8]]] = {}

    def plan(self, order: list[int]) -> None:
        self.order = list(order)

    def get(self, row: int, config: ScoreConfig) -> tuple[npt.NDArray[np.uint8], npt.NDArray[np.uint8]]:
        if row not in self.ready:
            if row not in self.frames:
                self._load(row)
            frame = self.frames.pop(row)
            f1135 = resize_frame(frame.decode_bgr())
            s_map = static_map(self.job.detections[row], conf=config.det_conf, min_area=config.det_min_area,
                               dynamic=config.dynamic_classes)
            self.ready[row] = (f1135, s_map)
            while len(self.ready) > 2:  # a frame is asked for at most twice in a row
                self.ready.pop(next(iter(self.ready)))
        return self.ready[row]

    def _load(self, row: int) -> None:
        pos = self.order.index(row) if row in self.order else 0
        batch = [r for r in self.order[pos:] if r not in self.frames and r not in self.ready][: self.BATCH]
        if row not in batch:
            batch = [row] + batch[: self.BATCH - 1]
        want = {self.job.indices[r]: r for r in batch}
        job = self.job
        for f in self.reader.frames([job.topic], job.start_ns, job.end_ns, self.stride,
                                    indices={job.topic: set(want)}):
            self.frames[want[f.index]] = f
        if row not in self.frames:
            raise ImageDecodeError(f"frame {job.indices[row]} of {job.topic} could not be read again")


def choose_chunk(log: str, config: ScoreConfig, window: FrameWindow, jobs: list[SegmentJob],
                 weights: tuple[float, float, float], min_ms: float,
                 shortlist: int | None, score_alone: bool = True,
                 centre_tolerance: float = 0.0) -> list[SegmentResult]:
    """Pass 2 for a group of segments (a worker's job): each segment's winner, ResMem run only
    where it can change the choice (and on a segment's only candidate when ``score_alone``)."""
    scorer = _scorer_for(config)  # ResMem loads on the first frame scored (Scorer.memorability; K = 1: never)
    results: list[SegmentResult] = []
    with open_log(log) as reader:
        reader.quiet_warnings()
        for job in jobs:
            loader = _Loader(reader, job, window.stride)

            def score(row: int, threshold: float | None, known: npt.NDArray[Any] | None,
                      job: SegmentJob = job, loader: _Loader = loader) -> MSResult:
                f1135, s_map = loader.get(row, config)
                thr = threshold
                scale = 1.0
                if config.normalize == "static":  # MS_static = MS_all / SS
                    ss = job.ss[row]
                    scale = 1.0 / ss if ss > 0 else 0.0
                    thr = None if threshold is None else threshold * ss
                before = int(np.count_nonzero(~np.isnan(known))) if known is not None else 0
                mem = scorer.memorability
                mem = getattr(mem, "exact", mem)  # fast mode's surrogate is not used for the choice
                r = mem(f1135, s_map, thr, known=known)
                run = r.n_scored - before
                if r.exact:
                    ms = float(r.ms) * scale if r.ms is not None else 0.0
                    return MSResult(ms, ms, True, r.m, run)
                return MSResult(r.ms_low * scale, r.ms_high * scale, False, r.m, run)

            n = len(job.indices)
            ss = np.asarray(job.ss, dtype=np.float64)
            es = np.asarray(job.es, dtype=np.float64)
            ms_max = np.ones(n) if config.normalize == "static" else None
            winner, states = choose_in_segment(list(range(n)), ss, es, score, weights=weights, min_ms=min_ms,
                                               ms_max=ms_max, shortlist=shortlist, prepare=loader.plan,
                                               score_alone=score_alone,
                                               coord=job.coord,
                                               centre_tolerance=centre_tolerance)
            results.append(SegmentResult(winner, [states[i] for i in range(n)]))
    return results


def staged_record(cf: CheapFrame, state: MSState | None, config: ScoreConfig) -> dict[str, Any]:
    """The score record (``T/memlog/scores``) of a frame scored by the staged selection: MS exact
    where it was needed, else its bounds (``ms`` null); ``rejected_by`` by the paper rule at the
    config's thresholds as far as the bounds decide it (``"unscored"`` where they do not)."""
    if cf.error is not None or cf.ss is None:
        return scores_message(cf.frame, None, config, cf.error)
    low, high = (0.0, min(1.0, cf.ss)) if state is None else (state.low, state.high)
    exact = state is not None and state.exact
    rejected: str | None
    if cf.ss < config.st:
        rejected = "staticity"
    elif cf.es is not None and cf.es < config.et:
        rejected = "entropy"
    elif high < config.mt:
        rejected = "memorability"
    elif low >= config.mt:
        rejected = None
    else:
        rejected = "unscored"
    m = None if state is None or state.m is None else np.asarray(state.m, dtype=np.float32).reshape(5, 5)
    crops = 0 if m is None else int(np.count_nonzero(~np.isnan(m)))
    fs = FrameScore(ms=low if exact else None, ss=cf.ss, es=cf.es, selected=rejected is None, rejected_by=rejected,
                    memorability=m, ms_low=low, ms_high=high, ms_exact=exact, crops_scored=crops,
                    detections=cf.detections, timing_ms=cf.timing_ms, width=cf.width, height=cf.height)
    return scores_message(cf.frame, fs, config, None)

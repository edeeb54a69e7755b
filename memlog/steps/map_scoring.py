"""The map step's scoring: staged segment selection (ResMem only where it can change the map).

Used by :mod:`memlog.steps.map` when frames are chosen by segment with the geometric score.
Pass 1 (:func:`cheap_chunk`, on workers in chunks; in a job, frames are decoded and scored on a
few threads while the reader reads ahead, :func:`_pipelined`) computes what every frame needs:
its entropy (the SPEC's E of the grey 1135 x 1135 frame from the full decode) and the view vector
(and, when selection needs it, the thumbnail), decoded once. The drive is cut into segments from
these; the detector then runs only on the frames that can still be their segment's candidate
(:func:`detect_chunk`, :func:`memlog.selection.staged.detect_in_segment`: in order of the bound
``es_static``, the frame's ES were every pixel static), and ResMem
(:func:`choose_chunk`, a group of segments per job, :func:`memlog.selection.staged.choose_in_segment`)
only as far as it can change the choice. With ``detect=True`` (the unstaged path: more
candidates per segment, or ES divided by the static pixels) pass 1 runs the detector on every
frame as well. The records say what was computed: ``ms`` null with bounds ``ms_low``/``ms_high``
where MS was not needed, ``ss`` and ``es`` null where the detector did not run.

The number of crops ResMem would score for a frame (``crops_needed``, the map's
``resmem_crops_full_scoring``) is counted only when ResMem can run at all.
"""

from __future__ import annotations

import os
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any, TypeVar

import numpy as np
import numpy.typing as npt

from memlog.descriptors.registry import make_describer
from memlog.errors import ImageDecodeError
from memlog.io.base import FrameError, FrameWindow, LogReader
from memlog.io.frame import Frame
from memlog.io.open import open_log
from memlog.io.records import ReadReport
from memlog.outputs.annotated import scores_message
from memlog.scoring.config import ScoreConfig
from memlog.scoring.scorer import FrameScore, Scorer, crops_needed, resize_frame, view_vector
from memlog.scoring.staticity import static_map
from memlog.selection.staged import MSResult, MSState, StaticityMode, choose_in_segment, detect_in_segment
from memlog.steps.parallel import Executor, InProcess, cached, job_threads
from memlog.steps.score import Chunk, plan_chunks

__all__ = ["CheapFrame", "cheap_chunk", "cheap_frames", "SegmentJob", "choose_chunk", "staged_record",
           "DetectJob", "Detected", "DetectRule", "detect_chunk", "detect_segments"]

T = TypeVar("T")
R = TypeVar("R")


@dataclass
class CheapFrame:
    """The cheap criteria of one frame (no pixels kept). ``ss``/``es`` None (and no error): the
    detector has not run on it (yet); ``es_static`` bounds its ES then (its ES were every pixel
    static, :class:`~memlog.scoring.scorer.EntropyBound`). ``crops_needed``: crops of non-zero
    weight, what scoring it fully would run (None: not counted, ResMem does not run)."""

    frame: Frame
    ss: float | None = None
    es: float | None = None
    detections: list[Any] = field(default_factory=list)
    width: int = 0
    height: int = 0
    crops_needed: int | None = None
    timing_ms: dict[str, float] = field(default_factory=dict)
    thumb: npt.NDArray[np.float32] | None = None
    view: npt.NDArray[np.float32] | None = None
    error: str | None = None
    es_static: float | None = None


def _scorer_for(config: ScoreConfig) -> Scorer:
    return cached(("scorer", config), lambda: Scorer(config))


def _pipelined(items: Iterable[T], work: Callable[[T], R], threads: int, depth: int | None = None
               ) -> Iterator[tuple[T, R]]:
    """``(item, work(item))`` in the order of ``items``, ``work`` running on ``threads`` threads
    while the caller's iterator reads ahead: at most ``depth`` items (default ``2 * threads``) in
    flight, so memory stays bounded. ``work`` releases the GIL in its numpy/OpenCV calls; an
    exception it raises is raised here, in order."""
    depth = max(1, depth or 2 * threads)
    pending: deque[tuple[T, Future[R]]] = deque()
    with ThreadPoolExecutor(max_workers=max(1, threads), thread_name_prefix="memlog-cheap") as pool:
        try:
            for item in items:
                pending.append((item, pool.submit(work, item)))
                while len(pending) >= depth:
                    x, fut = pending.popleft()
                    yield x, fut.result()
            while pending:
                x, fut = pending.popleft()
                yield x, fut.result()
        finally:
            for _, fut in pending:
                fut.cancel()


def cheap_threads(config: ScoreConfig) -> int:
    """Threads of pass 1 in one process: ``config.threads`` when set (a worker's share of the
    cores), else this process's cores."""
    if config.threads:
        return int(config.threads)
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def _cheap_iter(reader: LogReader, frames: Iterable[Frame], config: ScoreConfig, thumbs: bool, views: bool,
                detect: bool, crops: bool, errors: list[FrameError]) -> Iterator[CheapFrame]:
    """Pass 1 on ``frames`` of ``reader``, in order (see :func:`cheap_chunk`)."""
    scorer = _scorer_for(config)
    thumb = make_describer("thumbnail") if thumbs else None

    def one(f: Frame) -> CheapFrame | ImageDecodeError:
        t0 = time.perf_counter()
        try:
            bgr = f.decode_bgr()
        except ImageDecodeError as exc:
            return exc
        dt = (time.perf_counter() - t0) * 1e3
        if detect:
            c = scorer.cheap(bgr, keep_maps=False)
            cf = CheapFrame(f.stripped(), c.ss, c.es, c.detections, c.width, c.height,
                            crops_needed(c.static_map) if crops else None, {"decode": dt, **c.timing_ms})
        else:
            b = scorer.entropy_bound(bgr)
            cf = CheapFrame(f.stripped(), width=b.width, height=b.height, timing_ms={"decode": dt, **b.timing_ms},
                            es_static=b.es_static)
        if thumb is not None:
            cf.thumb = thumb.describe([bgr])[0]
        if views:
            cf.view = view_vector(bgr).astype(np.float32)
        return cf

    for f, res in _pipelined(frames, one, cheap_threads(config)):
        if isinstance(res, ImageDecodeError):
            err = reader.decode_error(f, res)
            errors.append(err)
            yield CheapFrame(f.stripped(), error=err.reason)
        else:
            yield res


def cheap_chunk(log: str, config: ScoreConfig, window: FrameWindow, chunk: Chunk | None,
                thumbs: bool, views: bool = False, detect: bool = True,
                crops: bool = True) -> tuple[list[CheapFrame], ReadReport, list[FrameError]]:
    """Pass 1 on one chunk (a worker's job): each frame decoded once (full size: the SPEC's
    1135 x 1135 frame is resized from it), its entropy (``detect``: and the detector, so SS and
    ES; else the bound ``es_static``), its view vector and thumbnail when asked; ``crops``: count
    the crops ResMem would score (only when it can run). Frames are scored on
    :func:`cheap_threads` threads while the reader reads ahead (:func:`_pipelined`)."""
    with open_log(log) as reader:
        if chunk is not None:
            reader.quiet_warnings()
        errors: list[FrameError] = []
        w = window if chunk is None else FrameWindow(window.topics, chunk.start_ns, chunk.end_ns, window.stride)
        frames = reader.frames(w.topics, w.start_ns, w.end_ns, w.stride, errors,
                               indices=None if chunk is None else chunk.indices)
        out = list(_cheap_iter(reader, frames, config, thumbs, views, detect, crops, errors))
        return out, reader.report, errors


def cheap_frames(log: str, reader: LogReader, config: ScoreConfig, window: FrameWindow, executor: Executor,
                 *, thumbs: bool, views: bool = False, chunk_frames: int = 64, detect: bool = True,
                 crops: bool = True) -> Iterator[CheapFrame]:
    """Pass 1 over ``window`` in log-time order (here, frame by frame, or in chunks on the
    executor's workers); workers' frame-level damage is added to ``reader.report``."""
    if isinstance(executor, InProcess):
        with open_log(log) as own:
            errors: list[FrameError] = []
            frames = own.frames(window.topics, window.start_ns, window.end_ns, window.stride, errors)
            yield from _cheap_iter(own, frames, config, thumbs, views, detect, crops, errors)
        return
    wcfg = config.replace(threads=job_threads(executor, config.threads))
    for frames_, rep, errs in executor.map_ordered(
            cheap_chunk, ((log, wcfg, window, c, thumbs, views, detect, crops)
                          for c in plan_chunks(reader, window, chunk_frames))):
        reader.absorb(rep, errs)
        yield from frames_


@dataclass
class DetectJob:
    """One segment of one topic for the staged detector: every decodable frame of it, with its
    entropy bound (``es_static``, full precision) and its segment coordinate."""

    topic: str
    indices: list[int]
    es_static: list[float]
    start_ns: int
    end_ns: int
    coord: list[float] | None = None


@dataclass(frozen=True)
class DetectRule:
    """Which frames of a segment the detector must see (:func:`~memlog.selection.staged.detect_in_segment`)."""

    mode: StaticityMode
    weights: tuple[float, float, float]
    min_ss: float
    min_es: float
    centre_tolerance: float


@dataclass
class Detected:
    """What the detector pass gave for one frame (as :meth:`Scorer.cheap` gives it)."""

    ss: float
    es: float
    detections: list[Any]
    timing_ms: dict[str, float]
    crops_needed: int | None = None


class _Frames:
    """The frames of one segment, read from the log when first asked for, in batches along the
    order they are likely asked in (bounded memory for long segments: a robot standing still)."""

    BATCH = 64

    def __init__(self, reader: LogReader, topic: str, indices: list[int], start_ns: int, end_ns: int,
                 stride: int) -> None:
        self.reader, self.topic, self.indices = reader, topic, indices
        self.start_ns, self.end_ns, self.stride = start_ns, end_ns, stride
        self.order: list[int] = list(range(len(indices)))
        self.frames: dict[int, Frame] = {}
        self.used: set[int] = set()

    def plan(self, order: list[int]) -> None:
        self.order = list(order)

    def get(self, row: int) -> Frame:
        if row not in self.frames:
            pos = self.order.index(row) if row in self.order else 0
            batch = [r for r in self.order[pos:] if r not in self.frames and r not in self.used][: self.BATCH]
            if row not in batch:
                batch = [row] + batch[: self.BATCH - 1]
            self.frames.clear()  # (read ahead and not asked for: at most one batch is held)
            want = {self.indices[r]: r for r in batch}
            for f in self.reader.frames([self.topic], self.start_ns, self.end_ns, self.stride,
                                        indices={self.topic: set(want)}):
                self.frames[want[f.index]] = f
            if row not in self.frames:
                raise ImageDecodeError(f"frame {self.indices[row]} of {self.topic} could not be read again")
        self.used.add(row)
        return self.frames.pop(row)


def detect_segments(reader: LogReader, config: ScoreConfig, stride: int, jobs: Iterable[DetectJob],
                    rule: DetectRule, crops: bool) -> Iterator[dict[int, Detected]]:
    """The staged detector on each segment of ``jobs`` (through ``reader``): per segment, the
    rows (positions in ``job.indices``) it ran on and what it found. A frame without dynamic
    objects keeps ``es_static`` as its ES (the same number the scorer computes for it); one with
    dynamic objects has its entropy map computed again and masked."""
    scorer = _scorer_for(config)
    for job in jobs:
        n = len(job.indices)
        frames = _Frames(reader, job.topic, job.indices, job.start_ns, job.end_ns, stride)
        bound = [round(float(v), 6) for v in job.es_static]
        frames.plan(sorted(range(n), key=lambda r: (-bound[r], r)))
        found: dict[int, Detected] = {}

        def detect(row: int, job: DetectJob = job, frames: _Frames = frames,
                   found: dict[int, Detected] = found) -> tuple[float, float]:
            f = frames.get(row)
            t0 = time.perf_counter()
            bgr = f.decode_bgr()
            dt = (time.perf_counter() - t0) * 1e3
            c = scorer.cheap(bgr, keep_maps=False, es_static=job.es_static[row])
            assert c.es is not None  # every score: the staged path scores with all_scores
            timing = {"decode_again": dt, "resize_again": c.timing_ms.get("resize", 0.0),
                      "staticity": c.timing_ms.get("staticity", 0.0), "entropy_again": c.timing_ms.get("entropy", 0.0)}
            found[row] = Detected(c.ss, c.es, c.detections, timing, crops_needed(c.static_map) if crops else None)
            return round(c.ss, 6), round(c.es, 6)

        detect_in_segment(n, bound, detect, mode=rule.mode, weights=rule.weights, min_ss=rule.min_ss,
                          min_es=rule.min_es, coord=job.coord, centre_tolerance=rule.centre_tolerance)
        yield found


def detect_chunk(log: str, config: ScoreConfig, window: FrameWindow, jobs: list[DetectJob], rule: DetectRule,
                 crops: bool) -> list[dict[int, Detected]]:
    """The staged detector on a group of segments (a worker's job; :func:`detect_segments`)."""
    with open_log(log) as reader:
        reader.quiet_warnings()
        return list(detect_segments(reader, config, window.stride, jobs, rule, crops))


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
    config's thresholds as far as the bounds decide it (``"unscored"`` where they do not). A frame
    the detector did not run on (it could not be its segment's candidate) has ``ss`` and ``es``
    null too, MS within [0, 1], and ``rejected_by`` ``"unscored"``."""
    if cf.error is not None:
        return scores_message(cf.frame, None, config, cf.error)
    if cf.ss is None:
        fs0 = FrameScore(ms=None, ss=None, es=None, selected=False, rejected_by="unscored", ms_low=0.0, ms_high=1.0,
                         ms_exact=False, timing_ms=cf.timing_ms, width=cf.width, height=cf.height)
        return scores_message(cf.frame, fs0, config, None)
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

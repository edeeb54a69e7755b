"""Pipeline step ``map``: the memorable-map log (kept frames only) and its reference descriptors.

:func:`make_map` scores the log (or reuses an annotated MCAP from ``memlog score``), builds a
:class:`~memlog.selection.ScoreTable` per camera topic (with positions from a GNSS/pose topic
when the log has one), selects frames once (:class:`~memlog.selection.config.SelectionConfig`)
and writes, in one more pass over the log,

* ``MAP.mcap`` (:class:`~memlog.outputs.maplog.MapLogWriter`): the selected frames, their score
  records, the topics kept whole and metadata ``memlog_map``;
* ``MAP.parquet`` (:mod:`memlog.outputs.descriptor_table`): one reference descriptor per kept
  frame, described in batches while the map is written.

The two are one artefact (:mod:`memlog.outputs.map_artefact`): each records the other's sha256,
and they are put in place together when both are complete, so a failed run leaves the earlier
pair (or neither file), never a new map beside an old Parquet;
:func:`~memlog.outputs.map_artefact.check_map_pair` checks that a Parquet belongs to a map.

The :class:`MapResult` carries the selections, so ``evaluate`` measures exactly the map written.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Collection, Iterable, Mapping, Sequence
from concurrent.futures import Future
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from memlog.configfile import check_ints
from memlog.descriptors.auto import AUTO, DescriptorChoice, resolve_descriptor
from memlog.descriptors.extract import ReferenceDescribing, drive_distinctiveness
from memlog.descriptors.registry import DESCRIBERS, make_describer
from memlog.errors import ConfigError, ImageDecodeError, SelectionError
from memlog.io.atomic import check_output
from memlog.io.base import FrameWindow, LogReader
from memlog.io.identity import same_identity
from memlog.io.open import open_log
from memlog.io.positions import MotionTrack, PositionTrack, read_tracks
from memlog.io import spool
from memlog.io.records import ReadReport
from memlog.models.runtime import choose_providers, on_thread
from memlog.outputs.annotated import read_scores, run_config, run_input_identity, scores_message
from memlog.progress import progress
from memlog.settings import Flag, count_or_all, int_range, positive_int, setting
from memlog.scoring.config import ScoreConfig
from memlog.scoring.motion import frame_motion
from memlog.scoring.scorer import view_vector
from memlog.selection import ScoreTable, Selection
from memlog.selection.config import DEFAULT_CANDIDATES, SelectionConfig
from memlog.selection.segment import SegmentConfig, cut_segments
from memlog.selection.staged import MSState, StaticityMode, staticity_mode
from memlog.steps import map_scoring
from memlog.steps.map_log import Looks, MapPlan, MapResult, drive_stops, moving_frames, write_map_log
from memlog.steps.map_scoring import (CheapFrame, Detected, DetectJob, DetectRule, SegmentJob, cheap_frames,
                                      choose_chunk, detect_chunk, detect_segments, staged_record)
from memlog.steps.parallel import Executor, InProcess, job_threads, make_executor
from memlog.steps.score import end_at_container, scored_frames

__all__ = ["make_map", "MapConfig", "MapResult", "Looks", "score_table", "EmptyMapError", "collect_scores", "staged_scores",
           "staged_scores_and_looks", "staged_stageable"]

Records = dict[str, list[dict[str, Any]]]


class EmptyMapError(SelectionError):
    """No frame passed the selection."""


@dataclass(frozen=True)
class MapConfig:
    """Settings of the map step (the ``[map]`` table; scoring and selection have their own).

    ``topics``: camera topics to map (default: every camera topic); ``keep_topics``: topics
    copied whole (GPS, odometry); ``position_topic``: NavSatFix/pose/odometry topic for
    positions (default: the first found); ``image_format``/``jpeg_quality``: how raw frames
    are encoded; ``descriptor``: reference descriptor kind (``"auto"``: chosen from the frame
    size, :mod:`memlog.descriptors.auto`; None: no descriptors); ``descriptors_path``: the Parquet
    file (default: the map path with ``.parquet``); ``descriptor_dtype``: how it stores them,
    float32 or float16 (half the size; read back as float32); ``whiten``: fit a PCA-whitening and
    store it with the map (:mod:`memlog.descriptors.whitening`), fitted, with the patch PCA, on the
    drive's moving frames (:func:`~memlog.steps.map_log.moving_frames`: one transform per drive,
    whatever the map keeps; frames not kept are described for it but not stored); fewer than
    :data:`~memlog.descriptors.whitening.MIN_SAMPLES` leave the map unwhitened;
    ``whiten_dim``: its largest dimension (default: the documented rule); ``workers``: processes
    scoring frames; ``candidates``: with segment selection, score at most this many frames per
    segment with ResMem (the best by their cheap scores, spread over the segment; approximate;
    default :data:`~memlog.selection.config.DEFAULT_CANDIDATES`), or ``"all"``: exactly the
    frames that can still win (the same frames as scoring every frame); ``stride``: consider every n-th
    frame of each topic only (frame indices stay positions on the topic); ``score_kept``: also run
    ResMem on a segment's only candidate (``candidates=1``, or one passing frame) to record its MS —
    by default it is not run there, because its MS chooses nothing (the record's ``ms`` is null,
    ``ms_low``/``ms_high`` its bounds), unless the selection has an MS minimum.
    """

    score: ScoreConfig = field(default_factory=ScoreConfig)
    select: SelectionConfig = field(default_factory=SelectionConfig)
    topics: tuple[str, ...] | None = setting(None, Flag(
        ("-t", "--topic"), "camera topic(s) to map (repeatable; default: every camera topic)", "inputs",
        action="append", dest="topics", metavar="TOPIC", value=tuple))
    keep_topics: tuple[str, ...] = setting((), Flag(
        ("--keep-topic",), "copy this topic whole into the map (GPS, odometry...; repeatable)", "outputs",
        action="append", metavar="TOPIC", value=tuple))
    position_topic: str | None = setting(None, Flag(
        ("--position-topic",), "NavSatFix/pose/odometry topic for positions (default: first found)", "inputs",
        metavar="TOPIC"))
    image_format: Literal["jpeg", "png"] = setting("jpeg", Flag(
        ("--image-format",), "encoding of raw frames (default jpeg)", "outputs", choices=("jpeg", "png")))
    jpeg_quality: int = setting(90, Flag(("--jpeg-quality",), "JPEG quality of raw frames, 1..100 (default 90)",
                                         "outputs", int_range(1, 100), metavar="Q"))
    descriptor: str | None = setting(AUTO, Flag(
        ("--descriptor",), "reference descriptor: auto (default: by frame size), a kind (thumbnail, dinov2-gem, ...) "
        "or none", "outputs", metavar="KIND", value=lambda v: None if v == "none" else v))
    descriptors_path: str | None = setting(None, Flag(
        ("--descriptors",), "descriptor Parquet path (default: OUT.parquet)", "outputs", metavar="PATH"))
    descriptor_dtype: Literal["float32", "float16"] = setting("float32", Flag(
        ("--descriptor-dtype",), "storage of the descriptors (default float32; float16 halves the file)", "outputs",
        choices=("float32", "float16")))
    whiten: bool = setting(True, Flag(
        ("--no-whiten",), "do not fit and store a PCA-whitening of the descriptors (default: whitened, one "
        "whitening per drive, fitted on its moving frames)", "outputs",
        action="store_true", value=lambda v: False))
    whiten_dim: int | None = setting(None, Flag(
        ("--whiten-dim",), "largest whitened dimension (default 512; never more than half the frames)", "outputs",
        positive_int, metavar="D"))
    workers: int = setting(1, Flag(("--workers",), "worker processes scoring frames (default 1)", "performance",
                                   positive_int, metavar="N"))
    candidates: int | Literal["all"] = setting(DEFAULT_CANDIDATES, Flag(
        ("--candidates",), "segment selection: run ResMem on at most K frames per segment, the best by staticity and "
        f"entropy spread over the segment (approximate; default {DEFAULT_CANDIDATES}, see docs/defaults.md); 'all': "
        "exactly the frames that can still win, which keeps the same frames as scoring every frame", "selection",
        count_or_all, metavar="K|all"))
    stride: int = setting(1, Flag(("--stride",), "consider every n-th frame of each topic (default 1)", "inputs",
                                  positive_int, metavar="N"))
    score_kept: bool = setting(False, Flag(
        ("--score-kept",), "also run ResMem (25 crops) on a segment's only candidate to record its memorability; by "
        "default it is not run where it would choose nothing (--candidates 1): the kept frame's record has ms null "
        "and its bounds", "scoring", action="store_true", default=None))

    def __post_init__(self) -> None:
        if not isinstance(self.score_kept, bool):
            raise ConfigError(f"score_kept must be true or false, got {self.score_kept!r}")
        if self.descriptor is not None and self.descriptor != AUTO and self.descriptor not in DESCRIBERS:
            raise ConfigError(f"descriptor must be auto, one of {', '.join(sorted(DESCRIBERS))} or none, "
                              f"got {self.descriptor!r}")
        if self.descriptor_dtype not in ("float32", "float16"):
            raise ConfigError(f"descriptor_dtype must be float32 or float16, got {self.descriptor_dtype!r}")
        if self.candidates != "all" and (isinstance(self.candidates, bool) or not isinstance(self.candidates, int)
                                         or self.candidates < 1):
            raise ConfigError(f"candidates must be an integer >= 1 or 'all', got {self.candidates!r}")
        check_ints(self, {"workers": 1, "stride": 1, "whiten_dim": 1}, optional=True)
        if self.image_format not in ("jpeg", "png"):
            raise ConfigError(f"image_format must be jpeg or png, got {self.image_format!r}")
        q = self.jpeg_quality
        if isinstance(q, bool) or not isinstance(q, int) or not 1 <= q <= 100:
            raise ConfigError(f"jpeg_quality must be an integer in 1..100, got {q!r}")
        if self.topics is not None:
            object.__setattr__(self, "topics", tuple(self.topics))
        object.__setattr__(self, "keep_topics", tuple(self.keep_topics))

    def descriptors_file(self, output: str | os.PathLike[str]) -> Path | None:
        """Where the reference descriptors go (None without a descriptor)."""
        if self.descriptor is None:
            return None
        return Path(self.descriptors_path) if self.descriptors_path else Path(output).with_suffix(".parquet")


def _val(v: Any) -> float:
    return float("nan") if v is None else float(v)


def score_table(records: list[dict[str, Any]], topic: str, track: PositionTrack | None = None,
                descriptors: np.ndarray | None = None, ds: dict[int, float] | None = None,
                view: np.ndarray | None = None, motion: Sequence[MotionTrack] = ()) -> ScoreTable:
    """A ScoreTable from score records (``T/memlog/scores`` messages) of one topic; records of
    frames that did not decode are left out. Where MS was only bounded (staged selection), its
    lower bound stands in: such a frame provably did not win its segment, or was its segment's one
    candidate (MS did not choose). ``ds``: distinctiveness by frame index; ``descriptors``/``view``
    one row per kept record; ``motion``: the log's (:func:`memlog.io.positions.read_motion`), at
    the frames when a topic of it knows every one (the stops then come from it)."""
    recs = [r for r in records if r.get("rejected_by") != "undecodable"]
    t = np.array([r["log_time"] for r in recs], dtype=np.int64)
    pos = track.at(t.tolist()) if track is not None and len(recs) else None
    if pos is not None and np.isnan(pos).all():
        pos = None
    return ScoreTable(
        index=np.array([r["frame_index"] for r in recs], dtype=np.int64), t_ns=t,
        ms=np.array([_val(r["ms"] if r["ms"] is not None else r.get("ms_low")) for r in recs]),
        ss=np.array([_val(r["ss"]) for r in recs]),
        es=np.array([_val(r["es"]) for r in recs]), positions=pos, descriptors=descriptors, topic=topic,
        ds=None if ds is None else np.array([ds.get(r["frame_index"], np.nan) for r in recs]), view=view,
        motion=frame_motion(motion, t),
    )


def collect_scores(
    log: str, reader: LogReader, config: ScoreConfig, window: FrameWindow, executor: Executor | None = None,
) -> Records:
    """Score the frames of ``window`` without writing them: score records per camera topic (as in
    ``T/memlog/scores``)."""
    out: Records = {}
    total = reader.count_frames(window)
    frames = scored_frames(log, reader, config, window, executor=executor)
    for item in progress(frames, total=total, desc="score", unit="frame"):
        rec = scores_message(item.frame, item.score, config, item.error)
        rec.pop("memorability", None)
        out.setdefault(item.frame.topic, []).append(rec)
    return out



def frame_looks(reader: LogReader, topic: str, indices: set[int], thumbs: bool, views: bool
                ) -> dict[int, tuple[np.ndarray | None, np.ndarray | None]]:
    """:data:`Looks` of the given frames of ``topic`` (one pass over that topic's frames)."""
    d = make_describer("thumbnail") if thumbs else None
    out: dict[int, tuple[np.ndarray | None, np.ndarray | None]] = {}
    for f in reader.frames([topic], indices={topic: indices}):
        try:
            bgr = f.decode_bgr()
        except ImageDecodeError as exc:  # reported; it has no scores either
            reader.decode_error(f, exc)
            continue
        out[f.index] = (d.describe([bgr])[0] if d is not None else None,
                        view_vector(bgr).astype(np.float32) if views else None)
    return out


def _scores_from(scores: str | os.PathLike[str] | Records, cfg: MapConfig, log: str) -> Records:
    """Score records of a scoring run to reuse: refused when made from another log (or with early
    exit when selection needs every score), or when a camera topic to map has none."""
    if isinstance(scores, dict):
        return scores
    ident = run_input_identity(scores)
    if ident is not None and not same_identity(ident, log):
        raise ConfigError(f"--scores {scores}: it was scored from {ident.get('path')}, not from {log} "
                          "(or that log changed since); score this log first")
    used = run_config(scores)
    if cfg.select.needs_all_scores and used is not None and not (used.all_scores or used.mode == "paper"):
        raise ConfigError(
            f"--scores {scores}: scored with early exit, so skipped scores are missing; --keep-fraction and "
            "--select segment need every score: run `memlog score --all-scores` first"
        )
    recs = read_scores(scores)
    missing = [t for t in (cfg.topics or ()) if t not in recs]
    if missing:
        raise ConfigError(f"--scores {scores}: no scores for topic {', '.join(missing)} "
                          f"(it has scores for: {', '.join(sorted(recs)) or 'none'})")
    if not recs:
        raise ConfigError(f"--scores {scores}: holds no score records (is it an output of `memlog score`?)")
    return recs


def _window(cams: list[str], cfg: MapConfig, window: FrameWindow | None) -> FrameWindow:
    """The frames to score: ``window``'s times and stride on the camera topics ``cams`` (default:
    every frame at ``cfg.stride``)."""
    if window is None:
        return FrameWindow(tuple(cams), stride=cfg.stride)
    return FrameWindow(tuple(cams), window.start_ns, window.end_ns, window.stride)


def _stageable(cfg: MapConfig) -> bool:
    """Whether the staged selection applies: segments chosen by the geometric score, and the
    user did not ask for every score (``--all-scores``) or the literal pipeline, and distinctiveness
    (a score over the whole drive) is not part of the choice."""
    sel = cfg.select
    return sel.mode == "segment" and sel.combine == "geometric" and not cfg.score.all_scores \
        and cfg.score.mode != "paper" and not sel.needs_distinctiveness


def _selections(reader: LogReader, cfg: MapConfig, cams: list[str], recs_by_topic: Records,
                track: PositionTrack | None, looks: Looks | None,
                ds_by_topic: dict[str, dict[int, float]] | None = None,
                tables: dict[str, ScoreTable] | None = None, motion: Sequence[MotionTrack] = ()) -> dict[str, Selection]:
    """Select once per topic from the score records (and the frames' looks when selection needs
    them, and the log's ``motion``); ``tables`` receives each topic's ScoreTable."""
    selections: dict[str, Selection] = {}
    for t in cams:
        recs = recs_by_topic.get(t, [])
        descs = view = None
        if looks is not None and recs:
            have = looks.get(t, {})
            recs = [r for r in recs if r["frame_index"] in have]
            if recs and cfg.select.needs_descriptors:
                descs = np.stack([np.asarray(have[r["frame_index"]][0]) for r in recs]).astype(np.float32)
            if recs and _needs_view(cfg):
                view = np.stack([np.asarray(have[r["frame_index"]][1]) for r in recs]).astype(np.float32)
        table = score_table(recs, t, track, descs, None if ds_by_topic is None else ds_by_topic.get(t, {}), view,
                            motion)
        left_out = len(recs_by_topic.get(t, [])) - table.n
        if left_out:
            reader.warn(f"{reader.path}: topic {t}: {left_out} frame(s) left out of the selection "
                        "(they did not decode; see the warnings above)")
        selections[t] = cfg.select.run(table, shortlist=_shortlist(cfg), ms_bound=_ms_bound(cfg))
        if tables is not None:
            tables[t] = table
    return selections


def _shortlist(cfg: MapConfig) -> int | None:
    """Candidates per segment of segment selection (None: every frame, exact)."""
    return None if cfg.candidates == "all" or cfg.select.mode != "segment" else int(cfg.candidates)


def _ms_bound(cfg: MapConfig) -> str:
    return "one" if cfg.score.normalize == "static" else "ss"


def _needs_view(cfg: MapConfig) -> bool:
    """Every frame's view vector is needed: by selection, or for the map's moving index (the
    stops the query's are found alike with), whatever ``--select``, when descriptors are written."""
    return cfg.select.needs_view or cfg.descriptor is not None


def _needs_looks(cfg: MapConfig) -> bool:
    return cfg.select.needs_descriptors or _needs_view(cfg)


Crops = tuple[int | None, int | None]


def _full(log: str, reader: LogReader, cfg: MapConfig, cams: list[str], track: PositionTrack | None,
          ex: Executor, scores: str | os.PathLike[str] | Records | None,
          known_looks: Looks | None = None, window: FrameWindow | None = None) -> tuple[Records, Looks | None, Crops]:
    """Every score of every frame (or a reused scoring run), and the frames' looks when selection
    needs them (one more pass over the frames, unless ``known_looks`` has every frame's)."""
    sel_cfg = cfg.select
    crops: Crops = (None, None)
    if scores is None:
        score_cfg = cfg.score.replace(all_scores=True) if sel_cfg.needs_all_scores else cfg.score
        recs_by_topic = collect_scores(log, reader, score_cfg, _window(cams, cfg, window), ex)
        n = sum(int(r.get("crops_scored") or 0) for recs in recs_by_topic.values() for r in recs)
        crops = (n, n if score_cfg.all_scores else None)
    else:
        recs_by_topic = _scores_from(scores, cfg, log)
    looks: Looks | None = None
    if _needs_looks(cfg):
        looks = {}
        for t in cams:
            need = {r["frame_index"] for r in recs_by_topic.get(t, []) if r.get("rejected_by") != "undecodable"}
            have = (known_looks or {}).get(t, {})
            if need <= have.keys() and all((v[0] is not None or not sel_cfg.needs_descriptors)
                                           and (v[1] is not None or not _needs_view(cfg)) for v in have.values()):
                looks[t] = {i: have[i] for i in need}
            else:
                looks[t] = frame_looks(reader, t, need, sel_cfg.needs_descriptors, _needs_view(cfg))
    return recs_by_topic, looks, crops


def _resmem_may_run(cfg: MapConfig) -> bool:
    """Whether the staged selection can run ResMem at all (:func:`~memlog.selection.staged.choose_in_segment`):
    not when MS does not count, nor with one candidate per segment that is kept without it."""
    sel = cfg.select
    if sel.weights[0] <= 0 and sel.min_ms <= 0:
        return False
    return _shortlist(cfg) != 1 or cfg.score_kept or sel.min_ms > 0


def _scores_of(frames: list[CheapFrame], name: str) -> np.ndarray:
    """SS or ES of the frames as score records store them (6 decimals); NaN where not computed."""
    return np.array([np.nan if getattr(cf, name) is None else round(float(getattr(cf, name)), 6) for cf in frames])


def _staged(log: str, reader: LogReader, cfg: MapConfig, cams: list[str], track: PositionTrack | None,
            ex: Executor, motion: Sequence[MotionTrack] = (), *, window: FrameWindow | None = None,
            stage_staticity: bool = True) -> tuple[Records, Looks | None, Crops]:
    """Staged segment selection (:mod:`memlog.steps.map_scoring`): the entropy and view of every
    frame, segments, the detector only where it can change which frame is a segment's candidate
    (``stage_staticity=False``: on every frame, the unstaged path), then ResMem only where it can
    change which frame a segment keeps."""
    sel_cfg = cfg.select
    score_cfg = cfg.score.replace(all_scores=True)  # every score of the frames that are scored
    window = _window(cams, cfg, window)
    shortlist = _shortlist(cfg)
    mode: StaticityMode = "every"
    if stage_staticity:
        mode = staticity_mode(tuple(sel_cfg.weights), sel_cfg.min_ms, shortlist,  # type: ignore[arg-type]
                              es_bounded=cfg.score.normalize == "all")
    detect_first = mode == "every"  # the detector on every frame in pass 1
    resmem = _resmem_may_run(cfg)
    cheap: dict[str, list[CheapFrame]] = {t: [] for t in cams}
    total = reader.count_frames(window)
    warm = _warm_detector(score_cfg) if not detect_first and isinstance(ex, InProcess) else None
    for cf in progress(cheap_frames(log, reader, score_cfg, window, ex, thumbs=sel_cfg.needs_descriptors,
                                    views=_needs_view(cfg), detect=detect_first, crops=resmem),
                       total=total, desc="cheap scores" if detect_first else "entropy", unit="frame"):
        cheap[cf.frame.topic].append(cf)
    if warm is not None:
        warm.result()  # (a model that cannot load says so here)
    seg_cfg = SegmentConfig(**sel_cfg.segment_settings())
    cut: dict[str, tuple[list[CheapFrame], ScoreTable, np.ndarray, np.ndarray | None]] = {}
    for t in cams:
        good = [cf for cf in cheap[t] if cf.error is None]
        if not good:
            continue
        t_ns = np.array([cf.frame.log_time_ns for cf in good], dtype=np.int64)
        table = ScoreTable(
            index=np.array([cf.frame.index for cf in good], dtype=np.int64), t_ns=t_ns,
            ms=np.zeros(len(good)), ss=_scores_of(good, "ss"), es=_scores_of(good, "es"),
            positions=_positions(track, good),
            descriptors=np.stack([np.asarray(cf.thumb) for cf in good]) if sel_cfg.needs_descriptors else None,
            view=np.stack([np.asarray(cf.view) for cf in good]) if _needs_view(cfg) else None,
            topic=t, motion=frame_motion(motion, t_ns))
        seg, coord, _ = cut_segments(table, seg_cfg)  # (segments do not depend on the scores)
        cut[t] = (good, table, seg, coord)
    if not detect_first:
        rule = DetectRule(mode, (float(sel_cfg.weights[0]), float(sel_cfg.weights[1]), float(sel_cfg.weights[2])),
                          sel_cfg.min_ss, sel_cfg.min_es, sel_cfg.centre_tolerance)
        _detect_staged(log, score_cfg, window, ex, cut, rule, resmem,
                       {t: reader.frame_table(t).entries()[1] for t in cut})
        for good, table, _seg, _coord in cut.values():
            table.ss, table.es = _scores_of(good, "ss"), _scores_of(good, "es")
    jobs: list[tuple[str, list[int], SegmentJob]] = []
    for t, (good, table, seg, coord) in cut.items():
        with np.errstate(invalid="ignore"):
            passing = (table.ss >= sel_cfg.min_ss) & (table.es >= sel_cfg.min_es)  # (NaN: not detected, fails)
        for sid in np.unique(seg):
            rows = [int(r) for r in np.flatnonzero((seg == sid) & passing)]
            if not rows:
                continue
            jobs.append((t, rows, SegmentJob(
                t, [int(table.index[r]) for r in rows], [float(table.ss[r]) for r in rows],
                [float(table.es[r]) for r in rows], [good[r].detections for r in rows],
                int(table.t_ns[rows[0]]), int(table.t_ns[rows[-1]]) + 1,
                None if coord is None else [float(coord[r]) for r in rows])))
    states: dict[tuple[str, int], MSState] = {}
    group = max(1, min(32, len(jobs) // max(1, 4 * ex.workers)))
    batches = [jobs[i:i + group] for i in range(0, len(jobs), group)]
    wcfg = score_cfg.replace(threads=job_threads(ex, score_cfg.threads))
    args = ((log, score_cfg if isinstance(ex, InProcess) else wcfg, window, [j for _, _, j in b], sel_cfg.weights,
             sel_cfg.min_ms, shortlist, cfg.score_kept or shortlist is None, sel_cfg.centre_tolerance)
            for b in batches)
    results = ex.map_ordered(choose_chunk, args)
    if resmem:  # (otherwise every segment's choice is made without ResMem: nothing to show)
        results = progress(results, total=len(batches), desc="memorability", unit="job")
    for b, res in zip(batches, results):
        for (t, _rows, job), r in zip(b, res):
            for idx, st in zip(job.indices, r.states):
                states[(t, idx)] = st
    recs_by_topic: Records = {}
    run = 0
    full: int | None = 0
    for t in cams:
        recs = []
        for cf in cheap[t]:
            state = states.get((t, cf.frame.index))
            recs.append(staged_record(cf, state, cfg.score))
            run += state.crops_run if state is not None else 0
            if cf.error is None:
                full = None if full is None or cf.crops_needed is None else full + cf.crops_needed
        recs_by_topic[t] = recs
    looks: Looks | None = None
    if _needs_looks(cfg):
        looks = {t: {cf.frame.index: (cf.thumb, cf.view) for cf in cheap[t] if cf.error is None} for t in cams}
    return recs_by_topic, looks, (run, full)


def _warm_detector(config: ScoreConfig) -> Future[None] | None:
    """Load the detector of this process's scorer for ``config`` (and run its slower first forward)
    on a thread while pass 1 computes entropy: the staged detection then starts at once. None when
    the scorer's staticity stage has nothing to warm (a staticity given to the scorer)."""
    scorer = map_scoring._scorer_for(config)  # (through the module: the one detection uses; tests replace it)
    warm = getattr(scorer.staticity, "warm", None)
    return None if warm is None else on_thread(warm)


def _detect_staged(log: str, score_cfg: ScoreConfig, window: FrameWindow, ex: Executor,
                   cut: dict[str, tuple[list[CheapFrame], ScoreTable, np.ndarray, np.ndarray | None]],
                   rule: DetectRule, crops: bool, containers: Mapping[str, np.ndarray] | None = None) -> None:
    """The detector on the frames of each segment that can still be its candidate
    (:func:`~memlog.steps.map_scoring.detect_segments`); fills their SS, ES and detections in.
    ``containers``: per topic, the log chunk each frame lies in (a worker's group of segments then
    ends where a log chunk ends, so two workers do not both read one chunk)."""
    djobs: list[tuple[list[CheapFrame], list[int], DetectJob]] = []
    for t, (good, table, seg, coord) in cut.items():
        starts = np.flatnonzero(np.concatenate([[True], seg[1:] != seg[:-1]]))
        ends = np.concatenate([starts[1:], [len(seg)]])
        for a, e in zip(starts.tolist(), ends.tolist()):
            rows = list(range(a, e))
            djobs.append((good, rows, DetectJob(
                t, [int(table.index[r]) for r in rows], [float(good[r].es_static or 0.0) for r in rows],
                int(table.t_ns[a]), int(table.t_ns[e - 1]) + 1,
                None if coord is None else [float(coord[r]) for r in rows])))
    found: Iterable[dict[int, Detected]]
    if isinstance(ex, InProcess):
        own = open_log(log)
        own.quiet_warnings()
        found = progress(detect_segments(own, score_cfg, window.stride, (j for _, _, j in djobs), rule, crops),
                         total=len(djobs), desc="staticity", unit="segment")
    else:
        group = max(1, min(32, len(djobs) // max(1, 4 * ex.workers)))
        batches = _segment_groups(djobs, group, containers or {})
        wcfg = score_cfg.replace(threads=job_threads(ex, score_cfg.threads))
        per_batch = progress(ex.map_ordered(detect_chunk, ((log, wcfg, window, [j for _, _, j in b], rule, crops)
                                                           for b in batches)),
                             total=len(batches), desc="staticity", unit="job")
        found = (f for res in per_batch for f in res)
        own = None
    try:
        for (good, rows, _job), got in zip(djobs, found):
            for r, d in got.items():
                cf = good[rows[r]]
                cf.ss, cf.es, cf.detections, cf.crops_needed = d.ss, d.es, d.detections, d.crops_needed
                cf.timing_ms.update(d.timing_ms)
    finally:
        if own is not None:
            own.close()


def _segment_groups(djobs: list[tuple[list[CheapFrame], list[int], DetectJob]], group: int,
                    containers: Mapping[str, np.ndarray]) -> list[list[tuple[list[CheapFrame], list[int], DetectJob]]]:
    """``djobs`` in groups of about ``group`` segments, in order, each ending where a log chunk
    ends when that is near (:func:`~memlog.steps.score.end_at_container`)."""

    def place(k: int, at: int) -> int | None:
        job = djobs[k][2]
        c = containers.get(job.topic)
        return None if c is None or not job.indices else int(c[job.indices[at]])

    out = []
    i = 0
    while i < len(djobs):
        end = end_at_container(lambda k: place(k, 0), lambda k: place(k, -1), len(djobs), min(i + group, len(djobs)),
                               group)
        out.append(djobs[i:end])
        i = end
    return out


def staged_stageable(cfg: MapConfig) -> bool:
    """Whether ``memlog map`` with ``cfg`` scores by the staged selection (:func:`staged_scores`)."""
    return _stageable(cfg)


def staged_scores_and_looks(log: str | os.PathLike[str], config: MapConfig, window: FrameWindow | None = None,
                  executor: Executor | None = None, *, stage_staticity: bool = True
                  ) -> tuple[Records, Looks | None, ReadReport]:
    """The score records of ``log`` (per camera topic, as ``T/memlog/scores``) that ``memlog map``
    with ``config`` computes by the staged selection (``staged_stageable(config)`` must hold):
    the detector and ResMem only where they can change the map, ``ss``/``es``/``ms`` null where
    they did not run. ``window``: the frames to score (default: ``config``'s topics and stride).
    Selecting from these records keeps the frames the map keeps (``stage_staticity=False``: the
    detector on every frame, as :func:`make_map` has it). Also the frames' looks (thumbnail and view
    vector, where selection needs them), which :func:`make_map` takes as ``known_looks`` instead of
    decoding every frame again."""
    cfg = config
    if not _stageable(cfg):
        raise ConfigError("staged_scores: these settings do not select by the staged segment selection")
    with open_log(log) as reader:
        cams = reader.check_camera_topics(window.topics if window is not None and window.topics else cfg.topics)
        track, motion = read_tracks(reader, cfg.position_topic)
        w = _window(cams, cfg, window)
        ex = executor or make_executor(cfg.workers)
        try:
            recs, looks, _crops = _staged(str(log), reader, cfg, cams, track, ex, motion, window=w,
                                          stage_staticity=stage_staticity)
        finally:
            if executor is None:
                ex.close()
        return recs, looks, reader.report


def staged_scores(log: str | os.PathLike[str], config: MapConfig, window: FrameWindow | None = None,
                  executor: Executor | None = None, *, stage_staticity: bool = True) -> tuple[Records, ReadReport]:
    """The score records :func:`staged_scores_and_looks` gives, and the log's read report."""
    recs, _looks, report = staged_scores_and_looks(log, config, window, executor, stage_staticity=stage_staticity)
    return recs, report


def _positions(track: PositionTrack | None, frames: list[CheapFrame]) -> np.ndarray | None:
    if track is None or not frames:
        return None
    pos = track.at([cf.frame.log_time_ns for cf in frames])
    return None if np.isnan(pos).all() else pos


def make_map(
    log: str | os.PathLike[str],
    output: str | os.PathLike[str],
    config: MapConfig | None = None,
    *,
    scores: str | os.PathLike[str] | Records | None = None,
    executor: Executor | None = None,
    known_descriptors: dict[tuple[str, int], np.ndarray] | None = None,
    known_patches: dict[tuple[str, int], np.ndarray] | None = None,
    stage_staticity: bool = True,
    keep_frames: Mapping[str, Collection[int]] | None = None,
    known_looks: Looks | None = None,
    window: FrameWindow | None = None,
) -> MapResult:
    """Build the memorable-map log of ``log`` (see module doc). ``scores``: an annotated MCAP of
    ``memlog score`` (or its records) to reuse instead of scoring; ``executor``: where scoring jobs
    run (default: ``config.workers`` local processes); ``known_descriptors``: raw descriptors of
    the configured kind by ``(topic, frame index)``, used instead of describing those frames again
    (``evaluate`` has them; ``known_patches``: their raw pooled patch features, the same way).
    ``stage_staticity=False``: the staged selection runs the detector on every frame (the unstaged
    path; it keeps the same frames, and is kept for comparison). ``keep_frames``: the frames to keep, by
    topic, instead of the selection's (``evaluate``'s baselines: every k-th and random frames written
    as maps by this same writer; the selection still runs, for the records, and the map's metadata
    says the frames were given). ``known_looks``: the frames' looks from an earlier pass
    (:func:`staged_scores_and_looks`, or :attr:`MapResult.looks`), used with ``scores`` instead of
    decoding every frame again. ``window``: score and select only these frames (times and stride;
    ``evaluate``'s quick trials), instead of every frame at ``config.stride``. Raises
    :class:`EmptyMapError` when nothing would be kept."""
    t0 = time.perf_counter()
    cfg = config or MapConfig()
    dpath = _check_map_inputs(log, output, cfg, scores, executor)
    with spool.job(log), open_log(log) as reader:  # (each chunk read from the log once: memlog.io.spool)
        cams = reader.check_camera_topics(cfg.topics)
        missing_keep = set(cfg.keep_topics) - set(reader.topics())
        if missing_keep:
            raise ConfigError(f"--keep-topic: {reader.path} has no topic {', '.join(sorted(missing_keep))} "
                              f"(topics: {', '.join(reader.topics())})")
        # positions (None when the log has no position topic) and the log's motion (stops), one pass
        track, motion = read_tracks(reader, cfg.position_topic)
        # no camera topic: nothing to describe (the selection below reports the empty map)
        choice = resolve_descriptor(cfg.descriptor, reader, cams[0]) if cfg.descriptor is not None and cams else None
        describer = make_describer(choice.chosen) if choice is not None else None
        ex = executor or make_executor(cfg.workers)
        try:
            if scores is None and _stageable(cfg):
                recs_by_topic, looks, crops = _staged(str(log), reader, cfg, cams, track, ex, motion,
                                                      window=window, stage_staticity=stage_staticity)
            else:
                recs_by_topic, looks, crops = _full(str(log), reader, cfg, cams, track, ex, scores, known_looks, window)
        finally:
            if executor is None:
                ex.close()
        cams = [t for t in cams if t in recs_by_topic] if cfg.topics is None else cams
        plan = _plan(reader, cfg, cams, recs_by_topic, looks, crops, track, motion, choice, describer,
                     known_descriptors, known_patches, keep_frames)
        result = write_map_log(reader, output, dpath, cfg, plan)
    result.seconds = time.perf_counter() - t0
    return result


def _check_map_inputs(log: str | os.PathLike[str], output: str | os.PathLike[str], cfg: MapConfig,
                      scores: str | os.PathLike[str] | Records | None, executor: Executor | None) -> Path | None:
    """Every check before the work: the outputs (never over an input), the device, the settings;
    the descriptor Parquet's path (None: no descriptors)."""
    dpath = cfg.descriptors_file(output)
    inputs: list[Any] = [log] + ([scores] if isinstance(scores, (str, os.PathLike)) else [])
    check_output(output, inputs)
    if not getattr(executor, "remote", False):  # (a cluster's workers check their own device)
        choose_providers(cfg.score.device)  # --device cuda without CUDA: said before any work
    if dpath is not None:
        check_output(dpath, inputs + [output], flag="--descriptors")
    if cfg.select.needs_distinctiveness and cfg.descriptor is None:
        raise ConfigError("distinctiveness (--dt / --distinct-weight) is computed from descriptors: give a descriptor")
    return dpath


def _plan(reader: LogReader, cfg: MapConfig, cams: list[str], recs_by_topic: dict[str, list[dict[str, Any]]],
          looks: Looks | None, crops: tuple[int | None, int | None], track: PositionTrack | None,
          motion: Sequence[MotionTrack], choice: DescriptorChoice | None, describer: Any,
          known_descriptors: dict[tuple[str, int], np.ndarray] | None,
          known_patches: dict[tuple[str, int], np.ndarray] | None,
          keep_frames: Mapping[str, Collection[int]] | None) -> MapPlan:
    """Select the frames (distinctiveness first, when the selection weighs it) and say what the map
    log will hold; :class:`EmptyMapError` when nothing would be kept."""
    sel_cfg = cfg.select
    ds_by_topic: dict[str, dict[int, float]] = {}
    known: dict[tuple[str, int], np.ndarray] = dict(known_descriptors or {})
    whitening = None
    if sel_cfg.needs_distinctiveness and describer is not None:
        ds_by_topic, known, whitening = drive_distinctiveness(
            reader, cams, describer, whiten=cfg.whiten, whiten_dim=cfg.whiten_dim, config=sel_cfg.distinct_config(),
            indices={t: {r["frame_index"] for r in recs_by_topic.get(t, [])} for t in cams}, known=known)
    tables: dict[str, ScoreTable] = {}
    selections = _selections(reader, cfg, cams, recs_by_topic, track, looks,
                             ds_by_topic if sel_cfg.needs_distinctiveness else None, tables, motion)
    kept = {t: {int(i) for i in s.index[s.keep]} for t, s in selections.items()}
    if keep_frames is not None:  # given frames (of those the selection saw: the ones that decoded)
        kept = {t: {int(i) for i in s.index} & {int(i) for i in keep_frames.get(t, ())} for t, s in selections.items()}
    n_in = sum(len(s.index) for s in selections.values())
    thresholds = next((s.thresholds for s in selections.values() if s.thresholds), {})
    if sum(len(k) for k in kept.values()) == 0:
        raise EmptyMapError(
            f"{reader.path}: no frame passes the selection ({n_in} frames scored; thresholds "
            f"{json.dumps(thresholds) if thresholds else 'n/a'}). Low-resolution or dark drives score low "
            "entropy; lower --mt/--st/--et or let memlog pick thresholds with --keep-fraction 0.25"
        )
    describing, stops = None, None
    if describer is not None:
        stops = drive_stops(tables, sel_cfg.still_distance)
        describing = ReferenceDescribing(describer, reader, fit_whitening=cfg.whiten and whitening is None,
                                         fit_frames=moving_frames(tables, stops), whiten_dim=cfg.whiten_dim,
                                         whitening=whitening, known=known, known_patches=known_patches)
    score_recs = {t: {r["frame_index"]: r for r in recs_by_topic.get(t, [])} for t in cams}
    return MapPlan(cams, kept, score_recs, selections, tables, looks, track, dict(thresholds), crops, choice,
                   describer, describing, "given" if keep_frames is not None else "selection", stops)

"""The map step's writing half: the map log (the kept frames, their score records, the topics kept
whole) and its reference descriptors, written in one pass over the log as one artefact
(:mod:`memlog.outputs.map_artefact`). :func:`memlog.steps.map.make_map` scores and selects, and hands
this module a :class:`MapPlan`; :class:`MapResult` is what it wrote."""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from memlog._version import __version__
from memlog.descriptors.auto import DescriptorChoice
from memlog.descriptors.extract import ReferenceDescribing, build_table
from memlog.descriptors.table import DescriptorTable
from memlog.descriptors.whitening import MIN_SAMPLES
from memlog.io.base import LogReader
from memlog.io.frame import Frame
from memlog.io.positions import PositionTrack
from memlog.io.records import ReadReport
from memlog.outputs.channels import family_of
from memlog.outputs.map_artefact import write_map
from memlog.io.camera import camera_kind
from memlog.outputs.maplog import MapLogWriter, image_topic
from memlog.progress import info, progress
from memlog.selection import ScoreTable, Selection
from memlog.scoring.motion import Stops, find_stops, moving_index, stops_record

__all__ = ["MapPlan", "MapResult", "Looks", "drive_stops", "moving_frames", "write_map_log"]

Looks = dict[str, dict[int, tuple[np.ndarray | None, np.ndarray | None]]]
"""What selection sees of each frame besides its scores, by topic and frame index: its thumbnail
descriptor (near-duplicates) and its view vector (view change, stops); None when not needed."""


@dataclass
class MapPlan:
    """What the map log holds, decided before it is written: the camera topics, the kept frame
    indices per topic, every frame's score record, the selections and the tables they were made
    from, the frames' looks, the positions, the selection's thresholds, ResMem's crops (run, and
    what scoring every frame would run), the descriptor (chosen kind, describer, and the
    describing of the kept frames), whether the frames were selected or given, and the drive's
    stops (:func:`drive_stops`, found once for the whitening's frames and the moving index; None:
    not known, or no descriptor)."""

    cams: list[str]
    kept: dict[str, set[int]]
    score_recs: dict[str, dict[int, dict[str, Any]]]
    selections: dict[str, Selection]
    tables: dict[str, ScoreTable]
    looks: Looks | None
    track: PositionTrack | None
    thresholds: dict[str, float]
    crops: tuple[int | None, int | None]
    choice: DescriptorChoice | None
    describer: Any
    describing: ReferenceDescribing | None
    kept_by: str
    stops: dict[str, Stops] | None = None


@dataclass
class MapResult:
    """What :func:`make_map` wrote and which frames it kept (``selections`` per topic)."""

    output: Path
    descriptors: Path | None
    selections: dict[str, Selection]
    frames_in: int
    frames_kept: int
    bytes_in: int
    bytes_out: int
    thresholds: dict[str, float] = field(default_factory=dict)
    seconds: float = 0.0
    report: ReadReport | None = None
    crops_run: int | None = None
    crops_full: int | None = None
    descriptor: DescriptorChoice | None = None
    whitening: dict[str, Any] | None = None
    tables: dict[str, ScoreTable] = field(default_factory=dict)  # what each topic was selected from
    looks: Looks | None = field(default=None, repr=False)  # the frames' looks selection used (make_map's known_looks)

    def to_dict(self) -> dict[str, Any]:
        return {
            "output": str(self.output), "descriptors": str(self.descriptors) if self.descriptors else None,
            "frames_in": self.frames_in, "frames_kept": self.frames_kept,
            "frame_fraction": self.frames_kept / max(self.frames_in, 1),
            "bytes_in": self.bytes_in, "bytes_out": self.bytes_out,
            "byte_fraction": self.bytes_out / max(self.bytes_in, 1), "thresholds": self.thresholds,
            "seconds": round(self.seconds, 3), "resmem_crops_run": self.crops_run,
            "resmem_crops_full_scoring": self.crops_full,
            "descriptor": self.descriptor.to_dict() if self.descriptor else None, "whitening": self.whitening,
            "topics": {t: s.to_dict() for t, s in self.selections.items()},
        }


def write_map_log(reader: LogReader, output: str | os.PathLike[str], dpath: Path | None, cfg: Any,
                  plan: MapPlan) -> MapResult:
    """Write ``output`` (the kept frames of ``reader``, the topics ``cfg.keep_topics`` whole) and,
    with a descriptor, the descriptor Parquet ``dpath``, as one artefact; the kept frames are
    described while they are written."""
    n_in = sum(len(s.index) for s in plan.selections.values())
    n_kept = sum(len(k) for k in plan.kept.values())
    with MapLogWriter(output, reader.profile, plan.cams, image_format=cfg.image_format,
                      jpeg_quality=cfg.jpeg_quality, family=family_of(reader, plan.cams)) as w:
        bytes_in, bytes_kept = _write_frames(reader, cfg, plan, w)
        result = MapResult(Path(output), None, plan.selections, n_in, n_kept, bytes_in, 0, plan.thresholds,
                           report=reader.report, crops_run=plan.crops[0], crops_full=plan.crops[1],
                           descriptor=plan.choice, tables=plan.tables, looks=plan.looks)
        table = _described(reader, cfg, plan, result, dpath, n_in)
        # the map and its descriptors as one artefact: each records the other, both in place or neither
        write_map(w, _metadata(reader, cfg, plan, result, bytes_kept),
                  dpath if dpath is not None else cfg.descriptors_path, table, dtype=cfg.descriptor_dtype)
        result.descriptors = dpath if table is not None else None
    result.bytes_out = os.path.getsize(output)
    return result


def _write_frames(reader: LogReader, cfg: Any, plan: MapPlan, w: MapLogWriter) -> tuple[int, int]:
    """Stream the log once: the kept frames and the passthrough topics into ``w``, every frame the
    describing wants to it; the camera bytes read and kept."""
    bytes_in = bytes_kept = 0
    counts = reader.message_counts()
    total = None
    if counts is not None:
        wanted = set(plan.cams) | set(cfg.keep_topics)
        total = sum(n for c in reader.channels() if c.topic in wanted for n in [counts.get(c.id, 0)])
    describing = plan.describing
    for item in progress(reader.stream(plan.cams, passthrough=cfg.keep_topics), total=total, desc="map", unit="msg"):
        if item.index is None:
            w.write_passthrough(item.raw)
            continue
        bytes_in += len(item.raw.data)
        frame = item.frame
        if frame is None:
            continue
        keep = item.index in plan.kept[item.raw.channel.topic]
        if describing is not None:
            describing.add(frame, keep)  # a kept frame, or one the whitening is fitted on
        if not keep:
            continue
        bytes_kept += len(item.raw.data)
        w.write_frame(frame, item.raw, plan.score_recs[frame.topic].get(frame.index))
    return bytes_in, bytes_kept


def _described(reader: LogReader, cfg: Any, plan: MapPlan, result: MapResult, dpath: Path | None,
               n_in: int) -> DescriptorTable | None:
    """The kept frames' descriptor table (None without descriptors); ``result.whitening`` says how
    they were whitened, or why not."""
    if plan.describing is None:
        return None
    described = plan.describing.result(source=f"{reader.path} ({', '.join(plan.cams)})")
    white = described[2]
    if white is not None:
        result.whitening = {"sha256": white.sha256, "dim_in": white.dim_in, "dim_out": white.dim_out,
                            "n_fit": white.n_fit, "eps": white.eps}
    elif cfg.whiten:
        result.whitening = {"skipped": f"fewer than {MIN_SAMPLES} frames of the drive; not whitened"}
        info(f"{reader.path}: the map is not whitened: whitening is fitted on at least {MIN_SAMPLES} frames of the "
             "drive")
    if plan.describer is None or dpath is None or plan.choice is None:
        return None
    frames, desc, white = described
    patches, patch_pca = plan.describing.patch_result()
    sel_cfg = cfg.select
    extra = {"map": str(result.output), "thresholds": plan.thresholds, "mode": sel_cfg.mode, "frames_in": n_in,
             "keep_fraction": sel_cfg.keep_fraction, "descriptor_choice": plan.choice.to_dict()}
    moving, stops = _moving(frames, plan.tables, plan.stops, sel_cfg.still_distance)
    return build_table(frames, desc, plan.describer, scores=plan.score_recs, track=plan.track, extra=extra,
                       whitening=white, moving=moving, stops=stops, patches=patches, patch_pca=patch_pca)


def _metadata(reader: LogReader, cfg: Any, plan: MapPlan, result: MapResult, bytes_kept: int) -> dict[str, str]:
    """The map log's ``memlog_map`` metadata: the run's settings, the selection and what was kept."""
    sel_cfg = cfg.select
    encoded = _encoded(reader, plan.cams)
    return {
        **({"frames_encoded_as": json.dumps(encoded, sort_keys=True)} if encoded else {}),
        "descriptor": json.dumps(plan.choice.to_dict() if plan.choice else None, sort_keys=True),
        "whitening": json.dumps(result.whitening, sort_keys=True),
        "memlog_version": __version__, "input": str(reader.path), "config": cfg.score.to_json(),
        "selection_config": json.dumps(sel_cfg.to_dict(), sort_keys=True),
        "mode": sel_cfg.mode, "keep_fraction": json.dumps(sel_cfg.keep_fraction),
        "thresholds": json.dumps(plan.thresholds),
        "frames_in": str(result.frames_in), "frames_kept": str(result.frames_kept),
        "camera_bytes_in": str(result.bytes_in), "camera_bytes_kept_before_reencoding": str(bytes_kept),
        "selection": json.dumps({t: s.to_dict() for t, s in plan.selections.items()}),
        "kept_by": plan.kept_by,
        "resmem_crops_run": json.dumps(plan.crops[0]), "resmem_crops_full_scoring": json.dumps(plan.crops[1]),
    }


def _encoded(reader: LogReader, cams: list[str]) -> dict[str, dict[str, str]]:
    """The camera topics whose kept frames the map log holds as encoded images, not as their own
    messages (video: a map of isolated frames cannot be a video stream; raw images): for each, the
    topic they are on and where they came from (none for compressed images: copied byte for byte)."""
    out = {}
    for c in reader.channels():
        kind = camera_kind(c.msgtype)
        if c.topic in cams and kind != "compressed":
            out[c.topic] = {"topic": image_topic(c.topic, c.msgtype), "from": c.msgtype,
                            "how": "each kept frame decoded from the video stream and encoded as an image"
                            if kind == "video" else "each kept frame encoded as an image"}
    return out


def drive_stops(tables: dict[str, ScoreTable], still_distance: float) -> dict[str, Stops] | None:
    """Each topic's stops as selection found them (from the log's motion or the view vectors of every
    frame it saw: :func:`find_stops`); None when a topic's table has neither view vectors nor
    motion for every frame."""
    found: dict[str, Stops] = {}
    for t, table in tables.items():
        if table.view is None and (table.motion is None or not table.motion.complete):
            return None
        found[t] = find_stops(table.n, table.view, table.motion, still_distance)
    return found


def moving_frames(tables: dict[str, ScoreTable], found: dict[str, Stops] | None) -> dict[str, set[int]]:
    """The frames the map's whitening and patch PCA are fitted on, by topic: the drive's moving frames
    (every frame selection saw but those of a stop after its first); every frame where stops are not
    known, or where fewer than :data:`MIN_SAMPLES` frames moved (a camera that crept along: the fit
    needs that many). ``found``: the drive's stops (:func:`drive_stops`). Every map of one drive,
    whatever it keeps, is whitened alike."""
    moving = {t: {int(i) for i, still in zip(table.index, found[t].still if found else np.zeros(table.n, bool))
                  if not still} for t, table in tables.items()}
    if sum(len(v) for v in moving.values()) < MIN_SAMPLES:
        return {t: {int(i) for i in table.index} for t, table in tables.items()}
    return moving


def _moving(frames: list[Frame], tables: dict[str, ScoreTable], found: dict[str, Stops] | None,
            still_distance: float) -> tuple[np.ndarray | None, dict[str, Any] | None]:
    """The kept frames' index with the drive's stops ``found`` (:func:`drive_stops`) left out and how
    they were found (``extra["stops"]``); None when the stops are not known."""
    if found is None:
        return None, None
    out = np.zeros(len(frames), dtype=np.int64)
    lookup = {t: dict(zip(table.index.tolist(), moving_index(table.index, found[t].still).tolist()))
              for t, table in tables.items()}
    for k, f in enumerate(frames):
        v = lookup.get(f.topic, {}).get(f.index)
        if v is None:
            return None, None
        out[k] = v
    return out, stops_record(still_distance, found)

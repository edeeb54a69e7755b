"""Describe the frames of a log and package them as a :class:`DescriptorTable`.

Shared by ``memlog map`` (reference descriptors of the kept frames), ``memlog localize`` (query
descriptors) and ``memlog evaluate``: frames stream in batches, so memory stays bounded.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Iterator, Mapping
from typing import Any

import numpy as np

from memlog.descriptors.base import Describer
from memlog.descriptors.table import DescriptorTable
from memlog.errors import ImageDecodeError
from memlog.io.base import FrameWindow, LogReader
from memlog.io.frame import Frame
from memlog.io.identity import log_identity
from memlog.io.open import open_log
from memlog.io.positions import PositionTrack, read_track
from memlog.io.records import ReadReport
from memlog.progress import progress

__all__ = ["describe_frames", "build_table", "describe_log"]


def _batches(frames: Iterable[Frame], n: int) -> Iterator[list[Frame]]:
    batch: list[Frame] = []
    for f in frames:
        batch.append(f)
        if len(batch) >= n:
            yield batch
            batch = []
    if batch:
        yield batch


def describe_frames(
    frames: Iterable[Frame], describer: Describer, reader: LogReader | None = None, batch: int = 16
) -> tuple[list[Frame], np.ndarray]:
    """Descriptors of ``frames`` ([N, dim] float32); frames that do not decode are reported
    through ``reader`` (when given) and left out."""
    kept: list[Frame] = []
    rows: list[np.ndarray] = []
    for group in _batches(frames, batch):
        imgs = []
        for f in group:
            try:
                imgs.append(f.decode_bgr())
                kept.append(f)
            except ImageDecodeError as exc:
                if reader is not None:
                    reader.decode_error(f, exc)
        if imgs:
            rows.append(describer.describe(imgs))
    desc = np.concatenate(rows) if rows else np.zeros((0, describer.dim), np.float32)
    return kept, desc


def build_table(
    frames: list[Frame],
    descriptors: np.ndarray,
    describer: Describer,
    *,
    scores: Mapping[str, Mapping[int, Mapping[str, Any]]] | None = None,
    track: PositionTrack | None = None,
    extra: dict[str, Any] | None = None,
) -> DescriptorTable:
    """A DescriptorTable of described frames, with their scores and interpolated positions."""
    def score(name: str) -> np.ndarray:
        if scores is None:
            return np.full(len(frames), np.nan)
        vals = []
        for f in frames:
            v = scores.get(f.topic, {}).get(f.index, {}).get(name)
            vals.append(np.nan if v is None else float(v))
        return np.asarray(vals, dtype=np.float64)

    positions: dict[str, np.ndarray] = {}
    if track is not None and frames:
        t = [f.log_time_ns for f in frames]
        if track.kind == "gnss":
            ll = track.latlon_at(t)
            assert ll is not None
            positions = {"lat": ll[:, 0], "lon": ll[:, 1], "alt": ll[:, 2]}
        else:
            xyz = track.at(t)
            positions = {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2]}
    ex = dict(extra or {})
    if track is not None:
        ex["position_topic"] = track.topic
    return DescriptorTable(
        topic=[f.topic for f in frames],
        frame_index=np.array([f.index for f in frames], dtype=np.int64),
        log_time_ns=np.array([f.log_time_ns for f in frames], dtype=np.int64),
        stamp_ns=np.array([f.stamp_ns for f in frames], dtype=np.int64),
        descriptors=descriptors,
        meta=describer.meta(),
        ms=score("ms"), ss=score("ss"), es=score("es"),
        positions=positions,
        extra=ex,
    )


def describe_log(
    log: str | os.PathLike[str],
    describer: Describer,
    window: FrameWindow | None = None,
    *,
    scores: Mapping[str, Mapping[int, Mapping[str, Any]]] | None = None,
) -> tuple[DescriptorTable, ReadReport]:
    """Descriptors of the frames of ``window`` (default: the first camera topic, every frame),
    with positions when the log has them, and the read report (damage found). The table's
    ``extra`` records the log, its identity and the window."""
    window = window or FrameWindow()
    with open_log(log) as reader:
        cams = reader.check_camera_topics(window.topics)
        if window.topics is None:
            cams = cams[:1]  # one camera per drive unless asked
        w = FrameWindow(tuple(cams), window.start_ns, window.end_ns, window.stride)
        track = read_track(reader)
        frames = progress(reader.frames(w.topics, w.start_ns, w.end_ns, w.stride), total=reader.count_frames(w),
                          desc="describe", unit="frame")
        kept, desc = describe_frames(frames, describer, reader)
        extra = {"log": str(reader.path), "log_identity": log_identity(log), "window": w.to_dict()}
        return build_table(kept, desc, describer, scores=scores, track=track, extra=extra), reader.report

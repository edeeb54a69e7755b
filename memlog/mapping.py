"""Pipeline step: the memorable-map log (kept frames only) and its reference descriptors.

``make_map`` scores the log (or reuses an annotated MCAP from ``memlog score``), builds a
:class:`~memlog.selection.ScoreTable` per camera topic (with positions from a GNSS/pose
topic when the log has one), selects frames (paper rule, calibrated thresholds, or place
segments; optional near-duplicate removal), then writes

* ``MAP.mcap``: the selected frames, compressed frames byte for byte, raw frames encoded to
  JPEG/PNG as ``CompressedImage`` on ``T/compressed``; their score messages; the topics the
  user names (GPS, odometry...) kept whole; metadata ``memlog_map`` (config, thresholds,
  size reduction);
* ``MAP.parquet``: one reference descriptor per selected frame.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from memlog import __version__
from memlog.config import ScoreConfig
from memlog.errors import ConfigError, LogWriteError
from memlog.io import Frame, McapLogWriter, open_log
from memlog.io.base import LogReader
from memlog.io.camera import camera_kind
from memlog.io.positions import PositionTrack, read_track
from memlog.io.records import RawMessage
from memlog.progress import progress
from memlog.schemas import schema_bytes
from memlog.selection import RedundancyConfig, ScoreTable, Selection, select

__all__ = ["make_map", "MapResult", "score_table", "choose_frames", "EmptyMapError"]


class EmptyMapError(ConfigError):
    """No frame passed the selection."""


@dataclass
class MapResult:
    output: Path
    descriptors: Path | None
    selections: dict[str, Selection]
    frames_in: int
    frames_kept: int
    bytes_in: int
    bytes_out: int
    thresholds: dict[str, float] = field(default_factory=dict)
    seconds: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        return {
            "output": str(self.output), "descriptors": str(self.descriptors) if self.descriptors else None,
            "frames_in": self.frames_in, "frames_kept": self.frames_kept,
            "frame_fraction": self.frames_kept / max(self.frames_in, 1),
            "bytes_in": self.bytes_in, "bytes_out": self.bytes_out,
            "byte_fraction": self.bytes_out / max(self.bytes_in, 1), "thresholds": self.thresholds,
            "seconds": round(self.seconds, 3),
            "topics": {t: s.to_dict() for t, s in self.selections.items()},
        }


def _val(v: Any) -> float:
    return float("nan") if v is None else float(v)


def score_table(records: list[dict[str, Any]], topic: str, track: PositionTrack | None = None,
                descriptors: np.ndarray | None = None) -> ScoreTable:
    """A ScoreTable from score records (``T/memlog/scores`` messages) of one topic."""
    recs = [r for r in records if r.get("rejected_by") != "undecodable"]
    t = np.array([r["log_time"] for r in recs], dtype=np.int64)
    pos = track.at(t.tolist()) if track is not None and len(recs) else None
    if pos is not None and np.isnan(pos).all():
        pos = None
    return ScoreTable(
        index=np.array([r["frame_index"] for r in recs], dtype=np.int64), t_ns=t,
        ms=np.array([_val(r["ms"]) for r in recs]), ss=np.array([_val(r["ss"]) for r in recs]),
        es=np.array([_val(r["es"]) for r in recs]), positions=pos, descriptors=descriptors, topic=topic,
    )


def choose_frames(
    table: ScoreTable,
    mode: str = "paper",
    *,
    keep_fraction: float | None = None,
    thresholds: dict[str, float] | None = None,
    dedup_distance: float | None = None,
    **overrides: Any,
) -> Selection:
    """Select frames: ``paper`` (fixed thresholds, or ``calibrated`` when ``keep_fraction``),
    or ``segment`` (place segments sized by ``keep_fraction`` or a spacing)."""
    dedup = None if dedup_distance is None else RedundancyConfig(dup_distance=dedup_distance)
    if mode == "paper":
        if keep_fraction is not None:
            return select(table, "calibrated", keep_fraction=keep_fraction, dedup=dedup)
        return select(table, "paper", dedup=dedup, **(thresholds or {}))
    if mode == "segment":
        kw = dict(overrides)
        if keep_fraction is not None:
            kw["keep_fraction"] = keep_fraction
        return select(table, "segment", dedup=dedup, **kw)
    raise ConfigError(f"unknown selection mode {mode!r} (paper, segment)")


# -- writing ------------------------------------------------------------------------------
def _encode(img: np.ndarray, fmt: str, quality: int) -> bytes:
    if fmt == "png":
        return bytes(cv2.imencode(".png", img, [cv2.IMWRITE_PNG_COMPRESSION, 6])[1])
    return bytes(cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, quality])[1])


class _CompressedOut:
    """Writes raw frames as CompressedImage in the input's profile (ros2 cdr, ros1, or foxglove json)."""

    def __init__(self, w: McapLogWriter, profile: str) -> None:
        self.w, self.profile = w, profile
        self._store: Any = None
        self._chans: dict[str, int] = {}

    def channel(self, topic: str) -> int:
        if topic in self._chans:
            return self._chans[topic]
        if self.profile in ("ros1", "ros2"):
            from rosbags.typesys import Stores, get_typestore

            ver = 1 if self.profile == "ros1" else 2
            self._store = get_typestore(Stores.ROS1_NOETIC if ver == 1 else Stores.ROS2_HUMBLE)
            text, md5 = self._store.generate_msgdef("sensor_msgs/msg/CompressedImage", ros_version=ver)
            name = "sensor_msgs/CompressedImage" if ver == 1 else "sensor_msgs/msg/CompressedImage"
            sid = self.w.add_schema(name, "ros1msg" if ver == 1 else "ros2msg", text.encode())
            cid = self.w.add_channel(topic, "ros1" if ver == 1 else "cdr", sid, {"md5sum": md5} if ver == 1 else {})
        else:
            sid = self.w.add_schema("foxglove.CompressedImage", "jsonschema", schema_bytes("foxglove.CompressedImage"))
            cid = self.w.add_channel(topic, "json", sid)
        self._chans[topic] = cid
        return cid

    def write(self, topic: str, frame: Frame, data: bytes, fmt: str) -> None:
        cid = self.channel(topic)
        sec, nsec = divmod(frame.stamp_ns, 1_000_000_000)
        if self.profile in ("ros1", "ros2"):
            T = self._store.types
            stamp = T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec)
            hdr_kw: dict[str, Any] = {"stamp": stamp, "frame_id": frame.frame_id}
            if self.profile == "ros1":
                hdr_kw["seq"] = frame.index
            msg = T["sensor_msgs/msg/CompressedImage"](
                header=T["std_msgs/msg/Header"](**hdr_kw), format=fmt, data=np.frombuffer(data, np.uint8))
            ser = self._store.serialize_ros1 if self.profile == "ros1" else self._store.serialize_cdr
            payload = bytes(ser(msg, "sensor_msgs/msg/CompressedImage"))
        else:
            import base64

            payload = json.dumps({"timestamp": {"sec": sec, "nsec": nsec}, "frame_id": frame.frame_id,
                                  "format": fmt, "data": base64.b64encode(data).decode()}).encode()
        self.w.write(cid, frame.log_time_ns, payload)


def _kept_size(reader: LogReader, topics: list[str], kept: dict[str, set[int]]) -> tuple[int, int]:
    """Bytes of all camera messages of ``topics`` in the input, and of the kept ones."""
    total = kept_b = 0
    counters: dict[str, int] = {}
    for m in reader.messages(topics):
        i = counters.get(m.channel.topic, 0)
        counters[m.channel.topic] = i + 1
        total += len(m.data)
        if i in kept.get(m.channel.topic, set()):
            kept_b += len(m.data)
    return total, kept_b


def write_reference_descriptors(
    reader: LogReader,
    frames: list[Frame],
    score_recs: dict[str, dict[int, dict[str, Any]]],
    track: PositionTrack | None,
    kind: str,
    path: Path,
    extra: dict[str, Any],
) -> Path:
    """Describe the kept frames and write them to ``path`` (Parquet)."""
    from memlog.descriptors.base import make_describer
    from memlog.descriptors.extract import build_table, describe_frames
    from memlog.descriptors.parquet import write_descriptors

    describer = make_describer(kind)
    kept, desc = describe_frames(progress(frames, total=len(frames), desc="describe", unit="frame"), describer, reader)
    return write_descriptors(path, build_table(kept, desc, describer, scores=score_recs, track=track, extra=extra))


def collect_scores(
    log: str | os.PathLike[str], config: ScoreConfig, topics: list[str] | None = None, stride: int = 1
) -> dict[str, list[dict[str, Any]]]:
    """Score a log without writing it: score records per camera topic (as in ``T/memlog/scores``)."""
    from memlog.score import iter_scores, scores_message
    from memlog.scoring.scorer import Scorer

    scorer = Scorer(config).load()
    out: dict[str, list[dict[str, Any]]] = {}
    with open_log(log) as reader:
        for frame, s, err in progress(iter_scores(reader, scorer, topics=topics, stride=stride), desc="score",
                                      unit="frame"):
            rec = scores_message(frame, s, config, err)
            rec.pop("memorability", None)
            out.setdefault(frame.topic, []).append(rec)
    return out


def thumbnails_of(log: str | os.PathLike[str], topic: str, indices: set[int] | None = None) -> dict[int, np.ndarray]:
    """Cheap thumbnail descriptors (for view-change segments and near-duplicate removal)."""
    from memlog.descriptors.base import make_describer

    d = make_describer("thumbnail")
    out: dict[int, np.ndarray] = {}
    with open_log(log) as reader:
        for f in reader.frames([topic]):
            if indices is not None and f.index not in indices:
                continue
            try:
                out[f.index] = d.describe([f.decode_bgr()])[0]
            except Exception:  # undecodable frames have no scores either
                continue
    return out


def make_map(
    log: str | os.PathLike[str],
    output: str | os.PathLike[str],
    config: ScoreConfig | None = None,
    *,
    scores: str | os.PathLike[str] | dict[str, list[dict[str, Any]]] | None = None,
    topics: list[str] | None = None,
    mode: str = "segment",
    keep_fraction: float | None = None,
    dedup_distance: float | None = None,
    keep_topics: Sequence[str] = (),
    position_topic: str | None = None,
    image_format: str = "jpeg",
    jpeg_quality: int = 90,
    descriptor: str | None = "thumbnail",
    descriptors_path: str | os.PathLike[str] | None = None,
    segment: dict[str, Any] | None = None,
) -> MapResult:
    """Build the memorable-map log of ``log`` (see module doc). Raises :class:`EmptyMapError`
    when nothing would be kept."""
    t0 = time.perf_counter()
    config = config or ScoreConfig()
    if image_format not in ("jpeg", "png"):
        raise ConfigError(f"image format must be jpeg or png, got {image_format!r}")
    needs_all = keep_fraction is not None or mode == "segment"
    if scores is None:
        cfg = config.replace(all_scores=True) if needs_all else config
        recs_by_topic = collect_scores(log, cfg, topics)
    elif isinstance(scores, dict):
        recs_by_topic = scores
    else:
        from memlog.score import read_scores, run_config

        used = run_config(scores)
        if needs_all and used is not None and not (used.all_scores or used.mode == "paper"):
            raise ConfigError(
                f"{scores}: scored with early exit, so skipped scores are missing; --keep-fraction and "
                "--select segment need every score: run `memlog score --all-scores` first"
            )
        recs_by_topic = read_scores(scores)
    with open_log(log) as reader:
        if Path(output).resolve() == Path(reader.path).resolve():
            raise LogWriteError(f"{output}: output would overwrite the input log")
        cams = topics or [t for t in reader.camera_topics() if t in recs_by_topic]
        missing_keep = set(keep_topics) - set(reader.topics())
        if missing_keep:
            raise ConfigError(f"{reader.path}: no topic {', '.join(sorted(missing_keep))} to keep")
        track = read_track(reader, position_topic)  # None when the log has no position topic
        selections: dict[str, Selection] = {}
        for t in cams:
            recs = recs_by_topic.get(t, [])
            descs = None
            need_desc = dedup_distance is not None or (mode == "segment" and (segment or {}).get("by") == "view")
            if need_desc and recs:
                thumbs = thumbnails_of(log, t, {r["frame_index"] for r in recs})
                recs = [r for r in recs if r["frame_index"] in thumbs]
                descs = np.stack([thumbs[r["frame_index"]] for r in recs]).astype(np.float32)
            table = score_table(recs, t, track, descs)
            selections[t] = choose_frames(table, mode, keep_fraction=keep_fraction,
                                          thresholds={"mt": config.mt, "st": config.st, "et": config.et},
                                          dedup_distance=dedup_distance, **(segment or {}))
        kept = {t: {int(i) for i in s.index[s.keep]} for t, s in selections.items()}
        n_in = sum(len(s.index) for s in selections.values())
        n_kept = sum(len(k) for k in kept.values())
        thresholds = next((s.thresholds for s in selections.values() if s.thresholds), {})
        if n_kept == 0:
            raise EmptyMapError(
                f"{reader.path}: no frame passes the selection ({n_in} frames scored; thresholds "
                f"{json.dumps(thresholds) if thresholds else 'n/a'}). Low-resolution or dark drives score low "
                "entropy; lower --mt/--st/--et or let memlog pick thresholds with --keep-fraction 0.25"
            )
        bytes_in, bytes_kept = _kept_size(reader, cams, kept)
        score_recs = {t: {r["frame_index"]: r for r in recs_by_topic.get(t, [])} for t in cams}
        desc_frames: list[Frame] = []
        with McapLogWriter(output, profile=reader.profile) as w:
            comp = _CompressedOut(w, reader.profile)
            sid = w.add_schema("memlog.FrameScores", "jsonschema", schema_bytes("memlog.FrameScores"))
            score_ch = {t: w.add_channel(f"{t}/memlog/scores", "json", sid) for t in cams}
            for frame_or_msg in progress(_map_stream(reader, cams, list(keep_topics), kept), desc="map"):
                if isinstance(frame_or_msg, tuple):
                    frame, ch_msg = frame_or_msg
                    if camera_kind(frame.msgtype) == "compressed":
                        w.write_raw(ch_msg)
                    else:
                        data = _encode(frame.decode_bgr(), image_format, jpeg_quality)
                        comp.write(f"{frame.topic}/compressed", frame, data, image_format)
                    rec = score_recs[frame.topic].get(frame.index)
                    if rec is not None:
                        w.write_json(score_ch[frame.topic], frame.log_time_ns, rec)
                    if descriptor:
                        desc_frames.append(frame)
                else:
                    w.write_raw(frame_or_msg)
            result = MapResult(Path(output), None, selections, n_in, n_kept, bytes_in, 0, dict(thresholds))
            w.add_metadata("memlog_map", {
                "memlog_version": __version__, "input": str(reader.path), "config": config.to_json(),
                "mode": mode, "keep_fraction": json.dumps(keep_fraction), "thresholds": json.dumps(thresholds),
                "frames_in": str(n_in), "frames_kept": str(n_kept), "camera_bytes_in": str(bytes_in),
                "camera_bytes_kept_before_reencoding": str(bytes_kept),
                "selection": json.dumps({t: s.to_dict() for t, s in selections.items()}),
            })
        result.bytes_out = os.path.getsize(output)
        if descriptor:
            dpath = Path(descriptors_path) if descriptors_path else Path(output).with_suffix(".parquet")
            write_reference_descriptors(reader, desc_frames, score_recs, track, descriptor, dpath,
                                        extra={"map": str(output), "thresholds": thresholds, "mode": mode,
                                               "frames_in": n_in, "keep_fraction": keep_fraction})
            result.descriptors = dpath
    result.seconds = time.perf_counter() - t0
    return result


def _map_stream(
    reader: LogReader, cams: list[str], keep_topics: list[str], kept: dict[str, set[int]]
) -> Iterator[tuple[Frame, RawMessage] | RawMessage]:
    """Kept camera frames as (Frame, RawMessage) and whole kept topics as RawMessage, in log-time order."""
    from memlog.io.base import FrameError

    counters: dict[str, int] = {}
    decoders: dict[int, Any] = {}
    errs: list[FrameError] = []
    for m in reader.messages(sorted(set(cams) | set(keep_topics))):
        t = m.channel.topic
        if t in kept:
            i = counters.get(t, 0)
            counters[t] = i + 1
            if i in kept[t]:
                frame = reader.to_frame(m, i, decoders, errs)
                if frame is not None:
                    yield frame, m
        else:
            yield m

"""The memorable-map log of ``memlog map``: the kept frames only, compressed, in the input's profile.

Compressed frames are copied byte for byte; raw frames, and the frames of a video topic (a map of
isolated frames cannot be a video stream: each kept frame is decoded from its stream), are encoded to
JPEG/PNG and written as ``CompressedImage`` on ``T/compressed`` (:func:`image_topic`; the map's
metadata names each in ``frames_written_as``). Each kept frame's score record goes to ``T/memlog/scores``
(``memlog.FrameScores``). Both are in the input's encoding family (:mod:`memlog.outputs.channels`:
``sensor_msgs/CompressedImage`` + ``memlog_msgs/FrameScores`` in ROS 2 CDR or ROS 1, Foxglove JSON
or protobuf). Topics the user keeps whole (GPS, odometry) are copied; metadata ``memlog_map``
records the run, and ``memlog_map_descriptors`` the map's descriptor table
(:mod:`memlog.outputs.map_artefact`: the map and its descriptors are written as one artefact).
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from types import TracebackType
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from memlog.io.atomic import AtomicFile
from memlog.io.camera import camera_kind
from memlog.io.frame import Frame
from memlog.io.mcap import McapLogWriter
from memlog.io.records import RawMessage
from memlog.outputs.annotated import SCORES_SUFFIX
from memlog.outputs.channels import IMAGE, SCORES, MemlogChannels

__all__ = ["MapLogWriter", "encode_image"]


def encode_image(img: npt.NDArray[np.uint8], fmt: str, quality: int) -> bytes:
    """A BGR/grey image as PNG (``fmt="png"``) or JPEG at ``quality``."""
    if fmt == "png":
        return bytes(cv2.imencode(".png", img, [cv2.IMWRITE_PNG_COMPRESSION, 6])[1])
    return bytes(cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, quality])[1])


_PROFILE_FAMILY = {"ros1": "ros1", "ros2": "ros2"}


def image_topic(topic: str, msgtype: str) -> str:
    """Where a map log keeps the frames of camera ``topic`` (of type ``msgtype``): the topic itself
    for compressed images (copied byte for byte), else ``topic/compressed`` (encoded images)."""
    return topic if camera_kind(msgtype) == "compressed" else f"{topic}/compressed"


class MapLogWriter:
    """Writes a map log: :meth:`write_frame` for each kept frame (with its raw record and score
    record), :meth:`write_passthrough` for messages of kept-whole topics, :meth:`close` with the
    ``memlog_map`` metadata (atomic; :meth:`abort` drops the file)."""

    def __init__(self, path: str | os.PathLike[str], profile: str, topics: list[str], *,
                 image_format: str = "jpeg", jpeg_quality: int = 90, family: str | None = None) -> None:
        """``family``: the encoding family of memlog's channels
        (:func:`~memlog.outputs.channels.family_of` the input; default: from ``profile``, JSON
        outside ros1/ros2)."""
        self.w = McapLogWriter(path, profile=profile)
        self.image_format = image_format
        self.jpeg_quality = jpeg_quality
        self.family = family or _PROFILE_FAMILY.get(profile, "json")
        self.out = MemlogChannels(self.w, self.family)
        self._score_ch = {t: self.out.add(f"{t}{SCORES_SUFFIX}", SCORES) for t in topics}
        self._image_ch: dict[str, int] = {}

    @property
    def path(self) -> Path:
        return self.w.path

    def write_frame(self, frame: Frame, raw: RawMessage, score: Mapping[str, Any] | None) -> None:
        """A kept frame: compressed payloads byte for byte, raw and video ones encoded; then its score record."""
        if camera_kind(frame.msgtype) == "compressed":
            self.w.write_raw(raw)
        else:
            topic = image_topic(frame.topic, frame.msgtype)
            if topic not in self._image_ch:
                self._image_ch[topic] = self.out.add(topic, IMAGE)
            sec, nsec = divmod(frame.stamp_ns, 1_000_000_000)
            self.out.write(self._image_ch[topic], frame.log_time_ns, {
                "timestamp": {"sec": sec, "nsec": nsec}, "frame_id": frame.frame_id, "format": self.image_format,
                "data": encode_image(frame.decode_bgr(), self.image_format, self.jpeg_quality), "seq": frame.index})
        if score is not None:
            self.out.write(self._score_ch[frame.topic], frame.log_time_ns, score)

    def write_passthrough(self, raw: RawMessage) -> None:
        """A message of a topic kept whole."""
        self.w.write_raw(raw)

    def add_metadata(self, name: str, data: Mapping[str, str]) -> None:
        """Another metadata record (the link to the map's descriptors,
        :mod:`memlog.outputs.map_artefact`)."""
        self.w.add_metadata(name, data)

    def finish(self, metadata: Mapping[str, str]) -> AtomicFile:
        """Add the ``memlog_map`` metadata and finish the file under its temporary name without
        moving it into place (see :meth:`McapLogWriter.finish`)."""
        self.w.add_metadata("memlog_map", metadata)
        return self.w.finish()

    def close(self, metadata: Mapping[str, str]) -> Path:
        self.finish(metadata)
        return self.w.close()

    def abort(self) -> None:
        self.w.abort()

    def __enter__(self) -> "MapLogWriter":
        return self

    def __exit__(self, et: type[BaseException] | None, ev: BaseException | None, tb: TracebackType | None) -> None:
        if et is not None:
            self.abort()

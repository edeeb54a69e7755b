"""The memorable-map log of ``memlog map``: the kept frames only, compressed, in the input's profile.

Compressed frames are copied byte for byte; raw frames are encoded to JPEG/PNG and written as
``CompressedImage`` on ``T/compressed`` in the input's encoding family (ROS 2 CDR, ROS 1, or
Foxglove JSON). Each kept frame's score record goes to ``T/memlog/scores``; topics the user
keeps whole (GPS, odometry) are copied; metadata ``memlog_map`` records the run.
"""

from __future__ import annotations

import base64
import json
import os
from collections.abc import Mapping
from pathlib import Path
from types import TracebackType
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from memlog.io.camera import camera_kind
from memlog.io.frame import Frame
from memlog.io.mcap import McapLogWriter
from memlog.io.records import RawMessage
from memlog.outputs.annotated import SCORES_SUFFIX
from memlog.outputs.schemas import schema_bytes

__all__ = ["MapLogWriter", "encode_image"]


def encode_image(img: npt.NDArray[np.uint8], fmt: str, quality: int) -> bytes:
    """A BGR/grey image as PNG (``fmt="png"``) or JPEG at ``quality``."""
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
            payload = json.dumps({"timestamp": {"sec": sec, "nsec": nsec}, "frame_id": frame.frame_id,
                                  "format": fmt, "data": base64.b64encode(data).decode()}).encode()
        self.w.write(cid, frame.log_time_ns, payload)


class MapLogWriter:
    """Writes a map log: :meth:`write_frame` for each kept frame (with its raw record and score
    record), :meth:`write_passthrough` for messages of kept-whole topics, :meth:`close` with the
    ``memlog_map`` metadata (atomic; :meth:`abort` drops the file)."""

    def __init__(self, path: str | os.PathLike[str], profile: str, topics: list[str], *,
                 image_format: str = "jpeg", jpeg_quality: int = 90) -> None:
        self.w = McapLogWriter(path, profile=profile)
        self.image_format = image_format
        self.jpeg_quality = jpeg_quality
        self._comp = _CompressedOut(self.w, profile)
        sid = self.w.add_schema("memlog.FrameScores", "jsonschema", schema_bytes("memlog.FrameScores"))
        self._score_ch = {t: self.w.add_channel(f"{t}{SCORES_SUFFIX}", "json", sid) for t in topics}

    @property
    def path(self) -> Path:
        return self.w.path

    def write_frame(self, frame: Frame, raw: RawMessage, score: Mapping[str, Any] | None) -> None:
        """A kept frame: compressed payloads byte for byte, raw ones encoded; then its score record."""
        if camera_kind(frame.msgtype) == "compressed":
            self.w.write_raw(raw)
        else:
            data = encode_image(frame.decode_bgr(), self.image_format, self.jpeg_quality)
            self._comp.write(f"{frame.topic}/compressed", frame, data, self.image_format)
        if score is not None:
            self.w.write_json(self._score_ch[frame.topic], frame.log_time_ns, score)

    def write_passthrough(self, raw: RawMessage) -> None:
        """A message of a topic kept whole."""
        self.w.write_raw(raw)

    def close(self, metadata: Mapping[str, str]) -> Path:
        self.w.add_metadata("memlog_map", metadata)
        return self.w.close()

    def abort(self) -> None:
        self.w.abort()

    def __enter__(self) -> "MapLogWriter":
        return self

    def __exit__(self, et: type[BaseException] | None, ev: BaseException | None, tb: TracebackType | None) -> None:
        if et is not None:
            self.abort()

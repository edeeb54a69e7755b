"""Plain data types that flow from the readers to the scorer and the writers."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import numpy.typing as npt

__all__ = ["ImagePayload", "Frame", "TopicInfo", "LogInfo"]

PayloadKind = Literal["compressed", "raw"]


@dataclass(frozen=True)
class ImagePayload:
    """The encoded pixels of one image message, not yet decoded.

    ``kind == "compressed"``: ``data`` is a compressed stream (JPEG, PNG, ...) and
    ``encoding`` is the message's ``format`` string (for example ``"jpeg"`` or
    ``"bgr8; jpeg compressed bgr8"``).
    ``kind == "raw"``: ``data`` holds ``height`` rows of ``step`` bytes in the ROS
    ``encoding`` (``mono8``, ``bgr8``, ``bayer_rggb8``, ``yuv422`` ...).
    """

    kind: PayloadKind
    encoding: str
    data: bytes
    width: int = 0
    height: int = 0
    step: int = 0
    is_bigendian: bool = False


@dataclass(frozen=True)
class Frame:
    """One camera message, with where it came from.

    ``index`` is the position of the message on its topic, counted from 0 in
    log-time order (the spec's frame index); ``stamp_ns`` is the header stamp
    (``log_time_ns`` when the message has no header).
    """

    topic: str
    index: int
    log_time_ns: int
    stamp_ns: int
    frame_id: str
    payload: ImagePayload
    msgtype: str = ""

    def decode_bgr(self) -> npt.NDArray[np.uint8]:
        """Decode the payload to an HxWx3 uint8 BGR array (see :mod:`memlog.io.image`)."""
        from memlog.io.image import decode_bgr

        return decode_bgr(self.payload)

    def decode_gray(self) -> npt.NDArray[np.uint8]:
        """Decode the payload to an HxW uint8 grey array (see :mod:`memlog.io.image`)."""
        from memlog.io.image import decode_gray

        return decode_gray(self.payload)


@dataclass
class TopicInfo:
    """What a log says about one topic."""

    topic: str
    msgtype: str
    encoding: str  # message encoding: cdr, ros1, json, protobuf
    count: int
    start_ns: int | None = None
    end_ns: int | None = None
    is_camera: bool = False


@dataclass
class LogInfo:
    """Summary of a log: format, size, topics, time range."""

    path: str
    format: str  # "mcap", "ros1bag", "ros2bag"
    size_bytes: int
    profile: str = ""
    topics: list[TopicInfo] = field(default_factory=list)
    start_ns: int | None = None
    end_ns: int | None = None
    storage: str = ""

    @property
    def duration_s(self) -> float:
        if self.start_ns is None or self.end_ns is None:
            return 0.0
        return (self.end_ns - self.start_ns) / 1e9

    @property
    def camera_topics(self) -> list[str]:
        return sorted(t.topic for t in self.topics if t.is_camera)

"""Plain data types of the readers: encoded image payloads and log summaries."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

__all__ = ["ImagePayload", "TopicInfo", "LogInfo"]

PayloadKind = Literal["compressed", "raw", "video"]


@dataclass(frozen=True)
class ImagePayload:
    """The encoded pixels of one image message, not yet decoded.

    ``kind == "compressed"``: ``data`` is a compressed stream (JPEG, PNG, ...) and
    ``encoding`` is the message's ``format`` string (for example ``"jpeg"`` or
    ``"bgr8; jpeg compressed bgr8"``).
    ``kind == "raw"``: ``data`` holds ``height`` rows of ``step`` bytes in the ROS
    ``encoding`` (``mono8``, ``bgr8``, ``bayer_rggb8``, ``yuv422`` ...).
    ``kind == "video"``: ``data`` is one packet of a video stream (:mod:`memlog.io.video`),
    ``encoding`` its codec or FFmpeg encoder name, ``keyframe`` the packet's own key flag when the
    message has one (FFMPEGPacket); :meth:`memlog.io.base.LogReader.stream` decodes it into a raw
    ``bgr8`` payload.
    """

    kind: PayloadKind
    encoding: str
    data: bytes
    width: int = 0
    height: int = 0
    step: int = 0
    is_bigendian: bool = False
    keyframe: bool | None = None


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

"""Which message types carry camera images, and how to pull an :class:`ImagePayload` out of them.

Works on messages decoded by rosbags (attribute access) and on JSON/protobuf messages
(converted to dicts), for the ROS 1 and ROS 2 spellings of ``sensor_msgs`` and for the
Foxglove schemas.
"""

from __future__ import annotations

import base64
from typing import Any

from memlog.io.types import ImagePayload

__all__ = ["CAMERA_TYPES", "camera_kind", "extract_image", "header_stamp", "normalize_msgtype"]

_COMPRESSED = {
    "sensor_msgs/CompressedImage",
    "foxglove.CompressedImage",
    "foxglove_msgs/CompressedImage",
}
_RAW = {
    "sensor_msgs/Image",
    "foxglove.RawImage",
    "foxglove_msgs/RawImage",
}
_VIDEO = {
    "foxglove.CompressedVideo",
    "foxglove_msgs/CompressedVideo",
    "ffmpeg_image_transport_msgs/FFMPEGPacket",
}

#: Every camera message type memlog reads (ROS 2 spells ``pkg/msg/Type``), for messages.
CAMERA_TYPES = tuple(sorted(_COMPRESSED | _RAW | _VIDEO))


def normalize_msgtype(name: str) -> str:
    """``sensor_msgs/msg/Image`` -> ``sensor_msgs/Image``; ``foxglove.RawImage`` unchanged."""
    parts = name.split("/")
    if len(parts) == 3 and parts[1] == "msg":
        return f"{parts[0]}/{parts[2]}"
    return name


def camera_kind(msgtype: str) -> str | None:
    """``"compressed"``, ``"raw"``, ``"video"`` (one packet of a video stream per message) or None
    for a message type name."""
    norm = normalize_msgtype(msgtype)
    if norm in _COMPRESSED:
        return "compressed"
    if norm in _RAW:
        return "raw"
    if norm in _VIDEO:
        return "video"
    return None


def _get(msg: Any, name: str, default: Any = None) -> Any:
    if isinstance(msg, dict):
        return msg.get(name, default)
    return getattr(msg, name, default)


def _stamp_ns(stamp: Any) -> int | None:
    if stamp is None:
        return None
    sec = _get(stamp, "sec", _get(stamp, "secs", _get(stamp, "seconds")))
    nsec = _get(stamp, "nanosec", _get(stamp, "nsec", _get(stamp, "nsecs", _get(stamp, "nanos", 0))))
    if sec is None:
        return None
    return int(sec) * 1_000_000_000 + int(nsec or 0)


def header_stamp(msg: Any) -> int | None:
    """The stamp (ns) a decoded message carries: ``header.stamp`` (std_msgs/Header, ROS 1 and
    ROS 2), else a Foxglove ``timestamp``; None when it has neither."""
    header = _get(msg, "header")
    return _stamp_ns(_get(header, "stamp") if header is not None else _get(msg, "timestamp"))


def _as_bytes(data: Any) -> bytes:
    if isinstance(data, bytes):
        return data
    if isinstance(data, str):  # JSON encodes bytes as base64
        return base64.b64decode(data)
    if hasattr(data, "tobytes"):
        return bytes(data.tobytes())
    return bytes(data)


def extract_image(msgtype: str, msg: Any) -> tuple[int | None, str, ImagePayload]:
    """Return (header stamp in ns or None, frame_id, payload) of a decoded image message."""
    kind = camera_kind(msgtype)
    if kind is None:
        raise ValueError(f"{msgtype} is not an image message type")
    header = _get(msg, "header")
    stamp = header_stamp(msg)
    frame_id = str(_get(header if header is not None else msg, "frame_id", "") or "")  # sensor_msgs, foxglove
    data = _as_bytes(_get(msg, "data", b""))
    if kind == "compressed":
        return stamp, frame_id, ImagePayload("compressed", str(_get(msg, "format", "") or ""), data)
    if kind == "video":  # foxglove CompressedVideo: format; FFMPEGPacket: encoding, flags (AV_PKT_FLAG_KEY)
        flags = _get(msg, "flags")
        return stamp, frame_id, ImagePayload(
            "video", str(_get(msg, "format", None) or _get(msg, "encoding", "") or ""), data,
            width=int(_get(msg, "width", 0) or 0), height=int(_get(msg, "height", 0) or 0),
            keyframe=None if flags is None else bool(int(flags) & 1))
    return stamp, frame_id, ImagePayload(
        "raw",
        str(_get(msg, "encoding", "") or ""),
        data,
        width=int(_get(msg, "width", 0) or 0),
        height=int(_get(msg, "height", 0) or 0),
        step=int(_get(msg, "step", 0) or 0),
        is_bigendian=bool(_get(msg, "is_bigendian", False)),
    )

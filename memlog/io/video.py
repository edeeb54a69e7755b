"""Camera topics recorded as video: H.264, H.265, VP9 and AV1 packets, one frame per message.

Foxglove's ``foxglove.CompressedVideo`` (protobuf, JSON, ROS 1 and ROS 2 ``foxglove_msgs``) and ROS 2's
``ffmpeg_image_transport_msgs/msg/FFMPEGPacket`` carry one encoded frame per message (Annex B for
H.264/H.265, OBUs for AV1, a VP9 frame), without B-frames. A packet is not a picture on its own: it
is decoded with every packet since the keyframe before it, so :meth:`memlog.io.base.LogReader.stream`
keeps one :class:`VideoDecoder` per topic, feeds it every packet of the topic in order from the
keyframe at or before the first frame it yields (a window, a chunk of a job, a worker starting
mid-stream: :func:`keyframe_before`), and yields each wanted frame as its decoded pixels (a raw
``bgr8`` payload), so every step downstream sees an ordinary frame. The frame numbering stays the
log's :class:`~memlog.io.frame_table.FrameTable`: every message of the topic is a frame.

Keyframes are found in the packets themselves (:func:`is_keyframe`: an IDR or SPS NAL unit in
H.264, an IRAP or parameter set in H.265, a sequence header OBU in AV1, a key frame header in VP9;
``FFMPEGPacket.flags``' key bit). Damage is what FFmpeg detects: a packet it refuses, a picture it
marks corrupt, a packet before the stream's first keyframe. Such a frame, and every frame after it
up to the next keyframe (they refer to the damaged one), is reported with its topic and index
(:class:`VideoDamage`) and skipped; a bit flip inside a slice that FFmpeg conceals is not detected
(the codecs carry no checksum).

Decoding uses PyAV (FFmpeg's libraries, shipped in its wheels; ``pip install av``).
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import numpy as np
import numpy.typing as npt

from memlog.errors import ImageDecodeError
from memlog.io.types import ImagePayload

__all__ = ["VIDEO_CODECS", "VideoDamage", "VideoDecoder", "codec_of", "is_keyframe", "keyframe_before",
           "payload_is_keyframe"]

#: The codecs memlog decodes, by the names Foxglove's ``format`` field uses.
VIDEO_CODECS = ("h264", "h265", "vp9", "av1")
#: FFmpeg's decoder for each codec (libdav1d: AV1 in PyAV's wheels).
_DECODERS = {"h264": ("h264",), "h265": ("hevc",), "vp9": ("vp9", "libvpx-vp9"), "av1": ("libdav1d", "av1")}
_ALIASES = {"h264": "h264", "avc": "h264", "avc1": "h264", "x264": "h264", "264": "h264", "h265": "h265",
            "hevc": "h265", "hev1": "h265", "hvc1": "h265", "x265": "h265", "265": "h265", "vp9": "vp9",
            "vp09": "vp9", "av1": "av1", "av01": "av1", "aom": "av1", "dav1d": "av1", "svtav1": "av1"}
_AV_PKT_FLAG_KEY = 0x1


class VideoDamage(ImageDecodeError):
    """A video frame that cannot be shown: its packet or one it depends on is damaged, or no
    keyframe came before it."""


def codec_of(name: str) -> str | None:
    """The codec of a ``format`` (``h264``, ``h265``, ``vp9``, ``av1``) or FFMPEGPacket ``encoding``
    (``libx264``, ``hevc_nvenc``, ...) string; None when it is none of :data:`VIDEO_CODECS`."""
    text = name.strip().lower()
    if text in _ALIASES:
        return _ALIASES[text]
    for part in text.replace("-", "_").split("_"):
        for key in (part, part.removeprefix("lib")):
            if key in _ALIASES:
                return _ALIASES[key]
    return None


def _nal_types(data: bytes) -> Iterable[int]:
    """The first byte of every NAL unit of an Annex B stream."""
    i, n = 0, len(data)
    while True:
        j = data.find(b"\x00\x00\x01", i)
        if j < 0 or j + 3 >= n:
            return
        yield data[j + 3]
        i = j + 3


def _leb128(data: bytes, i: int) -> tuple[int, int]:
    value = 0
    for k in range(8):
        if i + k >= len(data):
            return value, i + k
        b = data[i + k]
        value |= (b & 0x7F) << (7 * k)
        if not b & 0x80:
            return value, i + k + 1
    return value, i + 8


def _av1_has_sequence_header(data: bytes) -> bool:
    i = 0
    while i < len(data):
        header = data[i]
        obu_type, has_ext, has_size = (header >> 3) & 0xF, (header >> 2) & 1, (header >> 1) & 1
        if obu_type == 1:  # OBU_SEQUENCE_HEADER: sent with every key frame
            return True
        i += 1 + has_ext
        if not has_size:
            return False
        size, i = _leb128(data, i)
        i += size
    return False


def _vp9_key(data: bytes) -> bool:
    if not data:
        return False
    b = data[0]
    if b >> 6 != 2:  # frame_marker
        return False
    profile = ((b >> 5) & 1) | (((b >> 4) & 1) << 1)
    bit = 3 if profile < 3 else 2  # profile 3 has a reserved zero bit first
    if (b >> bit) & 1:  # show_existing_frame
        return False
    return not (b >> (bit - 1)) & 1  # frame_type 0: KEY_FRAME


def is_keyframe(codec: str, data: bytes, flags: int | None = None) -> bool:
    """Whether a packet of ``codec`` starts a stream a decoder can begin at (``flags``: an
    FFMPEGPacket's flags, whose key bit decides when given)."""
    if flags is not None:
        return bool(flags & _AV_PKT_FLAG_KEY)
    if codec == "h264":
        return any(t & 0x1F in (5, 7) for t in _nal_types(data))  # IDR slice, or SPS
    if codec == "h265":
        return any(16 <= (t >> 1) & 0x3F <= 23 or (t >> 1) & 0x3F in (32, 33) for t in _nal_types(data))
    if codec == "av1":
        return _av1_has_sequence_header(data)
    if codec == "vp9":
        return _vp9_key(data)
    return False


def payload_is_keyframe(codec: str, payload: ImagePayload) -> bool:
    """:func:`is_keyframe` of a video payload: its message's own key flag when it has one, else its bytes."""
    return is_keyframe(codec, payload.data, None if payload.keyframe is None else int(payload.keyframe))


def keyframe_before(keyframes: npt.NDArray[np.int64], index: int) -> int:
    """The frame index of the last keyframe at or before frame ``index`` (``keyframes``: their
    indices, sorted); ``index`` itself when none comes before it (the frame is then damage)."""
    k = int(np.searchsorted(keyframes, index, side="right")) - 1
    return int(keyframes[k]) if k >= 0 else index


class VideoDecoder:
    """One topic's decoder: packets go in in order (:meth:`decode`), each gives its picture."""

    def __init__(self, codec: str, topic: str) -> None:
        try:
            import av
        except ImportError:
            raise ImageDecodeError(f"topic {topic} is {codec} video: decoding it needs PyAV (pip install av)") from None
        self.codec, self.topic = codec, topic
        self._av = av
        self._ctx = self._open()
        self.synced = False  # a keyframe was decoded and nothing damaged since

    def _open(self) -> Any:
        for name in _DECODERS[self.codec]:
            try:
                ctx = self._av.CodecContext.create(name, "r")
            except (ValueError, self._av.error.FFmpegError):
                continue
            ctx.flags = self._av.codec.context.Flags.low_delay  # one picture per packet, no reordering delay
            return ctx
        raise ImageDecodeError(f"topic {self.topic}: this FFmpeg has no {self.codec} decoder")

    def decode(self, data: bytes, keyframe: bool, want: bool) -> npt.NDArray[np.uint8] | None:
        """Feed one packet; its picture as an HxWx3 BGR array when ``want`` (None otherwise).
        :class:`VideoDamage` when it cannot be shown; the decoder then waits for a keyframe."""
        if keyframe and not self.synced:
            self._ctx = self._open()  # a fresh start at the keyframe: nothing damaged carries over
            self.synced = True
        if not self.synced:
            raise VideoDamage("no keyframe since the stream started or since damage before it (the frame refers "
                              "to pictures that were not decoded)")
        try:
            pictures = self._ctx.decode(self._av.Packet(data))
        except self._av.error.FFmpegError as exc:
            self.synced = False
            raise VideoDamage(f"the {self.codec} packet does not decode: {exc}") from None
        if not pictures:
            self.synced = False
            raise VideoDamage(f"the {self.codec} packet gave no picture (a stream with B-frames or a damaged packet)")
        picture = pictures[-1]
        if getattr(picture, "is_corrupt", False):
            self.synced = False
            raise VideoDamage(f"the {self.codec} decoder marks the picture corrupt")
        if not want:
            return None
        out: npt.NDArray[np.uint8] = picture.to_ndarray(format="bgr24")
        return out

"""A camera frame streamed from a log: where it came from, and its pixels on request."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import numpy.typing as npt

from memlog.io.image import decode_bgr, decode_bgr_reduced, decode_gray
from memlog.io.types import ImagePayload

__all__ = ["Frame"]


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
        return decode_bgr(self.payload)

    def decode_bgr_reduced(self, min_width: int, min_height: int) -> npt.NDArray[np.uint8]:
        """Decode to BGR at the smallest JPEG DCT scale (full, 1/2, 1/4, 1/8) that is at least
        ``min_width`` x ``min_height`` (:func:`memlog.io.image.decode_bgr_reduced`: for consumers
        that shrink frames themselves, never for the scores)."""
        return decode_bgr_reduced(self.payload, min_width, min_height)

    def decode_gray(self) -> npt.NDArray[np.uint8]:
        """Decode the payload to an HxW uint8 grey array (see :mod:`memlog.io.image`)."""
        return decode_gray(self.payload)

    def stripped(self) -> Frame:
        """This frame without its pixels (payload data emptied; kind and encoding kept): what
        results carry once a frame is scored or described."""
        return replace(self, payload=ImagePayload(self.payload.kind, self.payload.encoding, b""))

"""``--descriptor auto``: the descriptor chosen from the camera's frame size.

Rule: the learned descriptor :data:`AUTO_LEARNED` when the shorter side of the first frame that
decodes is at least :data:`AUTO_MIN_SIDE` pixels, else the thumbnail. Why:

* on ordinary frames (960x540, a real second traversal with a lateral shift) DINOv2 localized
  far better than the thumbnail; of its poolings, layers, scales and input fits
  (``benchmarks/descriptor_choices.py``, Stromovka), GeM of the final tokens on the stretched
  frame held up on memlog's full, half and quarter maps alike (the mean of the tokens, better on
  the full map, lost on the half map: ``docs/defaults.md``);
* on tiny frames (Nordland 64x32, summer -> winter, 800 places; ``benchmarks/descriptor_recall.py``)
  the DINOv2 kinds are several times worse than the thumbnail, the frames being enlarged 3.5 to
  7 times to the network's 224 x 224 input.

No real second traversal between those two sizes was available, so the threshold is placed,
not measured: 112 px is half the network's input side, i.e. no frame is enlarged more than 2x
on its short side before DINOv2 sees it. The choice (rule, threshold, frame size, kind) is
recorded in the map's metadata and in ``results.json``.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

from memlog.errors import DescriptorError, ImageDecodeError
from memlog.io.base import LogReader

__all__ = ["AUTO", "AUTO_MIN_SIDE", "AUTO_LEARNED", "AUTO_SMALL", "DescriptorChoice", "choose_descriptor",
           "probe_frame_size", "resolve_descriptor"]

AUTO = "auto"
#: Shortest frame side (pixels) from which the learned descriptor is chosen.
AUTO_MIN_SIDE = 112
#: The learned descriptor ``auto`` picks for ordinary frames.
AUTO_LEARNED = "dinov2-gem"
#: The descriptor ``auto`` picks for tiny frames.
AUTO_SMALL = "thumbnail"
RULE = f"{AUTO_LEARNED} if min(width, height) >= {AUTO_MIN_SIDE} px else {AUTO_SMALL}"


@dataclass(frozen=True)
class DescriptorChoice:
    """Which descriptor a run uses and why (recorded with the map)."""

    requested: str
    chosen: str
    frame_size: tuple[int, int] | None = None  # (width, height) of the probed frame
    rule: str | None = None
    min_side: int | None = None

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["frame_size"] = list(self.frame_size) if self.frame_size else None
        return d

    def describe(self) -> str:
        if self.requested != AUTO:
            return f"descriptor {self.chosen}"
        size = f"{self.frame_size[0]}x{self.frame_size[1]}" if self.frame_size else "unknown size"
        return f"descriptor auto -> {self.chosen} (frames {size}; rule: {self.rule})"


def choose_descriptor(requested: str, frame_size: tuple[int, int] | None) -> DescriptorChoice:
    """The descriptor for ``requested`` (a registry name, or ``"auto"``) and frames of
    ``frame_size`` (width, height); ``auto`` with no known size is the thumbnail."""
    if requested != AUTO:
        return DescriptorChoice(requested, requested)
    small = frame_size is None or min(frame_size) < AUTO_MIN_SIDE
    return DescriptorChoice(AUTO, AUTO_SMALL if small else AUTO_LEARNED, frame_size, RULE, AUTO_MIN_SIDE)


def probe_frame_size(reader: LogReader, topic: str, max_tries: int = 20) -> tuple[int, int] | None:
    """(width, height) of the first frame of ``topic`` that decodes (of the first ``max_tries``)."""
    for n, frame in enumerate(reader.frames([topic])):
        try:
            img = frame.decode_bgr()
        except ImageDecodeError:
            if n + 1 >= max_tries:
                return None
            continue
        return int(img.shape[1]), int(img.shape[0])
    return None


def resolve_descriptor(requested: str, reader: LogReader, topic: str) -> DescriptorChoice:
    """:func:`choose_descriptor` for the frames of ``topic`` in ``reader`` (probes only for auto)."""
    if requested != AUTO:
        return DescriptorChoice(requested, requested)
    size = probe_frame_size(reader, topic)
    if size is None:
        raise DescriptorError(f"{reader.path}: topic {topic}: no frame decodes, so --descriptor auto cannot choose; "
                              "name a descriptor with --descriptor")
    return choose_descriptor(requested, size)

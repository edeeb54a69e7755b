"""Staticity (the paper's map S and score SS): pixels covered by dynamic objects count 0.

One detector pass per frame (:func:`detect`, SSD MobileNet v2 COCO, see
:mod:`memlog.models.detector`), then :func:`static_map`: every pixel inside a kept box is
dynamic (0), every other pixel static (1). A box is kept when its class is dynamic, its
confidence is >= ``conf`` (0.55) and it covers >= ``min_area`` (5 %) of the pixels.

Reference conventions (SPEC.md): boxes are clipped to [0, 1]; pixel (row i, col j) of a
``size`` x ``size`` map is inside a box iff its centre ((j + 0.5) / size, (i + 0.5) / size)
lies in [x0, x1) x [y0, y1); the 5 % test counts the pixels by the same rule.

Dynamic classes: the paper says 21 of the 80 COCO classes ("cars, pedestrians, buses, trucks,
animals etc.") without listing them. memlog takes person, the eight vehicles and the ten
animals of COCO (19), plus the two objects that are only in a scene while a person is moving
them and are never part of a place: skateboard and kite (:data:`DYNAMIC_CLASSES`, with reasons).
"""

from __future__ import annotations

import threading
from collections.abc import Iterable, Mapping
from dataclasses import asdict, dataclass
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from memlog.errors import ScoringError
from memlog.models.detector import COCO_LABELS

__all__ = [
    "DYNAMIC_CLASSES",
    "Detection",
    "detect",
    "static_map",
    "staticity_score",
    "Staticity",
]

#: The 21 dynamic COCO classes -> why each is not part of a place.
DYNAMIC_CLASSES: dict[str, str] = {
    "person": "pedestrians walk through the scene and are gone on the next visit",
    "bicycle": "ridden through or parked for a while; not a fixed landmark",
    "car": "drives past or is parked for hours; the commonest occluder on roads",
    "motorcycle": "a vehicle in traffic or parked for a while",
    "airplane": "flies, taxis or is moved between stands",
    "bus": "a vehicle in traffic, at a stop only for minutes",
    "train": "occupies the track only while it passes or stops",
    "truck": "a vehicle in traffic or parked for a delivery",
    "boat": "sails, or is moored and moved with the seasons",
    "bird": "an animal that flies off",
    "cat": "an animal that walks away",
    "dog": "an animal, usually walked by a person",
    "horse": "livestock that moves around its field or on the road",
    "sheep": "livestock that grazes from place to place",
    "cow": "livestock that grazes from place to place and is moved between fields",
    "elephant": "an animal that roams",
    "bear": "an animal that roams",
    "zebra": "an animal that roams",
    "giraffe": "an animal that roams",
    "skateboard": "only in the scene while someone rides or carries it",
    "kite": "only in the sky while someone flies it",
}


@dataclass(frozen=True)
class Detection:
    """One detector box, coordinates relative to the frame, clipped to [0, 1]."""

    class_id: int
    class_name: str
    confidence: float
    x0: float
    y0: float
    x1: float
    y1: float
    dynamic: bool

    def to_json(self) -> dict[str, Any]:
        """Plain dict (floats rounded to 6 digits) for JSON outputs."""
        d = asdict(self)
        for k in ("confidence", "x0", "y0", "x1", "y1"):
            d[k] = round(float(d[k]), 6)
        return d


def _names(dynamic: Iterable[str] | Mapping[str, Any]) -> frozenset[str]:
    if isinstance(dynamic, str):
        raise ScoringError("dynamic must be a collection of class names, not one string")
    return frozenset(dynamic)


def _check_frame(bgr: Any, size: int | None = None) -> npt.NDArray[np.uint8]:
    if not isinstance(bgr, np.ndarray) or bgr.ndim != 3 or bgr.shape[2] != 3 or bgr.dtype != np.uint8:
        shape = getattr(bgr, "shape", None)
        dtype = getattr(bgr, "dtype", None)
        raise ScoringError(f"expected an HxWx3 uint8 BGR frame, got shape {shape} dtype {dtype}")
    if size is not None and bgr.shape[:2] != (size, size):
        raise ScoringError(
            f"expected the {size}x{size} frame (memlog.scoring.scorer.resize_frame), got {bgr.shape[1]}x{bgr.shape[0]}"
        )
    return bgr


def detect(
    net: Any,
    bgr1135: npt.NDArray[np.uint8],
    *,
    min_conf: float = 0.0,
    dynamic: Iterable[str] | Mapping[str, Any] = DYNAMIC_CLASSES,
) -> list[Detection]:
    """Run the detector once on a BGR frame; detections with confidence >= ``min_conf``.

    Input blob: ``cv2.dnn.blobFromImage(frame, 1.0, (300, 300), swapRB=True)`` (the graph
    normalises the 0..255 RGB input itself). Sorted by confidence, highest first.
    """
    frame = _check_frame(bgr1135)
    names = _names(dynamic)
    blob = cv2.dnn.blobFromImage(frame, scalefactor=1.0, size=(300, 300), mean=(0.0, 0.0, 0.0), swapRB=True, crop=False)
    try:
        net.setInput(blob)
        out = np.asarray(net.forward(), dtype=np.float64)
    except cv2.error as exc:
        raise ScoringError(f"the detector failed: {exc}") from exc
    if out.size % 7:
        raise ScoringError(f"unexpected detector output shape {out.shape} (want Nx7 rows)")
    dets: list[Detection] = []
    for row in out.reshape(-1, 7):
        conf = float(row[2])
        if row[0] < 0 or not conf > 0.0 or conf < min_conf or not np.all(np.isfinite(row[3:7])):
            continue
        cid = int(row[1])
        name = COCO_LABELS.get(cid, f"id{cid}")
        x0, y0, x1, y1 = (min(1.0, max(0.0, float(v))) for v in row[3:7])
        dets.append(Detection(cid, name, conf, x0, y0, x1, y1, name in names))
    dets.sort(key=lambda d: -d.confidence)
    return dets


def _span(lo: float, hi: float, centres: npt.NDArray[np.float64]) -> tuple[int, int]:
    """Indices [a, b) of the pixel centres c with lo <= c < hi."""
    a = int(np.searchsorted(centres, lo, side="left"))
    b = int(np.searchsorted(centres, hi, side="left"))
    return a, max(a, b)


def static_map(
    detections: Iterable[Detection],
    size: int = 1135,
    conf: float = 0.55,
    min_area: float = 0.05,
    dynamic: Iterable[str] | Mapping[str, Any] = DYNAMIC_CLASSES,
) -> npt.NDArray[np.uint8]:
    """The ``size`` x ``size`` staticity map S (uint8, 1 = static, 0 = dynamic).

    Kept boxes: class name in ``dynamic``, confidence >= ``conf``, and at least
    ``min_area * size**2`` pixels inside (centre rule of the module docstring).
    """
    if isinstance(size, bool) or not isinstance(size, (int, np.integer)) or size < 1:
        raise ScoringError(f"static map size must be a positive integer, got {size!r}")
    size = int(size)
    names = _names(dynamic)
    centres = (np.arange(size, dtype=np.float64) + 0.5) / size
    s = np.ones((size, size), np.uint8)
    need = min_area * size * size * (1.0 - 1e-12)  # a box of exactly 5 % passes despite rounding
    for d in detections:
        if d.class_name not in names or not d.confidence >= conf:
            continue
        x0, y0, x1, y1 = (min(1.0, max(0.0, float(v))) for v in (d.x0, d.y0, d.x1, d.y1))
        c0, c1 = _span(x0, x1, centres)
        r0, r1 = _span(y0, y1, centres)
        if c1 > c0 and r1 > r0 and (c1 - c0) * (r1 - r0) >= need:
            s[r0:r1, c0:c1] = 0
    return s


def staticity_score(static: npt.NDArray[Any]) -> float:
    """SS = sum(S) / (H * W): the fraction of static pixels."""
    if not isinstance(static, np.ndarray) or static.ndim != 2 or static.size == 0:
        raise ScoringError(f"staticity_score expects a non-empty 2-D map, got shape {getattr(static, 'shape', None)}")
    return float(static.sum(dtype=np.float64) / static.size)


class Staticity:
    """Detector + static map: ``Staticity()(frame1135) -> (S, SS, detections)``.

    The detector loads on first use (``.net``). ``detections`` are those with confidence
    >= ``conf``, dynamic or not (``Detection.dynamic`` tells).
    """

    def __init__(
        self,
        net: Any = None,
        *,
        conf: float = 0.55,
        min_area: float = 0.05,
        dynamic: Iterable[str] | Mapping[str, Any] = DYNAMIC_CLASSES,
        size: int = 1135,
        device: str = "auto",
    ) -> None:
        self._net = net
        self.device = device
        self.conf = float(conf)
        self.min_area = float(min_area)
        self.dynamic = _names(dynamic)
        unknown = sorted(self.dynamic - set(COCO_LABELS.values()))
        if unknown:
            raise ScoringError(f"unknown COCO class names in dynamic classes: {unknown}")
        self.size = int(size)
        self._lock = threading.Lock()

    @property
    def net(self) -> Any:
        """The ``cv2.dnn`` detector (loaded by :func:`memlog.models.detector.load_detector`)."""
        if self._net is None:
            from memlog.models.detector import load_detector

            self._net = load_detector(self.device)
        return self._net

    def warm(self) -> None:
        """Load the detector and run its first forward (slower than the others) on a blank frame,
        so that a thread can do both while other work goes on."""
        net = self.net
        with self._lock:
            detect(net, np.zeros((self.size, self.size, 3), np.uint8), min_conf=self.conf, dynamic=self.dynamic)

    def __call__(self, bgr1135: npt.NDArray[np.uint8]) -> tuple[npt.NDArray[np.uint8], float, list[Detection]]:
        frame = _check_frame(bgr1135, self.size)
        net = self.net
        with self._lock:  # one cv2.dnn.Net must not run two forwards at once
            dets = detect(net, frame, min_conf=self.conf, dynamic=self.dynamic)
        s = static_map(dets, self.size, self.conf, self.min_area, self.dynamic)
        return s, staticity_score(s), dets

    def __repr__(self) -> str:
        return f"Staticity(conf={self.conf}, min_area={self.min_area}, classes={len(self.dynamic)}, size={self.size})"

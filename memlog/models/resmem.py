"""ResMem memorability CNN: input geometry, state-dict check, ONNX conversion, the cached model.

ResMem (PyPI ``resmem==1.1.6``, Needell & Bainbridge) is a torchvision ResNet-152 (its 1000-way
``fc`` kept) next to an AlexNet-like branch; the 9216 AlexNet features and the 1000 ResNet
logits are concatenated and fed through seven fully connected layers to one sigmoid output.
Input: 227 x 227 RGB, float 0..1, no mean/std normalisation.

memlog never imports torch or the ``resmem`` package: :func:`convert` reads the shipped
``model.pt`` with the restricted reader of :mod:`memlog.models.state_dict`, checks every tensor
name and shape against :data:`EXPECTED_SHAPES` (derived from the architecture, not from the
file), folds the eval-mode BatchNorms into the preceding convolutions and writes an ONNX graph
built with :mod:`onnx.helper`.

Input geometry (SPEC.md, reference conventions): a frame is resized to 1135 x 1135 and cut into
a row-major 5 x 5 grid of 227 x 227 RGB crops (float32 / 255, NCHW, no mean/std)
(:func:`crops_from_frame`). The 5 x 5 crop scores M are bilinearly upsampled to the frame, so
MS = sum_k w_k M_k with weights ``w = A^T S A / 1135^2`` (:func:`crop_weights`), where A is the
interpolation matrix of ``cv2.resize`` and S the staticity map.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from functools import lru_cache
from pathlib import Path
from types import MappingProxyType
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from memlog.errors import ModelError
from memlog.models import cache
from memlog.models.fetch import cached_package_file, fetch_package_file, installed_package_file, sha256_file
from memlog.models.state_dict import load_state_dict
from memlog.progress import info

__all__ = [
    "FRAME",
    "GRID",
    "CROP",
    "crops_from_frame",
    "check_crops",
    "check_static_map",
    "crop_weights",
    "interp_matrix",
    "run_crops",
    "EXPECTED_SHAPES",
    "RESMEM_VERSION",
    "INPUT_NAME",
    "OUTPUT_NAME",
    "FEATURES_NAME",
    "check_state_dict",
    "resnet_bn_layers",
    "build_onnx",
    "convert",
    "locate_resmem_weights",
    "prepare_resmem",
    "resmem_onnx_path",
    "resmem_pins",
    "RESMEM_FILE",
]

RESMEM_DIST = "resmem"
RESMEM_VERSION = "1.1.6"
RESMEM_MEMBER = "resmem/model.pt"
#: sha256 of ``resmem/model.pt`` in the ``resmem-1.1.6-py3-none-any.whl`` wheel on PyPI.
RESMEM_SHA256 = "8e4b8ab0ac338909add68a674e9bd4c1602350731abe7f97bc060dc159706a53"
#: Bump when the generated graph changes; prepared models with another version are rebuilt.
CONVERTER_VERSION = "1"
OPSET = 17
BN_EPS = 1e-5
RESMEM_FILE = f"resmem-{RESMEM_VERSION}.onnx"

INPUT_NAME = "crops"
OUTPUT_NAME = "memorability"
FEATURES_NAME = "resnet_pool"
CROP = 227
GRID = 5
FRAME = GRID * CROP  # 1135

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]

#: torchvision ResNet-152: bottleneck blocks per stage, and the stage widths.
_RESNET_BLOCKS = (3, 8, 36, 3)
_RESNET_PLANES = (64, 128, 256, 512)
_EXPANSION = 4

Shape = tuple[int, ...]
Array = npt.NDArray[Any]


# ---------------------------------------------------------------------------------------------
# input geometry


def crops_from_frame(bgr1135: npt.NDArray[Any]) -> F32:
    """[25,3,227,227] float32 crops (RGB /255) of a 1135 x 1135 BGR uint8 frame, row-major."""
    if not isinstance(bgr1135, np.ndarray):
        raise ModelError(f"frame must be a numpy array, got {type(bgr1135).__name__}")
    if bgr1135.shape != (FRAME, FRAME, 3):
        raise ModelError(
            f"frame must be {FRAME}x{FRAME}x3 BGR (resize with cv2.resize first), got shape {bgr1135.shape}"
        )
    if bgr1135.dtype != np.uint8:
        raise ModelError(f"frame must be uint8 BGR, got dtype {bgr1135.dtype}")
    rgb = bgr1135[:, :, ::-1]
    grid = rgb.reshape(GRID, CROP, GRID, CROP, 3).transpose(0, 2, 4, 1, 3)
    crops = grid.reshape(GRID * GRID, 3, CROP, CROP).astype(np.float32)
    crops /= np.float32(255.0)
    return crops


def check_crops(crops: npt.NDArray[Any]) -> None:
    """:class:`ModelError` unless ``crops`` is a float32 ``[N, 3, 227, 227]`` array."""
    if not isinstance(crops, np.ndarray) or crops.ndim != 4 or crops.shape[1:] != (3, CROP, CROP):
        shape = getattr(crops, "shape", None)
        raise ModelError(f"crops must be [N,3,{CROP},{CROP}], got {shape}")
    if crops.dtype != np.float32:
        raise ModelError(f"crops must be float32, got {crops.dtype}")


def check_static_map(s: npt.NDArray[Any]) -> F64:
    """The staticity map as float64, checked: 1135 x 1135 with values in 0..1."""
    if not isinstance(s, np.ndarray) or s.shape != (FRAME, FRAME):
        raise ModelError(f"static map must be {FRAME}x{FRAME}, got {getattr(s, 'shape', None)}")
    s64 = np.asarray(s, dtype=np.float64)
    if not np.all((s64 >= 0) & (s64 <= 1)):
        raise ModelError("static map values must lie in 0..1")
    return s64


@lru_cache(maxsize=1)
def interp_matrix() -> F64:
    """A (1135 x 5) with cv2.resize(M) == A @ M @ A.T for INTER_LINEAR (read off cv2 itself)."""
    up = cv2.resize(np.eye(GRID, dtype=np.float64), (GRID, FRAME), interpolation=cv2.INTER_LINEAR)
    a: F64 = np.asarray(up, dtype=np.float64)
    a.setflags(write=False)
    return a


def crop_weights(s: npt.NDArray[Any] | None = None) -> F64:
    """5 x 5 weights w with MS = sum(w * M) for every M: w = A^T S A / 1135^2 (sums to SS)."""
    a = interp_matrix()
    if s is None:
        col = a.sum(axis=0)
        return np.asarray(np.outer(col, col) / (FRAME * FRAME), dtype=np.float64)
    # einsum's own loops, not BLAS: the same sums in the same order whatever BLAS's thread count
    # (workers run it on one thread), so a worker's weights are the driver's to the last bit; each
    # column of A only over the rows where it is not zero (the zeros add nothing: the same sums)
    sm = np.asarray(check_static_map(s), dtype=np.float64)
    s_a = np.empty((sm.shape[0], GRID))
    for j, (lo, hi) in enumerate(_spans()):
        s_a[:, j] = np.einsum("rc,c->r", sm[:, lo:hi], a[lo:hi, j])
    w = np.empty((GRID, GRID))
    for i, (lo, hi) in enumerate(_spans()):
        w[i] = np.einsum("r,rj->j", a[lo:hi, i], s_a[lo:hi])
    return np.asarray(w / (FRAME * FRAME), dtype=np.float64)


@lru_cache(maxsize=1)
def _spans() -> tuple[tuple[int, int], ...]:
    """Per column of :func:`interp_matrix`, the rows [lo, hi) outside which it is zero."""
    a = interp_matrix()
    out = []
    for j in range(a.shape[1]):
        nz = np.flatnonzero(a[:, j])
        out.append((int(nz.min()), int(nz.max()) + 1))
    return tuple(out)


def run_crops(session: Any, crops: F32) -> F32:
    """Scores (N,) of a crop batch through a ResMem ONNX session (fp32 or int8)."""
    try:
        out = session.run([OUTPUT_NAME], {INPUT_NAME: np.ascontiguousarray(crops)})[0]
    except Exception as exc:  # onnxruntime raises its own exception types
        raise ModelError(f"the memorability model failed: {exc}") from exc
    return np.asarray(out, dtype=np.float32).reshape(-1)


# ---------------------------------------------------------------------------------------------
# the state dict and its conversion


def _bn_shapes(prefix: str, ch: int) -> dict[str, Shape]:
    return {
        f"{prefix}.weight": (ch,),
        f"{prefix}.bias": (ch,),
        f"{prefix}.running_mean": (ch,),
        f"{prefix}.running_var": (ch,),
        f"{prefix}.num_batches_tracked": (),
    }


def _resnet_blocks() -> list[tuple[str, int, int, int, bool]]:
    """(prefix, in_ch, planes, stride, has_downsample) for every bottleneck, in order."""
    blocks: list[tuple[str, int, int, int, bool]] = []
    inplanes = 64
    for stage, (n, planes) in enumerate(zip(_RESNET_BLOCKS, _RESNET_PLANES), start=1):
        for i in range(n):
            stride = 2 if (i == 0 and stage > 1) else 1
            down = i == 0 and (stride != 1 or inplanes != planes * _EXPANSION)
            blocks.append((f"features.layer{stage}.{i}", inplanes, planes, stride, down))
            inplanes = planes * _EXPANSION
    return blocks


def _expected_shapes() -> dict[str, Shape]:
    shapes: dict[str, Shape] = {"features.conv1.weight": (64, 3, 7, 7)}
    shapes.update(_bn_shapes("features.bn1", 64))
    for prefix, cin, planes, _stride, down in _resnet_blocks():
        cout = planes * _EXPANSION
        shapes[f"{prefix}.conv1.weight"] = (planes, cin, 1, 1)
        shapes.update(_bn_shapes(f"{prefix}.bn1", planes))
        shapes[f"{prefix}.conv2.weight"] = (planes, planes, 3, 3)
        shapes.update(_bn_shapes(f"{prefix}.bn2", planes))
        shapes[f"{prefix}.conv3.weight"] = (cout, planes, 1, 1)
        shapes.update(_bn_shapes(f"{prefix}.bn3", cout))
        if down:
            shapes[f"{prefix}.downsample.0.weight"] = (cout, cin, 1, 1)
            shapes.update(_bn_shapes(f"{prefix}.downsample.1", cout))
    shapes["features.fc.weight"] = (1000, 2048)
    shapes["features.fc.bias"] = (1000,)
    # AlexNet-like branch: (name, out, in per group, kernel)
    for name, cout, cin_g, k in (
        ("conv1", 48, 3, 11),
        ("conv2", 256, 24, 5),
        ("conv3", 384, 128, 3),
        ("conv4", 384, 192, 3),
        ("conv5", 256, 192, 3),
    ):
        shapes[f"{name}.weight"] = (cout, cin_g, k, k)
        shapes[f"{name}.bias"] = (cout,)
    dims = (9216 + 1000, 4096, 4096, 2048, 1024, 512, 256, 1)
    for i, (din, dout) in enumerate(zip(dims[:-1], dims[1:]), start=6):
        shapes[f"fc{i}.weight"] = (dout, din)
        shapes[f"fc{i}.bias"] = (dout,)
    return shapes


#: Tensor name -> shape of the ResMem state dict (956 tensors).
EXPECTED_SHAPES: Mapping[str, Shape] = MappingProxyType(_expected_shapes())


def resnet_bn_layers() -> list[str]:
    """Names (state-dict prefixes) of the 155 BatchNorm layers of the ResNet-152, in graph order."""
    names = ["features.bn1"]
    for prefix, *_rest, down in _resnet_blocks():
        names += [f"{prefix}.bn1", f"{prefix}.bn2", f"{prefix}.bn3"]
        if down:
            names.append(f"{prefix}.downsample.1")
    return names


def _cap(items: list[str], limit: int = 8) -> str:
    shown = ", ".join(items[:limit])
    return shown + (f", ... ({len(items) - limit} more)" if len(items) > limit else "")


def check_state_dict(sd: Mapping[str, Array]) -> None:
    """Raise :class:`ModelError` unless ``sd`` has exactly the ResMem tensors with their shapes."""
    missing = [k for k in EXPECTED_SHAPES if k not in sd]
    unexpected = [k for k in sd if k not in EXPECTED_SHAPES]
    wrong = []
    for key, shape in EXPECTED_SHAPES.items():
        if key not in sd:
            continue
        arr = sd[key]
        if not isinstance(arr, np.ndarray) or tuple(arr.shape) != shape:
            got = tuple(arr.shape) if isinstance(arr, np.ndarray) else type(arr).__name__
            wrong.append(f"{key} {got} != {shape}")
        elif key.endswith("num_batches_tracked"):
            continue
        elif not np.issubdtype(arr.dtype, np.floating):
            wrong.append(f"{key} dtype {arr.dtype} is not floating point")
        elif not np.all(np.isfinite(arr)):
            wrong.append(f"{key} has non-finite values")
    if missing or unexpected or wrong:
        parts = []
        if missing:
            parts.append(f"{len(missing)} missing: {_cap(missing)}")
        if unexpected:
            parts.append(f"{len(unexpected)} unexpected: {_cap(unexpected)}")
        if wrong:
            parts.append(f"{len(wrong)} mis-shaped/invalid: {_cap(wrong)}")
        raise ModelError("not a ResMem state dict: " + "; ".join(parts))


def _onnx() -> Any:
    """The ``onnx`` package, imported on first use (it takes about a second to import)."""
    import onnx
    import onnx.helper
    import onnx.numpy_helper

    return onnx


class _Graph:
    """Small helper collecting nodes, initializers and outputs of an ONNX graph."""

    def __init__(self, sd: Mapping[str, Array], fold_bn: bool) -> None:
        self.sd = sd
        self.fold_bn = fold_bn
        self.nodes: list[Any] = []
        self.inits: list[Any] = []
        self.outputs: list[Any] = []
        self._n = 0

    def name(self, hint: str) -> str:
        self._n += 1
        return f"{hint}_{self._n}"

    def const(self, name: str, arr: Array) -> str:
        self.inits.append(_onnx().numpy_helper.from_array(np.ascontiguousarray(arr, dtype=np.float32), name))
        return name

    def node(self, op: str, inputs: list[str], hint: str, **attrs: Any) -> str:
        out = self.name(hint)
        self.nodes.append(_onnx().helper.make_node(op, inputs, [out], name=out, **attrs))
        return out

    def output(self, name: str, shape: list[int | str]) -> None:
        self.outputs.append(_onnx().helper.make_tensor_value_info(name, _onnx().TensorProto.FLOAT, shape))

    def conv(
        self, x: str, wname: str, bname: str | None, k: int, stride: int, pad: int, group: int = 1,
        w: Array | None = None, b: Array | None = None,
    ) -> str:
        """Conv with weights from the state dict (or explicit arrays ``w``/``b``)."""
        warr = self.sd[wname] if w is None else w
        inputs = [x, self.const(wname, warr)]
        if b is not None:
            inputs.append(self.const(bname or wname.removesuffix(".weight") + ".bias", b))
        elif bname is not None:
            inputs.append(self.const(bname, self.sd[bname]))
        return self.node(
            "Conv", inputs, wname.removesuffix(".weight"), kernel_shape=[k, k],
            strides=[stride, stride], pads=[pad] * 4, group=group,
        )

    def conv_bn(self, x: str, conv: str, bn: str, k: int, stride: int, pad: int) -> str:
        """Bias-free conv followed by eval-mode BatchNorm: folded, or explicit plus probe outputs."""
        wname = f"{conv}.weight"
        gamma = self.sd[f"{bn}.weight"].astype(np.float64)
        beta = self.sd[f"{bn}.bias"].astype(np.float64)
        mean = self.sd[f"{bn}.running_mean"].astype(np.float64)
        var = self.sd[f"{bn}.running_var"].astype(np.float64)
        if self.fold_bn:
            scale = gamma / np.sqrt(var + BN_EPS)
            w = self.sd[wname].astype(np.float64) * scale[:, None, None, None]
            return self.conv(x, wname, None, k, stride, pad, w=w, b=beta - mean * scale)
        y = self.conv(x, wname, None, k, stride, pad)
        # probe: per-channel mean and mean square of the conv output over batch and space
        for stat, src in (("mean", y), ("sqmean", self.node("Mul", [y, y], f"{bn}.sq"))):
            red = self.node("ReduceMean", [src], f"{bn}.{stat}", axes=[0, 2, 3], keepdims=0)
            name = f"bn_{stat}/{bn}"
            self.nodes.append(_onnx().helper.make_node("Identity", [red], [name], name=name))
            self.output(name, [int(gamma.size)])
        ins = [y] + [self.const(f"{bn}.{p}", self.sd[f"{bn}.{p}"])
                     for p in ("weight", "bias", "running_mean", "running_var")]
        return self.node("BatchNormalization", ins, bn, epsilon=BN_EPS)

    def gemm(self, x: str, fc: str) -> str:
        return self.node(
            "Gemm", [x, self.const(f"{fc}.weight", self.sd[f"{fc}.weight"]),
                     self.const(f"{fc}.bias", self.sd[f"{fc}.bias"])], fc, transB=1,
        )


def _resnet(g: _Graph, x: str) -> tuple[str, str]:
    """ResNet-152 trunk; returns (pooled 2048-d features, 1000-d fc output)."""
    y = g.conv_bn(x, "features.conv1", "features.bn1", 7, 2, 3)
    y = g.node("Relu", [y], "features.relu")
    y = g.node("MaxPool", [y], "features.maxpool", kernel_shape=[3, 3], strides=[2, 2], pads=[1] * 4)
    for prefix, _cin, _planes, stride, down in _resnet_blocks():
        h = g.node("Relu", [g.conv_bn(y, f"{prefix}.conv1", f"{prefix}.bn1", 1, 1, 0)], f"{prefix}.relu1")
        h = g.node("Relu", [g.conv_bn(h, f"{prefix}.conv2", f"{prefix}.bn2", 3, stride, 1)], f"{prefix}.relu2")
        h = g.conv_bn(h, f"{prefix}.conv3", f"{prefix}.bn3", 1, 1, 0)
        skip = g.conv_bn(y, f"{prefix}.downsample.0", f"{prefix}.downsample.1", 1, stride, 0) if down else y
        y = g.node("Relu", [g.node("Add", [h, skip], f"{prefix}.add")], f"{prefix}.relu3")
    pooled = g.node("GlobalAveragePool", [y], "features.avgpool")
    flat = g.node("Flatten", [pooled], "features.flatten", axis=1)
    return flat, g.gemm(flat, "features.fc")


def _alexnet(g: _Graph, x: str) -> str:
    """The AlexNet-like branch; returns the flattened 9216-d pool5 output."""
    def lrn(t: str, hint: str) -> str:
        # torch LocalResponseNorm(5): x / (k + alpha/n * sum_{c-2..c+2} x^2)^beta, same as ONNX LRN
        return g.node("LRN", [t], hint, size=5, alpha=1e-4, beta=0.75, bias=1.0)

    def pool(t: str, hint: str) -> str:
        return g.node("MaxPool", [t], hint, kernel_shape=[3, 3], strides=[2, 2])

    y = g.node("Relu", [g.conv(x, "conv1.weight", "conv1.bias", 11, 4, 0)], "relu1")
    y = lrn(pool(y, "pool1"), "lrn1")
    y = g.node("Relu", [g.conv(y, "conv2.weight", "conv2.bias", 5, 1, 2, group=2)], "relu2")
    y = lrn(pool(y, "pool2"), "lrn2")
    for name, cin in (("conv3", 3), ("conv4", 3), ("conv5", 3)):
        y = g.node("Relu", [g.conv(y, f"{name}.weight", f"{name}.bias", cin, 1, 1, group=2)], f"relu_{name}")
    return g.node("Flatten", [pool(y, "pool5")], "flatten5", axis=1)


def build_onnx(sd: Mapping[str, Array], *, bn_probe: bool = False) -> Any:
    """Build the ResMem ONNX graph from a checked state dict.

    Input ``crops`` [N,3,227,227] float32 RGB 0..1; outputs ``memorability`` [N,1] and
    ``resnet_pool`` [N,2048] (the pooled ResNet features). With ``bn_probe`` the BatchNorms
    stay explicit ``BatchNormalization`` nodes and, for every ResNet BN layer ``L``, two more
    outputs ``bn_mean/L`` and ``bn_sqmean/L`` give the per-channel mean and mean square of the
    conv output feeding it (over batch and space): a diagnostic graph, not for production.
    """
    check_state_dict(sd)
    g = _Graph(sd, fold_bn=not bn_probe)
    g.output(OUTPUT_NAME, ["N", 1])
    g.output(FEATURES_NAME, ["N", 2048])
    pooled, logits = _resnet(g, INPUT_NAME)
    alex = _alexnet(g, INPUT_NAME)
    h = g.node("Concat", [alex, logits], "concat", axis=1)
    for i in range(6, 12):
        h = g.node("Relu", [g.gemm(h, f"fc{i}")], f"relu{i}")
    g.nodes.append(_onnx().helper.make_node("Sigmoid", [g.gemm(h, "fc12")], [OUTPUT_NAME], name="sigmoid"))
    g.nodes.append(_onnx().helper.make_node("Identity", [pooled], [FEATURES_NAME], name="features_out"))
    graph = _onnx().helper.make_graph(
        g.nodes, "resmem_probe" if bn_probe else "resmem",
        [_onnx().helper.make_tensor_value_info(INPUT_NAME, _onnx().TensorProto.FLOAT, ["N", 3, CROP, CROP])],
        g.outputs, initializer=g.inits,
    )
    model = _onnx().helper.make_model(
        graph, opset_imports=[_onnx().helper.make_opsetid("", OPSET)], producer_name="memlog",
        producer_version=CONVERTER_VERSION,
        doc_string=f"ResMem {RESMEM_VERSION} (resnet152 + alexnet branch), converted by memlog",
    )
    model.ir_version = 8  # readable by onnxruntime >= 1.10
    return model


def resmem_pins() -> dict[str, Any]:
    """What a cached ResMem model must have been made with (see :mod:`memlog.models.cache`)."""
    return {"converter_version": CONVERTER_VERSION, "source_sha256": RESMEM_SHA256}


def convert(model_pt: Path, out_onnx: Path) -> Path:
    """Convert a ResMem ``model.pt`` to ONNX at ``out_onnx`` plus its cache sidecar; returns the path.

    Both files are written atomically (:func:`memlog.models.cache.write_model`); the sidecar
    records the source package, version and sha256, opset and converter version.
    """
    onnx = _onnx()
    model_pt, out_onnx = Path(model_pt), Path(out_onnx)
    src_sha = sha256_file(model_pt)
    model = build_onnx(load_state_dict(model_pt))
    try:
        onnx.checker.check_model(model)
    except onnx.checker.ValidationError as exc:
        raise ModelError(f"generated ResMem ONNX graph is invalid: {exc}") from None
    data = model.SerializeToString()
    del model
    meta = {
        "source": {"package": RESMEM_DIST, "version": RESMEM_VERSION, "member": RESMEM_MEMBER},
        "source_sha256": src_sha,
        "opset": OPSET,
        "converter_version": CONVERTER_VERSION,
        "inputs": {INPUT_NAME: ["N", 3, CROP, CROP]},
        "outputs": {OUTPUT_NAME: ["N", 1], FEATURES_NAME: ["N", 2048]},
    }
    return cache.write_model(out_onnx, data, meta)


def locate_resmem_weights() -> Path:
    """Path of ResMem's ``model.pt``: the installed ``resmem`` package, else the memlog cache."""
    path = installed_package_file("resmem", RESMEM_DIST, RESMEM_VERSION, "model.pt")
    if path is None:
        path = cached_package_file(RESMEM_DIST, RESMEM_VERSION, RESMEM_MEMBER)
    if path is None:
        raise ModelError(
            f"ResMem weights ({RESMEM_DIST}=={RESMEM_VERSION} {RESMEM_MEMBER}) not found; "
            "run `memlog models prepare`"
        )
    return path


def prepare_resmem(progress: bool = True) -> Path:
    """Fetch (if needed) and convert ResMem into ``cache_dir()/models``; returns the ONNX path.

    Does nothing when a prepared model of this converter version is already there. The source
    ``model.pt`` must have the pinned sha256 of the PyPI wheel.
    """
    out = cache.model_path(RESMEM_FILE)
    if cache.is_ready(out, resmem_pins()):
        return out
    try:
        src = locate_resmem_weights()
    except ModelError:
        src = fetch_package_file(RESMEM_DIST, RESMEM_VERSION, RESMEM_MEMBER, quiet=not progress)
    sha = sha256_file(src)
    if sha != RESMEM_SHA256:
        raise ModelError(
            f"{src} has sha256 {sha}, expected {RESMEM_SHA256} ({RESMEM_DIST}=={RESMEM_VERSION}); "
            "delete it and run `memlog models prepare` again"
        )
    if progress:
        info(f"converting {src} to ONNX ...")
    t0 = time.perf_counter()
    convert(src, out)
    if progress:
        info(f"wrote {out} ({time.perf_counter() - t0:.1f} s)")
    return out


def resmem_onnx_path() -> Path:
    """Path of the prepared ResMem ONNX model; :class:`ModelError` naming the command if it is
    missing or stale."""
    return cache.require(cache.model_path(RESMEM_FILE), resmem_pins(), "the ResMem memorability model",
                         "memlog models prepare")

"""ResMem's cost per crop counted from its ONNX graph, and what that means per frame and per GPU.

Reads the cached model (``memlog models prepare``), infers every tensor's shape for one 227 x 227
crop and counts multiply-accumulates of every Conv and Gemm (FLOPs = 2 x MACs; ReLU, pooling,
LRN and additions are under 0.5 % and listed apart). Prints a table, then frames/s per GPU for
a few sustained throughputs::

    python benchmarks/resmem_flops.py [--model PATH] [--crops-per-frame 25] [--tflops 200 400]
"""

from __future__ import annotations

import argparse
import math
from collections import defaultdict
from pathlib import Path

import numpy as np


def _attr(node, name: str, default):  # type: ignore[no-untyped-def]
    import onnx

    for a in node.attribute:
        if a.name == name:
            return onnx.helper.get_attribute_value(a)
    return default


def count(model_path: Path) -> dict[str, dict[str, float]]:
    """Per op type: nodes, MACs and output elements for one crop."""
    import onnx
    from onnx import shape_inference

    model = onnx.load(str(model_path))
    for inp in model.graph.input:  # batch of one crop
        dims = inp.type.tensor_type.shape.dim
        if dims and not dims[0].dim_value:
            dims[0].dim_value = 1
    model = shape_inference.infer_shapes(model)
    shapes: dict[str, list[int]] = {}
    for vi in list(model.graph.value_info) + list(model.graph.input) + list(model.graph.output):
        shapes[vi.name] = [d.dim_value for d in vi.type.tensor_type.shape.dim]
    weights = {t.name: list(t.dims) for t in model.graph.initializer}
    out: dict[str, dict[str, float]] = defaultdict(lambda: {"nodes": 0, "macs": 0.0, "elements": 0.0})
    for node in model.graph.node:
        y = shapes.get(node.output[0])
        elems = float(np.prod(y)) if y else 0.0
        row = out[node.op_type]
        row["nodes"] += 1
        row["elements"] += elems
        if node.op_type == "Conv":
            w = weights[node.input[1]]  # (Cout, Cin/groups, kh, kw)
            row["macs"] += elems * w[1] * w[2] * w[3]
        elif node.op_type in ("Gemm", "MatMul"):
            w = weights.get(node.input[1]) or shapes[node.input[1]]
            k = w[1] if node.op_type == "Gemm" and _attr(node, "transB", 0) else w[0]
            row["macs"] += elems * k
    return dict(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", type=Path, default=Path.home() / ".cache/memlog/models/resmem-1.1.6.onnx")
    ap.add_argument("--crops-per-frame", type=float, default=25.0,
                    help="crops ResMem runs per frame (25: every crop; early exit runs fewer)")
    ap.add_argument("--tflops", type=float, nargs="+", default=[100.0, 200.0, 400.0],
                    help="sustained dense TFLOP/s of the GPU to assume")
    args = ap.parse_args()
    rows = count(args.model)
    total_macs = sum(r["macs"] for r in rows.values())
    print(f"ResMem ({args.model.name}), one 227 x 227 crop")
    print(f"{'op':<18}{'nodes':>7}{'GMACs':>10}{'share':>8}")
    for op, r in sorted(rows.items(), key=lambda kv: -kv[1]["macs"]):
        print(f"{op:<18}{int(r['nodes']):>7}{r['macs'] / 1e9:>10.3f}{100 * r['macs'] / total_macs:>7.1f}%")
    other = sum(r["elements"] for op, r in rows.items() if op not in ("Conv", "Gemm", "MatMul"))
    gflop = 2 * total_macs / 1e9
    print(f"total: {total_macs / 1e9:.3f} GMACs = {gflop:.2f} GFLOPs per crop "
          f"(+ ~{other / 1e9:.3f} G element-wise ops); {gflop * args.crops_per_frame:.1f} GFLOPs per frame "
          f"of {args.crops_per_frame:g} crops")
    print()
    print(f"{'sustained TFLOP/s':>18}{'crops/s':>12}{'frames/s':>12}")
    for t in args.tflops:
        crops = t * 1e12 / (gflop * 1e9)
        print(f"{t:>18g}{crops:>12,.0f}{crops / args.crops_per_frame:>12,.0f}")
    assert math.isfinite(gflop)


if __name__ == "__main__":
    main()

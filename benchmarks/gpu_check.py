#!/usr/bin/env python3
"""memlog's GPU path, checked in minutes on a machine with an NVIDIA GPU (and its CPU fallback anywhere).

    python benchmarks/gpu_check.py [--smoke] [--work DIR] [--json FILE]

**What it needs on a GPU machine.** ONNX Runtime's CUDA execution provider, from pip only:
``pip uninstall -y onnxruntime && pip install 'memlog[gpu]'``, which installs
``onnxruntime-gpu[cuda,cudnn]==1.31.1`` (the pin in pyproject.toml; its ``cuda`` and ``cudnn``
extras bring NVIDIA's CUDA and cuDNN libraries as pip wheels, so only the driver must be on the
machine). The CPU ``onnxruntime`` must not stay beside it: both install the same ``onnxruntime``
module, and this check says when both are there. memlog asks ONNX Runtime for CUDA, then the CPU;
it does not use the TensorRT provider (that would need NVIDIA's ``tensorrt`` wheels and an engine
build per model and GPU), so none is pinned. The detector runs in OpenCV, whose PyPI wheels have no
CUDA: it stays on the CPU and is reported so.

**What it does.** On the shared Stromovka pair (1024x384; autumn map, winter query; ``../shared``
or ``MEMLOG_SHARED_DATA``), each command runs twice as users run it (``python -m memlog ...``, one
process each, model loading included): once with ``MEMLOG_DEVICE=cpu`` (every model on the CPU)
and once with ``--device cuda`` / ``MEMLOG_DEVICE=cuda``:

* ``score`` (exact ResMem, every criterion): frames/s and the scores' agreement (largest
  difference of MS, SS and ES over the frames, and how many frames' kept/rejected decision differs);
* ``map`` (defaults): frames/s and whether the kept frames are the same;
* ``localize`` of the winter drive against that map: frames/s, how many query frames get the same
  best map frame, and R@1 against the shared truth for both runs.

It prints the provider each model actually runs on (an ONNX Runtime session is made for ResMem
and DINOv2 and asked; OpenCV's backend for the detector) and the devices the annotated log
records. ``--smoke``: every 10th frame for ``score`` (11 of 101), the whole autumn drive for
``map`` and the first 41 winter frames for ``localize``: under two minutes on a GPU machine.
Without ``--smoke`` every frame (``score`` exact on the CPU takes minutes there).

**Without a GPU** (no CUDA provider in this ONNX Runtime) it says so, then checks the CPU
fallback: ``score --device auto`` runs on the CPU and records ``cpu`` for every model, and
``score --device cuda`` is refused before any work (exit 1, nothing written) with a message naming
the install command. It exits 0
when the fallback behaves so (1 otherwise): CI runs this mode (``tests/test_gpu_check.py``).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from importlib import metadata
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))
SHARED = Path(os.environ.get("MEMLOG_SHARED_DATA", ROOT.parent / "shared" / "data"))
AUTUMN, WINTER, TRUTH = "stromovka_autumn.mcap", "stromovka_winter.mcap", "stromovka_truth.json"
GPU_PIN = "onnxruntime-gpu[cuda,cudnn]==1.31.1"


def _version(dist: str) -> str | None:
    try:
        return metadata.version(dist)
    except metadata.PackageNotFoundError:
        return None


def environment() -> dict[str, Any]:
    """What this machine offers: ONNX Runtime's packages and providers, OpenCV's CUDA, the GPUs."""
    import cv2
    import onnxruntime as ort

    try:
        cv_cuda = int(cv2.cuda.getCudaEnabledDeviceCount())
    except (AttributeError, cv2.error):
        cv_cuda = 0
    gpus: list[str] = []
    if shutil.which("nvidia-smi"):
        res = subprocess.run(["nvidia-smi", "-L"], capture_output=True, text=True, timeout=30)
        gpus = [line.strip() for line in res.stdout.splitlines() if line.strip()]
    return {"onnxruntime": ort.__version__, "onnxruntime_cpu_dist": _version("onnxruntime"),
            "onnxruntime_gpu_dist": _version("onnxruntime-gpu"), "providers": list(ort.get_available_providers()),
            "opencv": cv2.__version__, "opencv_cuda_devices": cv_cuda, "gpus": gpus}


def model_devices(device: str) -> dict[str, str]:
    """The provider each model's session actually gets for ``device`` (sessions made here)."""
    from memlog.models.detector import load_detector
    from memlog.models.dinov2 import dinov2_session
    from memlog.models.runtime import make_session
    from memlog.scoring.memorability import resmem_onnx_path

    out = {"resmem": make_session(resmem_onnx_path(), device=device, what="ResMem").get_providers()[0],
           "dinov2": dinov2_session(device=device).get_providers()[0]}
    net = load_detector(device)
    out["ssd-mobilenet-v2-coco"] = f"OpenCV dnn ({getattr(net, 'device', 'cpu')})"
    return out


def memlog_cmd(args: Sequence[str], device_env: str, work: Path) -> tuple[float, subprocess.CompletedProcess[str]]:
    """Run ``python -m memlog -q ARGS`` with ``MEMLOG_DEVICE=device_env``; (seconds, result)."""
    env = dict(os.environ, MEMLOG_DEVICE=device_env)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(ROOT), env.get("PYTHONPATH", "")) if p)
    t0 = time.perf_counter()
    res = subprocess.run([sys.executable, "-m", "memlog", "-q", *args], cwd=work, env=env, capture_output=True,
                         text=True)
    return time.perf_counter() - t0, res


def _must(res: subprocess.CompletedProcess[str], what: str) -> None:
    if res.returncode != 0:
        raise SystemExit(f"{what} failed (exit {res.returncode}):\n{res.stderr[-3000:]}")


def _scores(path: Path) -> dict[int, dict[str, Any]]:
    from memlog.outputs.annotated import read_scores

    recs = read_scores(path)
    return {int(r["frame_index"]): r for topic_recs in recs.values() for r in topic_recs}


def _run_meta(path: Path) -> dict[str, str]:
    from mcap.reader import make_reader

    with open(path, "rb") as fh:
        for m in make_reader(fh).iter_metadata():
            if m.name == "memlog_run":
                return dict(m.metadata)
    return {}


def fallback_check(work: Path, log: Path) -> list[str]:
    """The CPU fallback on a machine without CUDA: problems found (empty: it behaves)."""
    problems: list[str] = []
    _, res = memlog_cmd(["score", str(log), "-o", "auto.mcap", "--stride", "50", "--device", "auto"], "auto", work)
    if res.returncode != 0:
        problems.append(f"score --device auto exited {res.returncode}: {res.stderr[-500:]}")
    else:
        devices = json.loads(_run_meta(work / "auto.mcap").get("devices", "{}"))
        if not devices or set(devices.values()) != {"cpu"}:
            problems.append(f"score --device auto recorded devices {devices}, expected cpu for every model")
        else:
            print(f"score --device auto: ran, every model on the CPU ({', '.join(sorted(devices))})")
    _, res = memlog_cmd(["score", str(log), "-o", "cuda.mcap", "--stride", "50", "--device", "cuda"], "auto", work)
    if res.returncode != 1 or "memlog[gpu]" not in res.stderr or "Traceback" in res.stderr \
            or (work / "cuda.mcap").exists():
        problems.append(f"score --device cuda: expected exit 1 (the work cannot be done here) with a message naming "
                        f"pip install 'memlog[gpu]', and no output; got exit {res.returncode}: {res.stderr[-500:]}")
    else:
        print(f"score --device cuda: refused (exit 1): {res.stderr.strip().splitlines()[-1]}")
    return problems


def _agreement_score(cpu: Path, gpu: Path) -> dict[str, Any]:
    a, b = _scores(cpu), _scores(gpu)
    common = sorted(set(a) & set(b))
    out: dict[str, Any] = {"frames": len(common), "only_one_run": len(set(a) ^ set(b))}
    for key in ("ms", "ss", "es"):
        diffs = [abs(float(a[i][key]) - float(b[i][key])) for i in common
                 if a[i].get(key) is not None and b[i].get(key) is not None]
        out[f"max_abs_{key}"] = max(diffs) if diffs else None
    out["decisions_differ"] = sum(1 for i in common if a[i].get("rejected_by") != b[i].get("rejected_by"))
    return out


def _kept(path: Path) -> list[int]:
    import pyarrow.parquet as pq

    return sorted(int(v) for v in pq.read_table(path, columns=["frame_index"]).column("frame_index").to_pylist())


def _best(path: Path) -> dict[int, int]:
    import pyarrow.parquet as pq

    t = pq.read_table(path).to_pydict()
    return {int(q): int(r) for q, r, k in zip(t["query_id"], t["ref_id"], t["rank"]) if k == 0}


def _recall1(best: dict[int, int], truth: dict[str, Any]) -> float:
    ok = [r in truth["matches"][q] for q, r in best.items() if q < len(truth["matches"]) and truth["matches"][q]]
    return sum(ok) / len(ok) if ok else float("nan")


def gpu_runs(work: Path, smoke: bool) -> list[dict[str, Any]]:
    """score, map and localize on the CPU and on CUDA; one row per command."""
    from memlog.io.open import open_log

    autumn, winter = SHARED / AUTUMN, SHARED / WINTER
    truth = json.loads((SHARED / TRUTH).read_text())
    with open_log(autumn) as r:
        n_map = len(r.frame_table(r.camera_topics()[0]).times)
    stride = ["--stride", "10"] if smoke else []  # score: 11 of the 101 frames
    window = ["--end", "+40"] if smoke else []  # localize: the first 41 query frames (1 Hz)
    rows: list[dict[str, Any]] = []
    runs: dict[str, dict[str, Path]] = {"cpu": {}, "cuda": {}}
    for dev in ("cpu", "cuda"):
        d = work / dev
        d.mkdir(exist_ok=True)
        sec, res = memlog_cmd(["score", str(autumn), "-o", "scored.mcap", "--device", dev, *stride], dev, d)
        _must(res, f"score on {dev}")
        n_score = len(_scores(d / "scored.mcap"))
        rows.append({"command": "score", "device": dev, "frames": n_score, "seconds": sec,
                     "devices_recorded": _run_meta(d / "scored.mcap").get("devices")})
        sec, res = memlog_cmd(["map", str(autumn), "-o", "map.mcap", "--device", dev], dev, d)
        _must(res, f"map on {dev}")
        rows.append({"command": "map", "device": dev, "frames": n_map, "seconds": sec})
        sec, res = memlog_cmd(["localize", "map.parquet", str(winter), "-o", "matches.parquet", "--map", "map.mcap",
                               *window], dev, d)
        _must(res, f"localize on {dev}")
        rows.append({"command": "localize", "device": dev, "frames": len(_best(d / "matches.parquet")), "seconds": sec})
        runs[dev] = {"scored": d / "scored.mcap", "map": d / "map.parquet", "matches": d / "matches.parquet"}
    agree = _agreement_score(runs["cpu"]["scored"], runs["cuda"]["scored"])
    same_kept = _kept(runs["cpu"]["map"]) == _kept(runs["cuda"]["map"])
    bc, bg = _best(runs["cpu"]["matches"]), _best(runs["cuda"]["matches"])
    same_best = sum(1 for q in bc if bg.get(q) == bc[q])
    for row in rows:
        if row["command"] == "score":
            row["agreement"] = agree
        elif row["command"] == "map":
            row["agreement"] = {"same_kept_frames": same_kept, "kept": len(_kept(runs[row["device"]]["map"]))}
        else:
            best = bc if row["device"] == "cpu" else bg
            row["agreement"] = {"same_best": f"{same_best}/{len(bc)}", "R@1": round(_recall1(best, truth), 3)}
    return rows


def print_rows(rows: list[dict[str, Any]]) -> None:
    print("| command | device | frames | seconds | frames/s | agreement with the CPU run |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        fps = r["frames"] / r["seconds"] if r["seconds"] else float("nan")
        agree = json.dumps(r.get("agreement", {}), sort_keys=True) if r["device"] == "cuda" or r["command"] == "localize" \
            else ""
        print(f"| {r['command']} | {r['device']} | {r['frames']} | {r['seconds']:.1f} | {fps:.2f} | {agree} |")


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    ap.add_argument("--smoke", action="store_true", help="a short run (under two minutes on a GPU machine)")
    ap.add_argument("--work", type=Path, default=None, help="folder for the outputs (default: a temporary one)")
    ap.add_argument("--json", type=Path, default=None, help="also write the results here")
    args = ap.parse_args(argv)
    for name in (AUTUMN, WINTER, TRUTH):
        if not (SHARED / name).is_file():
            print(f"gpu_check: {SHARED / name} not found (the shared data, or MEMLOG_SHARED_DATA)", file=sys.stderr)
            return 2
    env = environment()
    print(f"ONNX Runtime {env['onnxruntime']} (packages: onnxruntime {env['onnxruntime_cpu_dist']}, onnxruntime-gpu "
          f"{env['onnxruntime_gpu_dist']}); providers: {', '.join(env['providers'])}")
    print(f"OpenCV {env['opencv']}: {env['opencv_cuda_devices']} CUDA device(s); GPUs: {'; '.join(env['gpus']) or 'none'}")
    if env["onnxruntime_cpu_dist"] and env["onnxruntime_gpu_dist"]:
        print("warning: onnxruntime and onnxruntime-gpu are both installed and share one module: "
              "pip uninstall -y onnxruntime onnxruntime-gpu && pip install 'memlog[gpu]'")
    work = args.work or Path(tempfile.mkdtemp(prefix="memlog-gpu-"))
    work.mkdir(parents=True, exist_ok=True)
    result: dict[str, Any] = {"environment": env}
    if "CUDAExecutionProvider" not in env["providers"]:
        print(f"\nno GPU: this ONNX Runtime has no CUDA execution provider (install: pip uninstall -y onnxruntime && "
              f"pip install 'memlog[gpu]', i.e. {GPU_PIN}). Checking the CPU fallback instead.")
        print(f"models on the CPU: {model_devices('auto')}")
        problems = fallback_check(work, SHARED / AUTUMN)
        result.update(mode="no-gpu", problems=problems)
        for p in problems:
            print(f"FAILED: {p}", file=sys.stderr)
        print("CPU fallback: " + ("ok" if not problems else f"{len(problems)} problem(s)"))
        code = 1 if problems else 0
    else:
        print(f"models on cuda: {model_devices('cuda')}")
        rows = gpu_runs(work, args.smoke)
        print()
        print_rows(rows)
        result.update(mode="gpu-smoke" if args.smoke else "gpu", rows=rows)
        code = 0
    if args.json:
        args.json.write_text(json.dumps(result, indent=2, default=str))
    return code


if __name__ == "__main__":
    sys.exit(main())

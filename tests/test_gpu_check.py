"""benchmarks/gpu_check.py in its no-GPU mode (CI has no GPU): it says there is none, checks the CPU
fallback through the CLI and exits 0; the runtime context's device reaches every model session."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import ROOT, shared


def _has_cuda() -> bool:
    import onnxruntime as ort

    return "CUDAExecutionProvider" in ort.get_available_providers()


@pytest.mark.skipif(_has_cuda(), reason="this machine has CUDA: the no-GPU mode does not run (run the check itself)")
def test_gpu_check_without_a_gpu_checks_the_cpu_fallback_and_exits_0(tmp_path: Path) -> None:
    for name in ("stromovka_autumn.mcap", "stromovka_winter.mcap", "stromovka_truth.json"):
        shared(name)
    out = tmp_path / "result.json"
    res = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "gpu_check.py"), "--smoke", "--work",
                          str(tmp_path / "work"), "--json", str(out)], capture_output=True, text=True,
                         env=dict(os.environ, PYTHONPATH=str(ROOT)), timeout=900)
    assert res.returncode == 0, res.stdout + res.stderr
    assert "no GPU" in res.stdout and "memlog[gpu]" in res.stdout
    assert "score --device cuda: refused (exit 1)" in res.stdout
    result = json.loads(out.read_text())
    assert result["mode"] == "no-gpu" and result["problems"] == []
    assert "CUDAExecutionProvider" not in result["environment"]["providers"]
    # what the annotated log of the fallback run records: every model on the CPU
    from mcap.reader import make_reader

    with open(tmp_path / "work" / "auto.mcap", "rb") as fh:
        run = {m.name: m.metadata for m in make_reader(fh).iter_metadata()}["memlog_run"]
    devices = json.loads(run["devices"])
    assert devices and set(devices.values()) == {"cpu"}
    assert not (tmp_path / "work" / "cuda.mcap").exists()  # the refused run wrote nothing


def test_the_runtime_device_is_what_auto_means() -> None:
    from memlog.errors import ModelError
    from memlog.models import runtime as models_runtime
    from memlog.runtime import Runtime, use

    offered = ["CUDAExecutionProvider", "CPUExecutionProvider"]
    old = models_runtime.providers_hook
    models_runtime.providers_hook = lambda: offered
    try:
        assert models_runtime.choose_providers("auto") == offered  # a GPU machine: CUDA first
        with use(Runtime(device="cpu")):
            assert models_runtime.choose_providers("auto") == ["CPUExecutionProvider"]
            assert models_runtime.choose_providers("cuda") == offered  # a step's own --device wins
        models_runtime.providers_hook = lambda: ["CPUExecutionProvider"]
        with use(Runtime(device="cuda")), pytest.raises(ModelError, match="memlog\\[gpu\\]"):
            models_runtime.choose_providers("auto")
    finally:
        models_runtime.providers_hook = old
    assert Runtime.from_environment({"MEMLOG_DEVICE": "CPU"}).device == "cpu"
    from memlog.errors import ConfigError

    with pytest.raises(ConfigError, match="MEMLOG_DEVICE"):
        Runtime.from_environment({"MEMLOG_DEVICE": "gpu"})

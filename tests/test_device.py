"""Where models run: the provider choice for --device auto/cpu/cuda and the fallback on this
machine (no GPU), through the same code a GPU machine runs."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from memlog.errors import ModelError
from memlog.models import runtime
from memlog.models.dinov2 import dinov2_model_path
from tests.conftest import FIXTURES

CUDA, CPU = "CUDAExecutionProvider", "CPUExecutionProvider"


@pytest.fixture()
def providers(monkeypatch: pytest.MonkeyPatch):  # type: ignore[no-untyped-def]
    def set_available(names: list[str]) -> None:
        monkeypatch.setattr(runtime, "providers_hook", lambda: list(names))

    return set_available


def test_choice_with_cuda(providers) -> None:  # type: ignore[no-untyped-def]
    providers([CUDA, CPU])
    assert runtime.choose_providers("auto") == [CUDA, CPU]
    assert runtime.choose_providers("cuda") == [CUDA, CPU]
    assert runtime.choose_providers("cpu") == [CPU]


def test_choice_without_cuda(providers) -> None:  # type: ignore[no-untyped-def]
    providers([CPU])
    assert runtime.choose_providers("auto") == [CPU]
    with pytest.raises(ModelError, match=r"memlog\[gpu\]"):
        runtime.choose_providers("cuda")
    with pytest.raises(ModelError, match="device"):
        runtime.choose_providers("tpu")


def test_this_machine_runs_on_the_cpu() -> None:
    """Here ONNX Runtime has no CUDA provider: auto is the CPU, and a session says so."""
    assert not runtime.cuda_available()
    sess = runtime.make_session(dinov2_model_path(), threads=1, device="auto")
    assert runtime.session_device(sess) == "cpu"
    assert runtime.detector_backend("auto")[0] == "cpu"


def test_cuda_asked_but_absent_is_said_before_any_work(tmp_path: Path) -> None:
    out = tmp_path / "x.mcap"
    r = subprocess.run([sys.executable, "-m", "memlog", "score", str(FIXTURES / "demo.mcap"), "-o", str(out),
                        "--device", "cuda"], capture_output=True, text=True)
    assert r.returncode == 1 and "memlog[gpu]" in r.stderr and "Traceback" not in r.stderr
    assert not out.exists()


def test_requested_cuda_falls_back_and_is_recorded(providers, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    """A CUDA provider that ONNX Runtime lists but cannot use (no GPU): the session falls back to
    the CPU, and runs record where each model really ran."""
    providers([CUDA, CPU])
    sess = runtime.make_session(dinov2_model_path(), threads=1, device="cuda")
    assert runtime.session_device(sess) == "cpu"

"""Where models run: the provider choice for --device auto/cpu/cuda and the fallback, through the
same code a GPU machine runs. Every test sets what ONNX Runtime (and OpenCV) offer, so none
depends on whether this host has a GPU."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest

from memlog.errors import ModelError
from memlog.models import runtime
from memlog.models.dinov2 import dinov2_model_path
from tests.conftest import FIXTURES, ROOT

CUDA, CPU = "CUDAExecutionProvider", "CPUExecutionProvider"


@pytest.fixture()
def providers(monkeypatch: pytest.MonkeyPatch):  # type: ignore[no-untyped-def]
    def set_available(names: list[str]) -> None:
        monkeypatch.setattr(runtime, "providers_hook", lambda: list(names))

    return set_available


class _Recorded:
    """A stand-in ONNX Runtime session that runs where it was asked to (a working GPU, when
    CUDA is first), loading nothing."""

    def __init__(self, path: str, opts: Any, providers: list[str]) -> None:
        self.asked = list(providers)

    def get_providers(self) -> list[str]:
        return list(self.asked)


def _falling_back(real: Any) -> type:
    class FallingBack:
        """What ONNX Runtime does with a CUDA provider it lists but cannot use (no GPU): a real
        session on the CPU, without an error."""

        def __init__(self, path: str, opts: Any, providers: list[str]) -> None:
            self.asked = list(providers)
            self._session = real(path, opts, providers=[p for p in providers if p != CUDA])

        def get_providers(self) -> list[str]:
            return list(self._session.get_providers())

        def __getattr__(self, name: str) -> Any:
            return getattr(self._session, name)

    return FallingBack


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


def test_sessions_get_the_chosen_providers(providers, monkeypatch: pytest.MonkeyPatch) -> None:  # type: ignore[no-untyped-def]
    """make_session hands ONNX Runtime the provider list of the device, and session_device says
    where the session runs: the CUDA path on a (pretended) GPU, the CPU without one."""
    import onnxruntime as ort

    monkeypatch.setattr(ort, "InferenceSession", _Recorded)
    providers([CUDA, CPU])
    for device, want, where in (("auto", [CUDA, CPU], "cuda"), ("cuda", [CUDA, CPU], "cuda"), ("cpu", [CPU], "cpu")):
        sess = runtime.make_session("model.onnx", threads=1, device=device)
        assert sess.asked == want and runtime.session_device(sess) == where, device
    providers([CPU])
    sess = runtime.make_session("model.onnx", threads=1, device="auto")
    assert sess.asked == [CPU] and runtime.session_device(sess) == "cpu"
    with pytest.raises(ModelError, match=r"memlog\[gpu\]"):
        runtime.make_session("model.onnx", device="cuda")


def test_without_cuda_auto_runs_on_the_cpu(providers, monkeypatch: pytest.MonkeyPatch) -> None:  # type: ignore[no-untyped-def]
    """No CUDA provider (and no CUDA in OpenCV): auto is the CPU, and a real session says so."""
    import cv2

    providers([CPU])
    assert not runtime.cuda_available()
    sess = runtime.make_session(dinov2_model_path(), threads=1, device="auto")
    assert runtime.session_device(sess) == "cpu"
    monkeypatch.setattr(cv2.cuda, "getCudaEnabledDeviceCount", lambda: 0)
    assert runtime.detector_backend("auto") == ("cpu", cv2.dnn.DNN_BACKEND_OPENCV, cv2.dnn.DNN_TARGET_CPU)
    monkeypatch.setattr(cv2.cuda, "getCudaEnabledDeviceCount", lambda: 1)  # an OpenCV built with CUDA, a GPU
    assert runtime.detector_backend("auto") == ("cuda", cv2.dnn.DNN_BACKEND_CUDA, cv2.dnn.DNN_TARGET_CUDA)
    assert runtime.detector_backend("cpu")[0] == "cpu"


# Runs the command in a fresh interpreter, ONNX Runtime offering no CUDA provider, and fails
# (exit 99) if any model session is started: the refusal must come before any work.
_WITHOUT_CUDA = textwrap.dedent("""
    import sys
    from memlog.models import runtime
    runtime.providers_hook = lambda: ["CPUExecutionProvider"]
    def _no_work(*a, **k):
        print("a model session was started", file=sys.stderr)
        sys.exit(99)
    runtime.make_session = _no_work
    from memlog.cli.app import main
    sys.exit(main(sys.argv[1:]))
""")


@pytest.mark.parametrize("command", ["score", "map"])
def test_cuda_asked_but_absent_is_said_before_any_work(command: str, tmp_path: Path) -> None:
    out = tmp_path / "x.mcap"
    r = subprocess.run([sys.executable, "-c", _WITHOUT_CUDA, command, str(FIXTURES / "demo.mcap"), "-o", str(out),
                        "--device", "cuda"], capture_output=True, text=True, cwd=ROOT)
    assert r.returncode == 1, r.stderr
    assert "memlog[gpu]" in r.stderr and "Traceback" not in r.stderr
    assert not out.exists() and list(tmp_path.iterdir()) == []


def test_requested_cuda_falls_back_and_is_recorded(providers, monkeypatch: pytest.MonkeyPatch) -> None:  # type: ignore[no-untyped-def]
    """A CUDA provider that ONNX Runtime lists but cannot use (no GPU): the session falls back to
    the CPU, and runs record where each model really ran, not where it was asked to run."""
    import onnxruntime as ort

    from memlog.scoring.config import ScoreConfig
    from memlog.scoring.scorer import Scorer

    monkeypatch.setattr(ort, "InferenceSession", _falling_back(ort.InferenceSession))
    providers([CUDA, CPU])
    sess = runtime.make_session(dinov2_model_path(), threads=1, device="cuda")
    assert sess.asked == [CUDA, CPU] and runtime.session_device(sess) == "cpu"
    # what a run records (the provenance of its outputs) comes from that session, not from the
    # request: a model object with this session in the memorability slot (DINOv2's file stands in
    # for ResMem's: loading ResMem takes much longer and would test nothing more here)
    model = SimpleNamespace(path=dinov2_model_path(), session=sess)
    prov = Scorer(ScoreConfig(device="cuda", threads=1), memorability=model).provenance()
    assert prov["devices"]["resmem"] == "cpu"

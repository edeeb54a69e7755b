"""Where models run: ONNX Runtime sessions on the CPU or a CUDA GPU, and the detector's backend.

``device`` is ``"auto"`` (CUDA when ONNX Runtime has its CUDA execution provider, i.e. the
``onnxruntime-gpu`` package of ``pip install memlog[gpu]``, and a GPU is visible; else the CPU),
``"cpu"`` or ``"cuda"`` (an error naming the install command when CUDA is not available). Every
model (ResMem, int8 ResMem, DINOv2) gets its session from :func:`make_session`, so the GPU path is
the same code with another provider list; :func:`session_device` says which provider a session
really runs on (ONNX Runtime falls back to the CPU silently), and runs record it.
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any, TypeVar

from memlog.errors import ModelError
from memlog.runtime import DEVICES, current

__all__ = [
    "DEVICES",
    "available_providers",
    "cuda_available",
    "choose_providers",
    "make_session",
    "session_device",
    "on_thread",
    "detector_backend",
    "GPU_INSTALL",
]

R = TypeVar("R")

GPU_INSTALL = ("pip uninstall -y onnxruntime && pip install 'memlog[gpu]' (onnxruntime-gpu with NVIDIA's CUDA and "
               "cuDNN wheels; the machine needs the NVIDIA driver)")
_CUDA = "CUDAExecutionProvider"
_CPU = "CPUExecutionProvider"

#: Hook for tests: returns the providers ONNX Runtime offers (default: ``ort.get_available_providers``).
providers_hook: Callable[[], list[str]] | None = None


def available_providers() -> list[str]:
    """Execution providers this ONNX Runtime build offers."""
    if providers_hook is not None:
        return list(providers_hook())
    import onnxruntime as ort

    return list(ort.get_available_providers())


def cuda_available() -> bool:
    """Whether ONNX Runtime offers its CUDA execution provider."""
    return _CUDA in available_providers()


def choose_providers(device: str = "auto") -> list[str]:
    """The provider list for ``device`` (see the module doc; ``auto`` is the runtime context's
    device, :attr:`memlog.runtime.Runtime.device`); :class:`ModelError` for ``cuda`` without
    CUDA, naming the install command."""
    if device not in DEVICES:
        raise ModelError(f"device must be one of {', '.join(DEVICES)}, got {device!r}")
    if device == "auto":
        device = current().device
    if device == "cpu":
        return [_CPU]
    if cuda_available():
        return [_CUDA, _CPU]
    if device == "cuda":
        raise ModelError(f"--device cuda: this ONNX Runtime has no CUDA execution provider; install it: {GPU_INSTALL}")
    return [_CPU]


def make_session(path: Path | str, *, threads: int | None = None, device: str = "auto", what: str = "model") -> Any:
    """An ONNX Runtime session of the model at ``path`` on ``device`` with ``threads`` intra-op
    threads (None: ONNX Runtime's default, every core); :class:`ModelError` when it cannot load."""
    import onnxruntime as ort

    opts = ort.SessionOptions()
    if threads:
        opts.intra_op_num_threads = int(threads)
    opts.inter_op_num_threads = 1
    opts.log_severity_level = 3
    providers = choose_providers(device)
    try:
        return ort.InferenceSession(str(path), opts, providers=providers)
    except Exception as exc:  # onnxruntime raises its own exception types
        raise ModelError(f"could not load {what} from {path} ({exc}); run `memlog models prepare --force`") from None


def on_thread(fn: Callable[..., R], *args: Any, **kwargs: Any) -> Future[R]:
    """``fn(*args, **kwargs)`` started on a thread of its own (model loading while the caller goes on);
    the future's ``result()`` waits for it and raises what it raised. A pool per call, not one made at
    import: a process forked after this call starts its own threads."""
    pool = ThreadPoolExecutor(1, thread_name_prefix="memlog-load")
    try:
        return pool.submit(fn, *args, **kwargs)
    finally:
        pool.shutdown(wait=False)


def session_device(session: Any) -> str:
    """``"cuda"`` when the session's first provider is CUDA, else ``"cpu"``."""
    try:
        provs = session.get_providers()
    except AttributeError:
        return "cpu"
    return "cuda" if provs and provs[0] == _CUDA else "cpu"


def detector_backend(device: str = "auto") -> tuple[str, int, int]:
    """(device used, cv2.dnn backend, target) for the object detector: OpenCV's CUDA backend when
    ``device`` allows it and this OpenCV build has it, else the default CPU backend."""
    import cv2

    if device not in DEVICES:
        raise ModelError(f"device must be one of {', '.join(DEVICES)}, got {device!r}")
    if device == "auto":
        device = current().device
    has_cuda = False
    if device != "cpu":
        try:
            has_cuda = cv2.cuda.getCudaEnabledDeviceCount() > 0
        except (AttributeError, cv2.error):
            has_cuda = False
    if has_cuda:
        return "cuda", cv2.dnn.DNN_BACKEND_CUDA, cv2.dnn.DNN_TARGET_CUDA
    return "cpu", cv2.dnn.DNN_BACKEND_OPENCV, cv2.dnn.DNN_TARGET_CPU

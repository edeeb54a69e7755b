"""Model files: locating the packages that ship weights, converting and caching models, and
running them (ONNX Runtime sessions on the CPU or a GPU). Errors are :class:`ModelError`."""

from memlog.errors import ModelError

__all__ = ["ModelError"]

"""Read a PyTorch zip-format state dict into numpy arrays, without torch.

``torch.save`` (since torch 1.6) writes a zip archive ``<name>/data.pkl`` (a pickle of the
state dict) plus one raw little-endian storage per tensor in ``<name>/data/<key>``. The pickle
names a handful of torch globals; a general unpickler would import and call them, so this
module uses a restricted :class:`pickle.Unpickler` that resolves only the few globals a state
dict needs (tensor rebuild helpers, ``OrderedDict`` and the typed storage classes) to local
stand-ins. Any other global, or a persistent id that is not a storage reference, is refused
with :class:`~memlog.errors.ModelError`: loading never runs code from the file.
"""

from __future__ import annotations

import collections
import io
import pickle
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Literal

import numpy as np
import numpy.typing as npt

from memlog.errors import ModelError

__all__ = ["load_state_dict"]

#: torch storage class name -> numpy dtype (little-endian unless the archive says otherwise).
_STORAGE_DTYPES: dict[str, str] = {
    "DoubleStorage": "f8",
    "FloatStorage": "f4",
    "HalfStorage": "f2",
    "LongStorage": "i8",
    "IntStorage": "i4",
    "ShortStorage": "i2",
    "CharStorage": "i1",
    "ByteStorage": "u1",
    "BoolStorage": "?",
}


@dataclass(frozen=True)
class _StorageType:
    """Stand-in for a ``torch.<X>Storage`` class: only its element dtype matters."""

    name: str
    dtype: str


class _Storages:
    """Reads raw storages from the archive on first use and keeps them for sharing."""

    def __init__(self, zf: zipfile.ZipFile, prefix: str, byteorder: Literal["<", ">"]) -> None:
        self._zf = zf
        self._prefix = prefix
        self._byteorder = byteorder
        self._cache: dict[str, npt.NDArray[Any]] = {}

    def get(self, stype: _StorageType, key: str, numel: int) -> npt.NDArray[Any]:
        """1-D array over the storage ``key`` with ``numel`` elements of ``stype``."""
        if key in self._cache:
            return self._cache[key]
        if not key or "/" in key or key.startswith("."):
            raise ModelError(f"state dict names an invalid storage key {key!r}")
        member = f"{self._prefix}/data/{key}"
        dtype = np.dtype(stype.dtype).newbyteorder(self._byteorder)
        try:
            info = self._zf.getinfo(member)
        except KeyError:
            raise ModelError(f"state dict archive lacks storage {member}") from None
        if info.file_size != numel * dtype.itemsize:
            raise ModelError(
                f"storage {member} has {info.file_size} bytes, expected {numel} x {dtype.itemsize}"
            )
        raw = bytearray(self._zf.read(info))  # writable, so whole-storage tensors need no copy
        arr = np.frombuffer(raw, dtype=dtype, count=numel)
        if not arr.dtype.isnative:
            arr = arr.astype(arr.dtype.newbyteorder("="))
        self._cache[key] = arr
        return arr


def _rebuild_tensor_v2(
    storage: npt.NDArray[Any],
    storage_offset: int,
    size: tuple[int, ...],
    stride: tuple[int, ...],
    requires_grad: bool = False,
    backward_hooks: Any = None,
    metadata: Any = None,
) -> npt.NDArray[Any]:
    """numpy counterpart of ``torch._utils._rebuild_tensor_v2``.

    A tensor that spans its whole storage contiguously is a reshaped view of it (no copy);
    any other layout is copied out with ``as_strided``.
    """
    if not isinstance(storage, np.ndarray):
        raise ModelError("tensor rebuild got something that is not a storage")
    try:
        offset = int(storage_offset)
        shape = tuple(int(s) for s in size)
        strides = tuple(int(s) for s in stride)
    except (TypeError, ValueError):
        raise ModelError("tensor rebuild got a malformed size/stride") from None
    if len(shape) != len(strides) or offset < 0 or any(s < 0 for s in shape + strides):
        raise ModelError(f"tensor rebuild got inconsistent size {shape} / stride {strides}")
    if any(s == 0 for s in shape):
        return np.zeros(shape, dtype=storage.dtype)
    last = offset + sum((n - 1) * st for n, st in zip(shape, strides))
    if last >= storage.size:
        raise ModelError(
            f"tensor of size {shape} stride {strides} offset {offset} overruns its storage "
            f"({storage.size} elements)"
        )
    contiguous = tuple(int(np.prod(shape[i + 1:])) for i in range(len(shape)))
    if offset == 0 and strides == contiguous and int(np.prod(shape)) == storage.size:
        return storage.reshape(shape)  # the usual case: one tensor per storage, no copy
    item = storage.itemsize
    view = np.lib.stride_tricks.as_strided(
        storage[offset:], shape=shape, strides=tuple(st * item for st in strides), writeable=False
    )
    return np.array(view, dtype=storage.dtype, order="C", copy=True)


def _rebuild_parameter(
    data: npt.NDArray[Any], requires_grad: bool = False, backward_hooks: Any = None
) -> npt.NDArray[Any]:
    """numpy counterpart of ``torch._utils._rebuild_parameter``."""
    if not isinstance(data, np.ndarray):
        raise ModelError("parameter rebuild got something that is not a tensor")
    return data


_ALLOWED_FUNCS: dict[tuple[str, str], Callable[..., Any]] = {
    ("collections", "OrderedDict"): collections.OrderedDict,
    ("torch._utils", "_rebuild_tensor_v2"): _rebuild_tensor_v2,
    ("torch._utils", "_rebuild_parameter"): _rebuild_parameter,
}


class _RestrictedUnpickler(pickle.Unpickler):
    """Unpickler that maps the few globals of a state dict to local stand-ins."""

    def __init__(self, data: bytes, storages: _Storages) -> None:
        super().__init__(io.BytesIO(data))
        self._storages = storages

    def find_class(self, module: str, name: str) -> Any:
        func = _ALLOWED_FUNCS.get((module, name))
        if func is not None:
            return func
        if module == "torch" and name in _STORAGE_DTYPES:
            return _StorageType(name, _STORAGE_DTYPES[name])
        raise ModelError(
            f"state dict pickle references {module}.{name}, which is not allowed "
            "(only tensors, storages and OrderedDict are)"
        )

    def persistent_load(self, pid: Any) -> Any:
        if not (isinstance(pid, tuple) and len(pid) == 5 and pid[0] == "storage"):
            raise ModelError(f"state dict pickle has an unsupported persistent id {pid!r:.80}")
        _, stype, key, _location, numel = pid
        if not isinstance(stype, _StorageType) or not isinstance(key, str) or not isinstance(numel, int):
            raise ModelError(f"state dict pickle has a malformed storage reference {pid!r:.80}")
        return self._storages.get(stype, key, numel)


def _archive_prefix(zf: zipfile.ZipFile) -> str:
    pkls = [n for n in zf.namelist() if n.endswith("/data.pkl") and n.count("/") == 1]
    if len(pkls) != 1:
        raise ModelError(f"not a torch zip state dict (found {len(pkls)} top-level data.pkl)")
    return pkls[0].split("/", 1)[0]


def load_state_dict(path: Path) -> dict[str, npt.NDArray[Any]]:
    """Load a torch zip-format state dict as ``{name: numpy array}`` (C-contiguous, native byte order).

    Raises :class:`ModelError` when the file is not such an archive, when the pickle names
    any global other than the tensor/storage helpers, or when a storage is missing or short.
    """
    try:
        zf = zipfile.ZipFile(path)
    except (OSError, zipfile.BadZipFile) as exc:
        raise ModelError(f"cannot open {path} as a torch zip state dict: {exc}") from None
    with zf:
        prefix = _archive_prefix(zf)
        byteorder: Literal["<", ">"] = "<"
        try:
            text = zf.read(f"{prefix}/byteorder").decode("ascii", "replace").strip()
            byteorder = ">" if text == "big" else "<"
        except KeyError:
            pass
        storages = _Storages(zf, prefix, byteorder)
        try:
            obj = _RestrictedUnpickler(zf.read(f"{prefix}/data.pkl"), storages).load()
        except ModelError:
            raise
        except Exception as exc:  # malformed pickles raise many different types
            raise ModelError(f"cannot unpickle {path}: {type(exc).__name__}: {exc}") from None
    if not isinstance(obj, dict):
        raise ModelError(f"{path} holds a {type(obj).__name__}, not a state dict")
    out: dict[str, npt.NDArray[Any]] = {}
    for key, val in obj.items():
        if not isinstance(key, str) or not isinstance(val, np.ndarray):
            raise ModelError(f"{path}: state dict entry {key!r:.60} is not a named tensor")
        out[key] = val
    return out

"""The descriptor interface, the registry of named descriptor configurations and a factory.

A *describer* turns images into global descriptors: one L2-normalised float32 row per image.
Named configurations (hloc style) live in :data:`DESCRIBERS`; :func:`make_describer` builds a
describer from a name plus keyword overrides. The metadata of a describer
(:class:`DescriptorMeta`) travels with the descriptors (Parquet schema metadata) so that a map
and a query described differently are refused instead of silently compared.
"""

from __future__ import annotations

import copy
from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from memlog.errors import DescriptorError

__all__ = [
    "Describer",
    "DescriptorMeta",
    "DESCRIBERS",
    "make_describer",
    "l2_normalize",
    "as_bgr_list",
]

F32 = npt.NDArray[np.float32]


@dataclass(frozen=True)
class DescriptorMeta:
    """What produced a set of descriptors (enough to refuse comparing unlike descriptors).

    ``kind`` is the registry name (``"thumbnail"``, ``"dinov2-cls"`` ...), ``version`` the
    implementation version of that kind, ``params`` the parameters that change the numbers
    (image size, pooling ...), ``model_sha256`` the sha256 of the source weights (None for
    hand-crafted descriptors).
    """

    kind: str
    version: str
    dim: int
    model_sha256: str | None = None
    params: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict."""
        return asdict(self)


class Describer(ABC):
    """Computes global image descriptors: ``describe(images) -> [N, dim]`` float32, unit rows."""

    kind: str
    version: str
    dim: int
    model_sha256: str | None

    @abstractmethod
    def describe(self, images_bgr: Sequence[npt.NDArray[Any]]) -> F32:
        """Descriptors of ``images_bgr`` (HxWx3 BGR or HxW grey uint8), one L2-normalised row each.

        A degenerate image (for example a uniform one) may give an all-zero row, which has
        cosine similarity 0 with everything.
        """

    @property
    def params(self) -> dict[str, Any]:
        """Parameters that change the descriptor values (recorded in :class:`DescriptorMeta`)."""
        return {}

    def meta(self) -> DescriptorMeta:
        """The metadata recorded next to descriptors made by this describer."""
        return DescriptorMeta(self.kind, self.version, self.dim, self.model_sha256, dict(self.params))


#: Named descriptor configurations. ``"class"`` picks the implementation, the other keys are
#: its constructor arguments (overridable in :func:`make_describer`).
DESCRIBERS: dict[str, dict[str, Any]] = {
    "thumbnail": {
        "class": "thumbnail",
        "width": 64,
        "height": 32,
        "patch": 8,
    },
    "dinov2-cls": {
        "class": "dinov2",
        "pooling": "cls",
        "resize": "stretch",
        "batch_size": 16,
    },
    "dinov2-gem": {
        "class": "dinov2",
        "pooling": "gem",
        "gem_p": 3.0,
        "resize": "stretch",
        "batch_size": 16,
    },
}


def make_describer(name: str, **overrides: Any) -> Describer:
    """Build the describer registered as ``name`` in :data:`DESCRIBERS`, with ``overrides``.

    Raises :class:`DescriptorError` for an unknown name or parameter. A dinov2 describer raises
    :class:`~memlog.errors.ModelError` when its model has not been prepared.
    """
    if name not in DESCRIBERS:
        raise DescriptorError(f"unknown descriptor {name!r}; known: {', '.join(sorted(DESCRIBERS))}")
    conf = copy.deepcopy(DESCRIBERS[name])
    cls_name = conf.pop("class")
    conf.update(overrides)
    try:
        if cls_name == "thumbnail":
            from memlog.descriptors.thumbnail import ThumbnailDescriber

            return ThumbnailDescriber(kind=name, **conf)
        if cls_name == "dinov2":
            from memlog.descriptors.dinov2 import DinoV2Describer

            return DinoV2Describer(kind=name, **conf)
    except TypeError as exc:  # unexpected keyword
        raise DescriptorError(f"bad parameters for descriptor {name!r}: {exc}") from None
    raise DescriptorError(f"descriptor {name!r} names unknown implementation {cls_name!r}")


def l2_normalize(x: npt.NDArray[Any], eps: float = 1e-12) -> F32:
    """Rows of ``x`` scaled to unit L2 norm (all-zero rows stay zero), as float32."""
    x = np.asarray(x, dtype=np.float32)
    norms = np.linalg.norm(x, axis=-1, keepdims=True)
    out: F32 = np.where(norms > eps, x / np.maximum(norms, eps), 0.0).astype(np.float32)
    return out


def as_bgr_list(images: Sequence[npt.NDArray[Any]] | npt.NDArray[Any]) -> list[npt.NDArray[Any]]:
    """Validate images: each HxW, HxWx1, HxWx3 (BGR) or HxWx4 (BGRA), non-empty.

    ``images`` is a sequence of images or an ``[N, H, W(, C)]`` array. Returns HxWx3 BGR
    arrays (grey replicated, alpha dropped), dtype unchanged.
    """
    out: list[npt.NDArray[Any]] = []
    for i, img in enumerate(images):
        a = np.asarray(img)
        if a.size == 0:
            raise DescriptorError(f"image {i} is empty")
        if a.ndim == 2:
            a = np.repeat(a[:, :, None], 3, axis=2)
        elif a.ndim == 3 and a.shape[2] == 1:
            a = np.repeat(a, 3, axis=2)
        elif a.ndim == 3 and a.shape[2] == 4:
            a = a[:, :, :3]
        elif not (a.ndim == 3 and a.shape[2] == 3):
            raise DescriptorError(f"image {i} has shape {a.shape}; expected HxW, HxWx1, HxWx3 or HxWx4")
        if a.dtype not in (np.uint8, np.uint16, np.float32, np.float64):
            raise DescriptorError(f"image {i} has dtype {a.dtype}; expected uint8, uint16 or float")
        out.append(a)
    return out

"""The descriptor interface and the metadata that travels with descriptors.

A *describer* turns images into global descriptors: one L2-normalised float32 row per image.
The metadata of a describer (:class:`DescriptorMeta`) travels with the descriptors (Parquet
schema metadata) so that a map and a query described differently are refused
(:func:`check_compatible`) instead of silently compared. Named configurations and the factory
are in :mod:`memlog.descriptors.registry`.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from memlog.errors import DescriptorError

__all__ = [
    "Describer",
    "DescriptorMeta",
    "check_compatible",
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
    hand-crafted descriptors), ``whitening`` the sha256 of the whitening transform applied
    after the describer (:mod:`memlog.descriptors.whitening`; None = not whitened), ``dim`` the
    dimension after it.
    """

    kind: str
    version: str
    dim: int
    model_sha256: str | None = None
    params: dict[str, Any] = field(default_factory=dict)
    whitening: str | None = None

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict."""
        return asdict(self)

    @classmethod
    def from_dict(cls, m: Mapping[str, Any]) -> "DescriptorMeta":
        """Inverse of :meth:`to_dict`."""
        return cls(kind=str(m["kind"]), version=str(m["version"]), dim=int(m["dim"]),
                   model_sha256=m.get("model_sha256"), params=dict(m.get("params") or {}),
                   whitening=m.get("whitening") or None)

    def describe(self) -> str:
        """One line for messages: kind, version, size, model hash and parameters."""
        sha = f"sha256 {self.model_sha256[:12]}…" if self.model_sha256 else "no model"
        params = ", ".join(f"{k}={v}" for k, v in sorted(self.params.items()))
        white = f", whitened sha256 {self.whitening[:12]}…" if self.whitening else ", not whitened"
        return f"{self.kind} v{self.version} ({self.dim}-d{white}, {sha}{'; ' + params if params else ''})"


def check_compatible(map_meta: DescriptorMeta, query_meta: DescriptorMeta) -> None:
    """Raise :class:`DescriptorError` unless both were made by the same describer.

    Compares kind, version, dim, model sha256, params and the whitening transform, e.g. "map
    built with dinov2-cls v1 (384-d, sha256 198644e37de3…), query described with thumbnail v1
    (2048-d, no model)". A whitened map and a query described without its transform (or with
    another one) are refused with a message that says so.
    """
    if map_meta.whitening != query_meta.whitening:
        if map_meta.whitening and not query_meta.whitening:
            why = (f"the map's descriptors are whitened (transform sha256 {map_meta.whitening[:12]}…) but the query "
                   "descriptors were described without whitening")
        elif query_meta.whitening and not map_meta.whitening:
            why = (f"the query descriptors are whitened (transform sha256 {query_meta.whitening[:12]}…) but the "
                   "map's are not")
        else:
            why = (f"the map's descriptors are whitened with transform sha256 {str(map_meta.whitening)[:12]}… but "
                   f"the query's with {str(query_meta.whitening)[:12]}…")
        raise DescriptorError(f"{why}; describe the query with the map's own transform "
                              "(memlog localize does this from the map file)")
    fields = ("kind", "version", "dim", "model_sha256", "params")
    diff = [f for f in fields if getattr(map_meta, f) != getattr(query_meta, f)]
    if diff:
        raise DescriptorError(
            f"map built with {map_meta.describe()}, query described with {query_meta.describe()}: "
            f"{', '.join(diff)} differ; describe both with the same descriptor"
        )


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

    @property
    def gives_patches(self) -> bool:
        """Whether :meth:`describe_patches` gives patch features (for re-ranking)."""
        return False

    def describe_patches(self, images_bgr: Sequence[npt.NDArray[Any]]) -> tuple[F32, F32 | None]:
        """Descriptors of ``images_bgr`` and, when the describer has them
        (:attr:`gives_patches`), each image's pooled patch features ``[N, P, D]`` from the same
        network pass (:mod:`memlog.descriptors.patches`); None otherwise."""
        return self.describe(images_bgr), None

    def meta(self) -> DescriptorMeta:
        """The metadata recorded next to descriptors made by this describer."""
        return DescriptorMeta(self.kind, self.version, self.dim, self.model_sha256, dict(self.params))


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

"""A table of descriptors: one row per frame with its identity, scores and position.

:class:`DescriptorTable` is what describing a log produces (:mod:`memlog.descriptors.extract`),
what a map's reference descriptors are, and what localization matches against; it is stored as
Parquet by :mod:`memlog.outputs.descriptor_table`.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import numpy.typing as npt

from memlog.descriptors.base import DescriptorMeta
from memlog.descriptors.patches import GRID, PatchPCA
from memlog.descriptors.whitening import Whitening
from memlog.errors import DescriptorError

__all__ = ["DescriptorTable", "POSITION_COLUMNS", "SCORE_COLUMNS"]

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]

#: Allowed position column sets: geographic (degrees, metres) or local (metres).
POSITION_COLUMNS: dict[str, tuple[str, ...]] = {"geo": ("lat", "lon", "alt"), "local": ("x", "y", "z")}
SCORE_COLUMNS = ("ms", "ss", "es")


@dataclass
class DescriptorTable:
    """Descriptors of ``N`` frames with their identities, scores, positions and metadata.

    ``descriptors`` is ``[N, dim]`` float32; ``ms``/``ss``/``es`` are float64 with NaN for
    "not scored"; ``positions`` maps column names of one :data:`POSITION_COLUMNS` set to
    float64 arrays (NaN = unknown). ``extra`` is caller metadata stored as JSON.
    ``whitening`` is the transform the descriptors were whitened with when the table carries it
    (a map does; a query table records only its sha256 in ``meta.whitening``).
    ``moving_index``: each frame's index with the drive's stops left out
    (:func:`memlog.scoring.motion.moving_index`: a standing camera's frames share one value; the
    stops from the log's motion, else its images, :func:`memlog.scoring.motion.find_stops`),
    None when it is not known (the table was written before it was recorded, or frames were
    described out of order); sequence matching runs along it.
    ``patches``: each frame's pooled patch features for re-ranking
    (:mod:`memlog.descriptors.patches`), ``[N, 64, d]`` float16, or None: raw (``d`` the
    network's width) while ``patch_pca`` is None, else projected by it (a map's are; a query's
    must be projected by its map's PCA to be compared, :meth:`projected`).
    """

    topic: list[str]
    frame_index: I64
    log_time_ns: I64
    stamp_ns: I64
    descriptors: npt.NDArray[np.float32]
    meta: DescriptorMeta
    ms: F64 | None = None
    ss: F64 | None = None
    es: F64 | None = None
    positions: dict[str, F64] = field(default_factory=dict)
    extra: dict[str, Any] = field(default_factory=dict)
    memlog_version: str | None = None
    whitening: Whitening | None = None
    moving_index: I64 | None = None
    patches: npt.NDArray[np.float16] | None = None
    patch_pca: PatchPCA | None = None

    def __post_init__(self) -> None:
        if self.whitening is not None and (self.whitening.sha256 != self.meta.whitening
                                           or self.whitening.dim_out != self.meta.dim):
            raise DescriptorError(f"the table's whitening transform ({self.whitening.describe()}) is not the one "
                                  f"its metadata names ({self.meta.describe()})")
        self.descriptors = np.ascontiguousarray(self.descriptors, dtype=np.float32)
        if self.descriptors.ndim != 2:
            raise DescriptorError(f"descriptors must be [N, dim], got shape {self.descriptors.shape}")
        n, dim = self.descriptors.shape
        if dim != self.meta.dim:
            raise DescriptorError(f"descriptors have dim {dim} but the metadata says {self.meta.dim}")
        self.topic = [str(t) for t in self.topic]
        self.frame_index = np.asarray(self.frame_index, dtype=np.int64)
        self.log_time_ns = np.asarray(self.log_time_ns, dtype=np.int64)
        self.stamp_ns = np.asarray(self.stamp_ns, dtype=np.int64)
        for name in SCORE_COLUMNS:
            val = getattr(self, name)
            setattr(self, name, np.full(n, np.nan) if val is None else np.asarray(val, dtype=np.float64))
        self.positions = {k: np.asarray(v, dtype=np.float64) for k, v in self.positions.items()}
        if self.moving_index is not None:
            self.moving_index = np.asarray(self.moving_index, dtype=np.int64)
        if self.patches is not None:
            self.patches = np.ascontiguousarray(self.patches, dtype=np.float16)
            want = self.patch_pca.dim if self.patch_pca is not None else None
            if (self.patches.ndim != 3 or len(self.patches) != n or self.patches.shape[1] != GRID * GRID
                    or (want is not None and self.patches.shape[2] != want)):
                raise DescriptorError(f"patches must be [{n}, {GRID * GRID}, {want or 'd'}], got {self.patches.shape}")
        elif self.patch_pca is not None:
            raise DescriptorError("a patch PCA without patches")
        used = [kind for kind, cols in POSITION_COLUMNS.items() if set(self.positions) & set(cols)]
        unknown = set(self.positions) - {c for cols in POSITION_COLUMNS.values() for c in cols}
        if unknown or len(used) > 1:
            raise DescriptorError(
                f"positions must use columns of one set {POSITION_COLUMNS}, got {sorted(self.positions)}"
            )
        columns: dict[str, Any] = {
            "topic": self.topic,
            "frame_index": self.frame_index,
            "log_time_ns": self.log_time_ns,
            "stamp_ns": self.stamp_ns,
            **{s: getattr(self, s) for s in SCORE_COLUMNS},
            **self.positions,
            **({} if self.moving_index is None else {"moving_index": self.moving_index}),
        }
        for name, col in columns.items():
            if len(col) != n or (isinstance(col, np.ndarray) and col.ndim != 1):
                raise DescriptorError(f"column {name} has {len(col)} values for {n} descriptors")

    def __len__(self) -> int:
        return int(self.descriptors.shape[0])

    def projected(self, pca: PatchPCA | None) -> DescriptorTable:
        """This table with its patches in ``pca``'s space: raw patches projected, patches of that
        PCA kept, patches of another PCA (or with ``pca`` None, any projected ones) dropped."""
        if self.patches is None or (pca is not None and self.patch_pca is not None
                                    and self.patch_pca.sha256 == pca.sha256):
            return self
        if pca is None or self.patch_pca is not None or self.patches.shape[2] != pca.mean.shape[0]:
            return replace(self, patches=None, patch_pca=None)
        return replace(self, patches=pca.apply(self.patches), patch_pca=pca)

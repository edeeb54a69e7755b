"""Patch features for re-ranking: what a map stores of each frame's DINOv2 patch tokens, and the
score of a (query frame, map frame) pair.

The global descriptor finds the right place among the first few candidates; the patch tokens
decide among them. Recipe (chosen by measurement on the Stromovka pair: ``docs/defaults.md``,
``benchmarks/rerank_table.py``):

* **Tokens** of a middle block (:data:`PATCH_LAYER`; the final layer's tokens match worse across
  seasons) from the same network pass as the global descriptor, CLS dropped: a 16 x 16 grid.
* **Pooled** 2 x 2 to an 8 x 8 grid (:data:`GRID`), **centred and projected** on the map's
  first :data:`PATCH_DIM` principal directions (:class:`PatchPCA`, fitted on the map's pooled
  patches and stored with it), L2-normalised, float16: 64 x 64 x 2 = 8 KiB per map frame.
* **Pair score**: the mutual nearest neighbours of the two frames' 64 patches (cosine) whose
  grid offset agrees, within one cell in x and in y, with the median offset of all the mutual
  pairs (:func:`pair_scores`): a count from 0 to 64 of patches that match *in place*, so a
  frame seen from a heading a few cells off still counts, and a frame that merely shares
  textures does not.
"""

from __future__ import annotations

import base64
import hashlib
import json
import tempfile
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from memlog.errors import DescriptorError

__all__ = ["PATCH_LAYER", "GRID", "PATCH_DIM", "PatchPCA", "PatchPCAFitter", "PatchStore", "pool_patches",
           "pair_scores"]

F32 = npt.NDArray[np.float32]
F16 = npt.NDArray[np.float16]
I64 = npt.NDArray[np.int64]

PATCH_LAYER = 7  # the middle block whose tokens the patches come from
GRID = 8  # patches per side after pooling
PATCH_DIM = 64  # dimensions kept by the PCA
PAIR_BLOCK = 256  # pairs scored per block (bounded memory)


def pool_patches(tokens: npt.ArrayLike) -> F32:
    """``[B, 1 + 256, D]`` tokens (CLS first, a 16 x 16 grid row-major) -> ``[B, 64, D]``: the
    grid averaged 2 x 2 into 8 x 8 (row-major)."""
    t = np.asarray(tokens, dtype=np.float32)
    side = int(round(np.sqrt(t.shape[1] - 1))) if t.ndim == 3 else 0
    if t.ndim != 3 or side * side != t.shape[1] - 1 or side % GRID:
        raise DescriptorError(f"tokens must be [B, 1 + n*n, D] with n a multiple of {GRID}, got {t.shape}")
    f = side // GRID
    b, _, d = t.shape
    out: F32 = t[:, 1:].reshape(b, GRID, f, GRID, f, d).mean(axis=(2, 4)).reshape(b, GRID * GRID, d)
    return np.ascontiguousarray(out, dtype=np.float32)


@dataclass(frozen=True)
class PatchPCA:
    """Centring and projection of pooled patches (``mean`` ``[D]``, ``components`` ``[dim, D]``),
    fitted on a map's patches; ``sha256`` names it (a query's patches must be projected with the
    map's own)."""

    mean: npt.NDArray[np.float64]
    components: npt.NDArray[np.float64]

    @property
    def dim(self) -> int:
        return int(self.components.shape[0])

    @property
    def sha256(self) -> str:
        h = hashlib.sha256()
        h.update(np.ascontiguousarray(self.mean, dtype=np.float64).tobytes())
        h.update(np.ascontiguousarray(self.components, dtype=np.float64).tobytes())
        return h.hexdigest()

    @classmethod
    def fit(cls, pooled: npt.ArrayLike, dim: int = PATCH_DIM) -> PatchPCA:
        """Fit on pooled patches ``[B, P, D]`` (or ``[N, D]``); at most ``dim`` directions."""
        x = np.asarray(pooled)
        fitter = PatchPCAFitter(int(x.shape[-1]))
        fitter.add(x)
        pca = fitter.fit(dim)
        if pca is None:
            raise DescriptorError("a patch PCA needs at least two patches")
        return pca

    def apply(self, pooled: npt.ArrayLike) -> F16:
        """``[B, P, D]`` pooled patches -> ``[B, P, dim]`` centred, projected, L2-normalised, float16."""
        x = np.asarray(pooled, dtype=np.float64)
        if x.shape[-1] != self.mean.shape[0]:
            raise DescriptorError(f"patches are {x.shape[-1]}-d but the patch PCA takes {self.mean.shape[0]}-d")
        y = (x - self.mean) @ self.components.T
        y /= np.maximum(np.linalg.norm(y, axis=-1, keepdims=True), 1e-12)
        out: F16 = y.astype(np.float16)
        return out

    def to_json(self) -> str:
        def enc(a: npt.NDArray[np.float64]) -> str:
            return base64.b64encode(np.ascontiguousarray(a, dtype="<f8").tobytes()).decode("ascii")

        return json.dumps({"mean": enc(self.mean), "components": enc(self.components),
                           "shape": list(self.components.shape), "sha256": self.sha256})

    @classmethod
    def from_json(cls, text: str | bytes) -> PatchPCA:
        try:
            d: dict[str, Any] = json.loads(text)
            shape = tuple(int(v) for v in d["shape"])
            mean = np.frombuffer(base64.b64decode(d["mean"]), dtype="<f8").astype(np.float64)
            comps = np.frombuffer(base64.b64decode(d["components"]), dtype="<f8").astype(np.float64).reshape(shape)
        except (ValueError, KeyError, TypeError) as exc:
            raise DescriptorError(f"the stored patch PCA does not read: {exc}") from None
        pca = cls(mean, comps)
        if d.get("sha256") != pca.sha256:
            raise DescriptorError("the stored patch PCA does not match its sha256 (the file was changed)")
        return pca


class PatchPCAFitter:
    """Fits a :class:`PatchPCA` from pooled patches added batch by batch (their first and second
    moments in float64: memory does not grow with the patches)."""

    def __init__(self, dim_in: int) -> None:
        self.n = 0
        self.sum = np.zeros(dim_in)
        self.outer = np.zeros((dim_in, dim_in))

    def add(self, pooled: npt.ArrayLike) -> None:
        x = np.asarray(pooled, dtype=np.float64)
        x = x.reshape(-1, x.shape[-1])
        if x.shape[1] != len(self.sum):
            raise DescriptorError(f"patches are {x.shape[1]}-d but the patch PCA is fitted on {len(self.sum)}-d")
        self.n += len(x)
        self.sum += x.sum(axis=0)
        self.outer += x.T @ x

    def fit(self, dim: int = PATCH_DIM) -> PatchPCA | None:
        """The PCA of the patches added (at most ``dim`` directions); None with fewer than two."""
        if self.n < 2:
            return None
        mean = self.sum / self.n
        cov = (self.outer - self.n * np.outer(mean, mean)) / (self.n - 1)
        vals, vecs = np.linalg.eigh(cov)
        order = np.argsort(vals)[::-1][: min(dim, len(mean), self.n - 1)]
        comps = vecs[:, order].T
        comps *= np.where(comps[np.arange(len(comps)), np.abs(comps).argmax(axis=1)] < 0, -1.0, 1.0)[:, None]
        return PatchPCA(mean, comps)


class PatchStore:
    """Pooled patches kept aside (float16, in a temporary file: bounded memory) until the PCA
    that projects them is known; :meth:`projected` reads them back block by block."""

    def __init__(self) -> None:
        self._file: Any = None
        self.rows = 0
        self.shape: tuple[int, int] | None = None

    def add(self, pooled: npt.ArrayLike) -> None:
        x = np.ascontiguousarray(pooled, dtype=np.float16)
        if not len(x):
            return
        if self._file is None:
            self._file = tempfile.TemporaryFile()
            self.shape = (int(x.shape[1]), int(x.shape[2]))
        if x.shape[1:] != self.shape:
            raise DescriptorError(f"patches of shape {x.shape[1:]} added to a store of {self.shape}")
        self._file.write(x.tobytes())
        self.rows += len(x)

    def projected(self, pca: PatchPCA, block: int = 256) -> F16:
        """Every stored row projected by ``pca`` (:meth:`PatchPCA.apply`), ``[rows, P, dim]``."""
        out = np.zeros((self.rows, GRID * GRID if self.shape is None else self.shape[0], pca.dim), np.float16)
        if self._file is None or self.shape is None:
            return out
        self._file.seek(0)
        per_row = self.shape[0] * self.shape[1]
        for a in range(0, self.rows, block):
            m = min(block, self.rows - a)
            raw = np.frombuffer(self._file.read(m * per_row * 2), dtype=np.float16).reshape(m, *self.shape)
            out[a : a + m] = pca.apply(raw)
        return out

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None


def pair_scores(query: npt.ArrayLike, reference: npt.ArrayLike, q_rows: npt.ArrayLike, r_rows: npt.ArrayLike
                ) -> I64:
    """Score of each pair ``(query[q_rows[n]], reference[r_rows[n]])`` of frames' patches
    (``[Nq, 64, d]``, ``[Nr, 64, d]``, L2-normalised): the count of mutual nearest neighbours
    whose grid offset lies within one cell of the pair's median offset, in x and in y."""
    q = np.asarray(query)
    r = np.asarray(reference)
    qi = np.asarray(q_rows, dtype=np.int64)
    ri = np.asarray(r_rows, dtype=np.int64)
    out = np.zeros(len(qi), dtype=np.int64)
    n_p = q.shape[1] if q.ndim == 3 else 0
    if not len(qi) or not n_p:
        return out
    cols = np.arange(n_p) % GRID
    rows = np.arange(n_p) // GRID
    for a in range(0, len(qi), PAIR_BLOCK):
        qb = q[qi[a : a + PAIR_BLOCK]].astype(np.float32)
        rb = r[ri[a : a + PAIR_BLOCK]].astype(np.float32)
        s = np.einsum("bpd,bqd->bpq", qb, rb)
        fwd = s.argmax(axis=2)  # each query patch's best map patch
        back = s.argmax(axis=1)  # each map patch's best query patch
        mutual = np.take_along_axis(back, fwd, axis=1) == np.arange(n_p)[None, :]
        dx = (cols[fwd] - cols[None, :]).astype(np.float64)
        dy = (rows[fwd] - rows[None, :]).astype(np.float64)
        dx[~mutual] = np.nan
        dy[~mutual] = np.nan
        has = mutual.any(axis=1)
        with np.errstate(all="ignore"):
            mx = np.where(has, np.nanmedian(np.where(has[:, None], dx, 0.0), axis=1), 0.0)
            my = np.where(has, np.nanmedian(np.where(has[:, None], dy, 0.0), axis=1), 0.0)
            ok = mutual & (np.abs(dx - mx[:, None]) <= 1) & (np.abs(dy - my[:, None]) <= 1)
        out[a : a + PAIR_BLOCK] = ok.sum(axis=1)
    return out

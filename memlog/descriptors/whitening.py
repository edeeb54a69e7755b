"""PCA-whitening learned from the reference drive, stored with the map, applied to every query.

A :class:`Whitening` maps a describer's L2-normalised descriptors ``x`` (``dim_in``) to
``y = normalize(((x - mean) @ proj))`` with ``dim_out`` columns, where ``proj`` holds the top
``dim_out`` principal directions of the reference descriptors, each scaled by
``1 / sqrt(eigenvalue + eps * largest eigenvalue)`` (PCA-whitening, Jégou & Chum 2012; the
``eps`` term keeps near-empty directions from being blown up). It is fitted once, when the map
is built, on every described frame of the reference drive (:class:`WhiteningFitter`
accumulates the mean and covariance in float64, so memory is ``dim_in^2`` whatever the drive's
length), stored beside the map's descriptors (Parquet schema metadata, with its sha256) and
applied unchanged to every query (:class:`WhitenedDescriber`).

Blank frames stay blank: a describer gives a frame with no information (a black or uniform image)
the zero vector, which has similarity 0 with everything (:func:`~memlog.descriptors.base.l2_normalize`,
and :mod:`~memlog.descriptors.search` ranks an all-zero query against nothing in particular).
``(0 - mean) @ proj`` is not zero, so :meth:`Whitening.apply` maps the rows the fit leaves out
(all zeros; any NaN or infinite value: :func:`blank_rows`) to zero rows instead; otherwise every
blank frame would become the same unit vector and blank queries would match blank map frames
with similarity 1. Descriptor metadata records the
transform's sha256 (:attr:`DescriptorMeta.whitening`), so a query described without it, or with
another one, is refused by :func:`~memlog.descriptors.base.check_compatible`.

Dimension rule (:func:`whitening_dim`): ``dim_out = min(max_dim, dim_in, n // 2)`` with
``max_dim = 512`` by default. The covariance of ``n`` descriptors has at most ``n - 1`` non-zero
directions and the smallest ones are noise that whitening amplifies: on the Nordland slice
(``benchmarks/desc_table.py``; summer -> winter) R@1 rose with the dimension up to about
``n / 2`` and fell near ``n``, and the DINOv2 kinds were best unreduced (384-d); so ``n // 2``
stays on the safe side of the peak (the figures: ``docs/defaults.md``). ``max_dim`` bounds the
stored transform (``dim_in x dim_out`` floats).
"""

from __future__ import annotations

import base64
import hashlib
import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from memlog.descriptors.base import Describer, DescriptorMeta, l2_normalize
from memlog.errors import DescriptorError

__all__ = [
    "Whitening",
    "WhiteningFitter",
    "WhitenedDescriber",
    "blank_rows",
    "fit_whitening",
    "whitening_dim",
    "DEFAULT_MAX_DIM",
    "DEFAULT_EPS",
    "WHITENING_VERSION",
    "MIN_SAMPLES",
]

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]

WHITENING_VERSION = "1"
#: Upper bound of the whitened dimension (see the module docstring for how it was chosen).
DEFAULT_MAX_DIM = 512
#: Regulariser: added to every eigenvalue, relative to the largest one.
DEFAULT_EPS = 1e-3
#: At least this many descriptors are needed to fit a transform (a map of a shorter drive is
#: left unwhitened, and says so).
MIN_SAMPLES = 32


def blank_rows(x: npt.NDArray[Any]) -> npt.NDArray[np.bool_]:
    """Rows of ``x`` ``[N, d]`` that carry no descriptor: all zeros (a blank frame) or with a NaN or
    infinite value. The fit leaves them out and :meth:`Whitening.apply` keeps them zero."""
    a = np.asarray(x)
    out: npt.NDArray[np.bool_] = ~(np.all(np.isfinite(a), axis=1) & np.any(a != 0, axis=1))
    return out


def whitening_dim(n_samples: int, dim_in: int, max_dim: int | None = None) -> int:
    """The whitened dimension: ``min(max_dim, dim_in, n_samples // 2)`` (at least 1)."""
    cap = DEFAULT_MAX_DIM if max_dim is None else int(max_dim)
    if cap < 1:
        raise DescriptorError(f"whitening dimension must be >= 1, got {max_dim}")
    return max(1, min(cap, int(dim_in), int(n_samples) // 2))


def _b64(a: npt.NDArray[Any]) -> str:
    return base64.b64encode(np.ascontiguousarray(a, dtype="<f4").tobytes()).decode("ascii")


def _unb64(s: str, shape: tuple[int, ...], what: str) -> F32:
    try:
        raw = base64.b64decode(s.encode("ascii"), validate=True)
    except (ValueError, UnicodeEncodeError) as exc:
        raise DescriptorError(f"whitening {what} is not valid base64: {exc}") from None
    if len(raw) != 4 * int(np.prod(shape)):
        raise DescriptorError(f"whitening {what} has {len(raw)} bytes, expected {4 * int(np.prod(shape))}")
    out: F32 = np.frombuffer(raw, dtype="<f4").astype(np.float32).reshape(shape)
    return out


@dataclass(frozen=True, eq=False)
class Whitening:
    """A fitted PCA-whitening: ``y = l2_normalize((x - mean) @ proj)``.

    ``mean`` is ``[dim_in]``, ``proj`` ``[dim_in, dim_out]`` (float32); ``n_fit`` the number of
    descriptors it was fitted on; ``eps`` the regulariser; ``source`` what it was fitted on
    (for messages). ``sha256`` identifies the transform (its arrays and settings).
    """

    mean: F32
    proj: F32
    n_fit: int
    eps: float = DEFAULT_EPS
    source: str = ""

    def __post_init__(self) -> None:
        m = np.ascontiguousarray(self.mean, dtype=np.float32)
        p = np.ascontiguousarray(self.proj, dtype=np.float32)
        if m.ndim != 1 or p.ndim != 2 or p.shape[0] != m.shape[0] or p.shape[1] < 1:
            raise DescriptorError(f"whitening mean {m.shape} and projection {p.shape} do not fit")
        if not (np.all(np.isfinite(m)) and np.all(np.isfinite(p))):
            raise DescriptorError("whitening transform holds NaN or infinite values")
        object.__setattr__(self, "mean", m)
        object.__setattr__(self, "proj", p)

    @property
    def dim_in(self) -> int:
        return int(self.mean.shape[0])

    @property
    def dim_out(self) -> int:
        return int(self.proj.shape[1])

    @property
    def sha256(self) -> str:
        """sha256 of the transform: version, sizes, eps and the float32 arrays (little-endian)."""
        h = hashlib.sha256()
        h.update(f"memlog-whitening-{WHITENING_VERSION}:{self.dim_in}:{self.dim_out}:{self.eps!r}:".encode())
        h.update(np.ascontiguousarray(self.mean, dtype="<f4").tobytes())
        h.update(np.ascontiguousarray(self.proj, dtype="<f4").tobytes())
        return h.hexdigest()

    def apply(self, x: npt.ArrayLike) -> F32:
        """Whitened, L2-normalised descriptors ``[N, dim_out]`` of ``x`` ``[N, dim_in]``; a blank
        row (:func:`blank_rows`: all zeros, or NaN/inf) gives a zero row, as before whitening."""
        a = np.asarray(x, dtype=np.float32)
        if a.ndim != 2 or a.shape[1] != self.dim_in:
            raise DescriptorError(f"whitening expects [N, {self.dim_in}] descriptors, got shape {a.shape}")
        blank = blank_rows(a)
        y = (np.where(blank[:, None], self.mean, a) - self.mean) @ self.proj  # blank rows: exactly 0
        return l2_normalize(y)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict (arrays as base64 little-endian float32), with the sha256."""
        return {"version": WHITENING_VERSION, "dim_in": self.dim_in, "dim_out": self.dim_out, "eps": self.eps,
                "n_fit": self.n_fit, "source": self.source, "mean": _b64(self.mean), "proj": _b64(self.proj),
                "sha256": self.sha256}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "Whitening":
        """Inverse of :meth:`to_dict`; :class:`DescriptorError` when it is malformed or its
        arrays do not hash to the recorded sha256 (a damaged or edited transform)."""
        try:
            if str(d["version"]) != WHITENING_VERSION:
                raise DescriptorError(f"whitening version {d['version']} is not supported "
                                      f"(this memlog reads version {WHITENING_VERSION})")
            din, dout = int(d["dim_in"]), int(d["dim_out"])
            w = cls(_unb64(str(d["mean"]), (din,), "mean"), _unb64(str(d["proj"]), (din, dout), "projection"),
                    int(d["n_fit"]), float(d["eps"]), str(d.get("source", "")))
            recorded = str(d["sha256"])
        except (KeyError, TypeError, ValueError) as exc:
            raise DescriptorError(f"invalid whitening transform: {exc}") from None
        if w.sha256 != recorded:
            raise DescriptorError(f"whitening transform does not match its sha256 (recorded {recorded[:12]}…, "
                                  f"computed {w.sha256[:12]}…): the map's descriptor file is damaged or was edited")
        return w

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), sort_keys=True)

    def describe(self) -> str:
        """One line for messages."""
        return f"PCA-whitening {self.dim_in}->{self.dim_out}-d fitted on {self.n_fit} frames (sha256 {self.sha256[:12]}…)"


class WhiteningFitter:
    """Accumulates descriptors batch by batch and fits. While fewer descriptors than ``dim_in``
    were added they are kept (at most ``dim_in^2`` floats) and the fit diagonalises their
    ``N x N`` Gram matrix (the same principal directions, far cheaper for long descriptors such as
    thumbnails); beyond that the float64 sums (``dim_in^2`` memory) and the ``dim_in x dim_in``
    covariance."""

    def __init__(self, dim_in: int) -> None:
        self.dim_in = int(dim_in)
        self.n = 0
        self._sum = np.zeros(self.dim_in)
        self._rows: list[npt.NDArray[np.float64]] | None = []
        self._outer: npt.NDArray[np.float64] | None = None

    def add(self, x: npt.ArrayLike) -> None:
        """Add descriptors ``[N, dim_in]`` (rows with NaN or all zeros are left out)."""
        a = np.asarray(x, dtype=np.float64)
        if a.ndim != 2 or a.shape[1] != self.dim_in:
            raise DescriptorError(f"whitening fit expects [N, {self.dim_in}] descriptors, got shape {a.shape}")
        a = a[~blank_rows(a)]
        self.n += a.shape[0]
        self._sum += a.sum(axis=0)
        if self._rows is not None:
            self._rows.append(a)
            if self.n < self.dim_in:
                return
            a = np.concatenate(self._rows)  # as many rows as dimensions: the sums from here on
            self._rows = None
            self._outer = np.zeros((self.dim_in, self.dim_in))
        assert self._outer is not None
        self._outer += a.T @ a

    @property
    def enough(self) -> bool:
        """Whether enough descriptors were added to fit (:data:`MIN_SAMPLES`)."""
        return self.n >= MIN_SAMPLES

    def fit_or_none(self, max_dim: int | None = None, source: str = "") -> Whitening | None:
        """:meth:`fit`, or None when fewer than :data:`MIN_SAMPLES` descriptors were added."""
        return self.fit(max_dim, source=source) if self.enough else None

    def fit(self, max_dim: int | None = None, eps: float = DEFAULT_EPS, source: str = "") -> Whitening:
        """The transform of the descriptors added so far (:func:`whitening_dim` columns)."""
        if self.n < MIN_SAMPLES:
            raise DescriptorError(f"whitening needs at least {MIN_SAMPLES} described frames, got {self.n}; "
                                  "map more frames or turn whitening off (--no-whiten)")
        if not (np.isfinite(eps) and eps >= 0):
            raise DescriptorError(f"whitening eps must be >= 0, got {eps}")
        mean = self._sum / self.n
        k = whitening_dim(self.n, self.dim_in, max_dim)
        got = self._dual(mean, k) if self._rows is not None else None
        if got is None:
            vals, vecs = self._primal(mean)
        else:
            vals, vecs = got
        # a deterministic sign for each direction (eigh's signs are arbitrary): largest entry positive
        vecs = vecs[:, :k]
        signs = np.sign(vecs[np.argmax(np.abs(vecs), axis=0), np.arange(vecs.shape[1])])
        vecs = vecs * np.where(signs == 0, 1.0, signs)
        scale = 1.0 / np.sqrt(vals[:k] + eps * max(float(vals[0]), 1e-12))
        return Whitening(mean.astype(np.float32), (vecs * scale).astype(np.float32), self.n, float(eps), source)

    def _primal(self, mean: npt.NDArray[np.float64]) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """Eigenvalues (descending, >= 0) and eigenvectors of the ``dim_in x dim_in`` covariance."""
        outer = self._outer
        if outer is None:
            rows = np.concatenate(self._rows or [np.zeros((0, self.dim_in))])
            outer = rows.T @ rows
        cov = outer / self.n - np.outer(mean, mean)
        vals, vecs = np.linalg.eigh((cov + cov.T) / 2.0)
        order = np.argsort(vals)[::-1]
        return np.clip(vals[order], 0.0, None), vecs[:, order]

    def _dual(self, mean: npt.NDArray[np.float64], k: int
              ) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]] | None:
        """The top ``k`` eigenpairs of the covariance from the Gram matrix of the kept rows; None
        when one of them is (numerically) zero, where only the full covariance defines a direction."""
        xc = np.concatenate(self._rows or []) - mean
        gram = xc @ xc.T / self.n
        vals, u = np.linalg.eigh((gram + gram.T) / 2.0)
        order = np.argsort(vals)[::-1][:k]
        vals, u = vals[order], u[:, order]
        if k == 0 or vals[-1] <= 1e-9 * max(float(vals[0]), 1e-300):
            return None
        vecs = xc.T @ u / np.sqrt(self.n * vals)
        return vals, vecs


def fit_whitening(x: npt.ArrayLike, max_dim: int | None = None, eps: float = DEFAULT_EPS, source: str = "") -> Whitening:
    """Fit a :class:`Whitening` on descriptors ``x`` ``[N, dim_in]`` in one go."""
    a = np.asarray(x, dtype=np.float32)
    if a.ndim != 2:
        raise DescriptorError(f"descriptors must be [N, dim], got shape {a.shape}")
    f = WhiteningFitter(a.shape[1])
    f.add(a)
    return f.fit(max_dim, eps, source)


class WhitenedDescriber(Describer):
    """A describer followed by a fitted whitening: same kind, params and model; ``dim`` is the
    whitened dimension and the metadata records the transform's sha256."""

    def __init__(self, base: Describer, whitening: Whitening) -> None:
        if whitening.dim_in != base.dim:
            raise DescriptorError(f"whitening expects {whitening.dim_in}-d descriptors but {base.kind} gives {base.dim}-d")
        self.base = base
        self.whitening = whitening
        self.kind = base.kind
        self.version = base.version
        self.dim = whitening.dim_out
        self.model_sha256 = base.model_sha256

    @property
    def params(self) -> dict[str, Any]:
        return dict(self.base.params)

    def meta(self) -> DescriptorMeta:
        return DescriptorMeta(self.kind, self.version, self.dim, self.model_sha256, dict(self.params),
                              whitening=self.whitening.sha256)

    def describe(self, images_bgr: Sequence[npt.NDArray[Any]]) -> F32:
        return self.whitening.apply(self.base.describe(images_bgr))

    @property
    def gives_patches(self) -> bool:
        return self.base.gives_patches

    def describe_patches(self, images_bgr: Sequence[npt.NDArray[Any]]) -> tuple[F32, F32 | None]:
        desc, patches = self.base.describe_patches(images_bgr)
        return self.whitening.apply(desc), patches

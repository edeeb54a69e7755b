"""Local Shannon entropy (the paper's entropy map E) and the entropy score ES.

:func:`entropy_map` returns what ``skimage.filters.rank.entropy(gray, disk(radius))`` returns
(to ~1e-14): for every pixel, the Shannon entropy in bits (log2) of the histogram of the grey
values under a disk footprint, counting only the neighbours inside the image (the histogram
of an edge pixel has fewer than ``disk(radius).sum()`` entries).

scikit-image evaluates all 256 bins at every pixel. Here the histograms slide along the
columns, vectorised over all rows and a few column strips at once, with numpy only:

* each histogram has one extra bin for "outside the image", so borders need no special case
  while sliding; its count ``c_out`` is taken out at the end;
* moving the disk one column changes 2 x (2r + 1) bins; each change reads the bin's count
  (``ndarray.take``) and writes it back (fancy assignment), and the count it saw is recorded
  (uint8). ``T = sum_b f(c_b)``, ``f(c) = c log2 c``, then follows from the recorded counts
  through one table ``g(k) = f(k + 1) - f(k)`` and a cumulative sum along the columns;
* ``E = (f(n) - T + f(c_out)) / n = log2 n - sum_b (c_b / n) log2 c_b`` with ``n`` the number
  of in-image neighbours.

The histograms are exact integers, so the map equals scikit-image's up to float rounding
(the tests require <= 1e-9). The cost is set by numpy's fancy indexing, ~3 ns per bin
change: 22 changes x 1.29 M pixels at 1135 x 1135, about 0.14 s on one core against
0.6-0.9 s for scikit-image (which evaluates 256 bins x 1.29 M pixels).

**The compiled kernel.** ``memlog/scoring/_entropy.c`` slides one histogram along each row in
plain C (about 0.04 s per 1135 x 1135 frame on one core, a third of the numpy path). It is built
when memlog is installed with a C compiler (``setup.py``; optional: the install goes on without
one) and loaded with ctypes, which releases the GIL, so threads score frames in parallel.
:func:`entropy_kernel` says which implementation runs: ``"c"`` when the kernel is built, else
``"numpy"``; the runtime context's ``entropy_kernel`` (:mod:`memlog.runtime`; the command line and
the API take it from ``MEMLOG_ENTROPY_KERNEL``) set to ``"numpy"`` forces the numpy path (for
comparisons). Both give the same histograms; their maps differ only by float rounding (< 1e-12).
"""

from __future__ import annotations

import ctypes
import functools
import importlib.machinery
import logging
import math
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any, Literal, TypeVar

import cv2
import numpy as np
import numpy.typing as npt
from numpy.lib.stride_tricks import as_strided

from memlog.errors import ScoringError
from memlog.runtime import ENTROPY_KERNELS, current

__all__ = ["entropy_map", "entropy_score", "Entropy", "disk_footprint", "entropy_kernel", "KERNELS"]

log = logging.getLogger(__name__)
T = TypeVar("T")

#: The implementations of :func:`entropy_map` (``"auto"``: the compiled one when it is built).
KERNELS = ENTROPY_KERNELS
_KERNEL_VERSION = 1

_OUT = 256  # the histogram bin of pixels outside the image
_NB = 257  # bins per histogram: 256 grey values + outside


@functools.cache
def _compiled() -> Any | None:
    """The compiled kernel's row function (None when it is not built or does not load)."""
    here = Path(__file__).resolve().parent
    for suffix in importlib.machinery.EXTENSION_SUFFIXES:
        path = here / f"_entropy{suffix}"
        if not path.is_file():
            continue
        try:
            lib = ctypes.CDLL(str(path))
            if lib.memlog_entropy_version() != _KERNEL_VERSION:
                log.warning("%s is of another memlog version; reinstall memlog (pip install -e .): "
                            "entropy falls back to numpy", path)
                return None
            fn = lib.memlog_entropy_rows
        except (OSError, AttributeError) as exc:
            log.warning("could not load the compiled entropy kernel %s (%s): entropy falls back to numpy", path, exc)
            return None
        i64, ptr = ctypes.c_int64, ctypes.c_void_p
        fn.argtypes = [ptr, i64, i64, i64, ptr, ptr, ptr, i64, i64, ptr]
        fn.restype = None
        return fn
    log.info("memlog's compiled entropy kernel is not built (install memlog with a C compiler present): "
             "entropy is computed with numpy, about three times slower")
    return None


def entropy_kernel(kernel: str = "auto") -> Literal["c", "numpy"]:
    """Which implementation :func:`entropy_map` runs for ``kernel`` (see :data:`KERNELS`):
    ``"c"`` when the compiled kernel is built (and not turned off by the runtime context's
    ``entropy_kernel``, :func:`memlog.runtime.current`: ``MEMLOG_ENTROPY_KERNEL=numpy``), else
    ``"numpy"``. ``kernel="c"`` without the compiled kernel is a :class:`ScoringError`."""
    if kernel not in KERNELS:
        raise ScoringError(f"entropy kernel must be one of {', '.join(KERNELS)}, got {kernel!r}")
    if kernel == "auto":
        forced = current().entropy_kernel  # ("auto" unless the context asks for one)
        kernel = forced if forced in ("c", "numpy") else ("c" if _compiled() is not None else "numpy")
    if kernel == "c" and _compiled() is None:
        raise ScoringError("memlog's compiled entropy kernel is not built (it needs a C compiler when memlog is "
                           "installed: pip install -e . with gcc or clang present); use the numpy kernel")
    return "c" if kernel == "c" else "numpy"


def _rows_c(pad: npt.NDArray[np.uint16], hgt: int, wid: int, r: int, hw: npt.NDArray[np.int64],
            f: npt.NDArray[np.float64], g: npt.NDArray[np.float64], i0: int, i1: int,
            out: npt.NDArray[np.float64]) -> None:
    """Rows i0..i1-1 of the map into ``out`` (a C-contiguous view of those rows), by the kernel."""
    fn = _compiled()
    assert fn is not None
    fn(pad.ctypes.data, hgt, wid, r, hw.ctypes.data, f.ctypes.data, g.ctypes.data, i0, i1, out.ctypes.data)


def disk_footprint(radius: int) -> npt.NDArray[np.uint8]:
    """The disk footprint of ``skimage.morphology.disk(radius)``: ``x^2 + y^2 <= radius^2``."""
    r = _check_radius(radius)
    hw = _half_widths(r)
    fp = np.zeros((2 * r + 1, 2 * r + 1), np.uint8)
    for d, w in enumerate(hw):
        fp[d, r - w : r + w + 1] = 1
    return fp


def _check_radius(radius: int) -> int:
    if isinstance(radius, bool) or not isinstance(radius, (int, np.integer)) or radius < 0:
        raise ScoringError(f"entropy radius must be a non-negative integer, got {radius!r}")
    return int(radius)


def _half_widths(r: int) -> list[int]:
    """Half width of each footprint row dy = -r..r (exact integer square roots)."""
    return [math.isqrt(r * r - dy * dy) for dy in range(-r, r + 1)]


def _check_gray(gray: Any) -> npt.NDArray[np.uint8]:
    if not isinstance(gray, np.ndarray):
        raise ScoringError(f"entropy_map expects a numpy array, got {type(gray).__name__}")
    if gray.ndim != 2:
        raise ScoringError(
            f"entropy_map expects a 2-D HxW uint8 grey image, got shape {gray.shape} "
            "(convert BGR with cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY))"
        )
    if gray.dtype != np.uint8:
        raise ScoringError(f"entropy_map expects dtype uint8, got {gray.dtype}")
    if gray.shape[0] < 1 or gray.shape[1] < 1:
        raise ScoringError(f"entropy_map got an empty image of shape {gray.shape}")
    return gray


def _band_sums(
    pt: npt.NDArray[np.uint16],
    hw: list[int],
    lpad: int,
    wk: int,
    k: int,
    i0: int,
    i1: int,
    f: npt.NDArray[np.float64],
    g: npt.NDArray[np.float64],
) -> npt.NDArray[np.float64]:
    """``T = sum_b f(c_b)`` (outside bin included) for image rows i0..i1-1.

    ``pt`` is the transposed image padded with the outside value: ``pt[lpad + x, r + y]`` is
    pixel (y, x). Strip s covers columns s*wk .. s*wk + wk - 1. Returns a view of shape
    (wk, k, i1 - i0): column offset in the strip (step), strip, row.
    """
    r = len(hw) // 2
    nrows = 2 * r + 1
    h = i1 - i0
    hp = h + 2 * r  # padded rows of a strip
    nl = k * hp - 2 * r  # lanes swept: the k*h real ones and 2r between strips (ignored)
    nfp = sum(2 * w + 1 for w in hw)
    cdt = np.uint8 if nfp < 255 else np.uint16

    # Histograms are bin-major, ``hist[v * lanes + l]``: rows next to each other mostly see
    # close grey values, so their bin changes land on nearby bytes (~20 % faster on frames).
    # Index table: q[c - cmin, s*hp + p] = value * lanes + s*hp + p for padded row p of strip
    # s at column s*wk + c. Lane l (strip l // hp, row l % hp) reads footprint row d at
    # q[., l + d]; the histogram view shifted by -d undoes the +d, so every bin change is one
    # take and one assignment on a slice of q, with no index arithmetic in the loop.
    cmin = -r  # leftmost column offset read: the first disks and the first removals
    ncols = wk + r - cmin
    lanes = k * hp
    rs, cs = pt.strides
    pix = as_strided(pt[lpad + cmin :, i0:], shape=(ncols, k, hp), strides=(rs, wk * rs, cs))
    q = np.multiply(pix, lanes, dtype=np.intp)
    q += np.arange(lanes, dtype=np.intp).reshape(k, hp)
    q = q.reshape(ncols, lanes)

    # Histograms of the disks centred at column 0 of every strip, in one bincount.
    first = [q[dx - cmin, d : d + nl] + (2 * r - d) for d, w in enumerate(hw) for dx in range(-w, w + 1)]
    hist = np.bincount(np.concatenate(first), minlength=_NB * lanes + 2 * r).astype(cdt)
    del first
    dt = np.empty((wk, lanes), np.float64)
    dt[:, nl:] = 0.0
    h2 = hist[2 * r : 2 * r + _NB * lanes].reshape(_NB, lanes)[:, :nl]
    dt[0, :nl] = (cv2.LUT(h2, f[:256]) if cdt == np.uint8 else f.take(h2)).sum(axis=0)  # type: ignore[arg-type]

    views = [hist[2 * r - d :] for d in range(nrows)]
    # The methods: np.take's Python wrapper costs ~1 us a call. Indices are in range by
    # construction (q <= 257 * lanes - 1, view offset <= 2r), so mode="wrap" never wraps; it
    # only skips the buffered bounds check of mode="raise" (~8 % of the total).
    takes = [v.take for v in views]
    puts = [v.__setitem__ for v in views]
    rec = np.empty((2 * nrows, nl), cdt)
    rec_rem = list(rec[:nrows])
    rec_ins = list(rec[nrows:])
    gv = np.empty((2 * nrows, nl), np.float64)
    sign = np.repeat(np.array([-1.0, 1.0]), nrows)
    tmp = np.empty(nl, cdt)
    one = cdt(1)
    # step t (centre moves to column t): row d loses column t - w - 1 and gains column t + w
    rem_row = [-w - 1 - cmin for w in hw]
    ins_row = [w - cmin for w in hw]
    rows = range(nrows)
    sub = np.subtract
    add = np.add
    dot = np.dot
    for t in range(1, wk):
        for d in rows:
            ix = q[t + rem_row[d], d : d + nl]
            takes[d](ix, out=tmp, mode="wrap")
            sub(tmp, one, out=rec_rem[d])  # removal: record the count after
            puts[d](ix, rec_rem[d])
        for d in rows:
            ix = q[t + ins_row[d], d : d + nl]
            takes[d](ix, out=rec_ins[d], mode="wrap")  # insertion: record the count before
            add(rec_ins[d], one, out=tmp)
            puts[d](ix, tmp)
        if cdt == np.uint8:
            cv2.LUT(rec, g, dst=gv)
        else:
            g.take(rec, out=gv)
        dot(sign, gv, out=dt[t, :nl])  # sum over insertions - sum over removals
    np.cumsum(dt, axis=0, out=dt)
    return dt.reshape(wk, k, hp)[:, :, :h]


def entropy_map(gray: npt.NDArray[np.uint8], radius: int = 5, *, workers: int = 1,
                kernel: str = "auto") -> npt.NDArray[np.float64]:
    """Local Shannon entropy (bits) of a 2-D uint8 image under ``disk(radius)``.

    Equals ``skimage.filters.rank.entropy(gray, skimage.morphology.disk(radius))`` (float64,
    0..8 bits; out-of-image neighbours are not counted). ``workers > 1`` splits the rows
    between threads, which helps only when a core is free; the default 1 leaves the other
    core to the other stages. ``kernel``: ``"auto"`` (the compiled kernel when it is built),
    ``"c"`` or ``"numpy"`` (:func:`entropy_kernel`).
    """
    gray = _check_gray(gray)
    r = _check_radius(radius)
    if isinstance(workers, bool) or not isinstance(workers, (int, np.integer)) or workers < 1:
        raise ScoringError(f"workers must be a positive integer, got {workers!r}")
    which = entropy_kernel(kernel)
    hgt, wid = gray.shape
    if r == 0:
        return np.zeros((hgt, wid), np.float64)
    hw = _half_widths(r)
    nfp = sum(2 * w + 1 for w in hw)
    if nfp >= 65535:
        raise ScoringError(f"entropy radius {r} is too large (footprint of {nfp} pixels)")
    if which == "c":
        return _entropy_map_c(gray, r, hw, nfp, int(workers))

    # Column strips: more lanes per numpy call, fewer Python-level steps (~5600 lanes is
    # best measured at 1135 x 1135, where k = 5 also divides the width).
    k = max(1, min(8, wid // 128, (5600 + hgt // 2) // hgt))
    wk = -(-wid // k)
    lpad = r
    pt = np.full((wk * k + 2 * lpad, hgt + 2 * r), _OUT, np.uint16)
    pt[lpad : lpad + wid, r : r + hgt] = gray.T

    f, g = _tables(nfp)

    parts = _by_bands(hgt, workers, lambda i0, i1: _band_sums(pt, hw, lpad, wk, k, i0, i1, f, g))
    t = parts[0] if len(parts) == 1 else np.concatenate(parts, axis=2)
    # E = log2 n - T / n = (f(n) - T) / n: exactly 0 for a one-value histogram.
    # Interior: n = nfp neighbours, outside bin empty. t is (step, strip, row).
    out = np.empty((hgt, wid), np.float64)
    for s in range(k):
        c0, c1 = s * wk, min(wid, (s + 1) * wk)
        np.subtract(f[nfp], t[: c1 - c0, s, :].T, out=out[:, c0:c1])
    out *= 1.0 / nfp
    # Border bands (within r of an edge): n < nfp, and the outside bin's f(c_out) goes.
    rv, cv = _inside_factors(hgt, wid, hw)  # n = rv @ cv
    rows = np.unique(np.r_[0 : min(r, hgt), max(0, hgt - r) : hgt])
    cols = np.unique(np.r_[0 : min(r, wid), max(0, wid - r) : wid])
    nb = rv[rows] @ cv
    tb = t[:, :, rows].transpose(2, 1, 0).reshape(len(rows), k * wk)[:, :wid]
    out[rows, :] = (f[nb] - tb + f[nfp - nb]) / nb
    nb = rv @ cv[:, cols]
    tb = t[cols % wk, cols // wk, :].T
    out[:, cols] = (f[nb] - tb + f[nfp - nb]) / nb
    # A histogram with one value has entropy 0; any other has >= 1e-4 bits (n <= 65535),
    # so values below 1e-9 are float residue of an exact 0.
    out[out < 1e-9] = 0.0
    return out


def _tables(nfp: int) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """``f(k) = k log2 k`` and ``g(k) = f(k + 1) - f(k)`` for k = 0..max(nfp + 1, 255)."""
    c = np.arange(max(nfp + 2, 256), dtype=np.float64)
    f = np.zeros_like(c)
    f[1:] = c[1:] * np.log2(c[1:])
    g = np.zeros_like(c)
    g[:-1] = f[1:] - f[:-1]
    return f, g


def _entropy_map_c(gray: npt.NDArray[np.uint8], r: int, hw: list[int], nfp: int, workers: int
                   ) -> npt.NDArray[np.float64]:
    """:func:`entropy_map` by the compiled kernel, rows split between ``workers`` threads."""
    hgt, wid = gray.shape
    pad = np.full((hgt + 2 * r, wid + 2 * r), _OUT, np.uint16)
    pad[r : r + hgt, r : r + wid] = gray
    hwa = np.asarray(hw, np.int64)
    f, g = _tables(nfp)
    out = np.empty((hgt, wid), np.float64)
    _by_bands(hgt, workers, lambda i0, i1: _rows_c(pad, hgt, wid, r, hwa, f, g, i0, i1, out[i0:i1]))
    return out


def _by_bands(hgt: int, workers: int, work: Callable[[int, int], T]) -> list[T]:
    """``work(i0, i1)`` on bands of rows covering 0..hgt-1, in order: one band, or up to ``workers``
    bands of at least 64 rows on as many threads (both kernels release the GIL in their loops)."""
    nw = int(min(workers, max(1, hgt // 64)))
    if nw == 1:
        return [work(0, hgt)]
    cuts = np.linspace(0, hgt, nw + 1).astype(int)
    with ThreadPoolExecutor(nw) as ex:
        return list(ex.map(lambda ab: work(int(ab[0]), int(ab[1])), zip(cuts[:-1], cuts[1:])))


def _inside_factors(hgt: int, wid: int, hw: list[int]) -> tuple[npt.NDArray[np.intp], npt.NDArray[np.intp]]:
    """Factors of the in-image neighbour count: ``n[i, j] = (rv @ cv)[i, j]``.

    ``rv[i, d]`` is 1 when footprint row d of pixel row i is inside the image, ``cv[d, j]``
    the number of in-image columns of that footprint row around column j.
    """
    r = len(hw) // 2
    rows = np.arange(hgt)[:, None] + (np.arange(2 * r + 1) - r)[None, :]
    rv = ((rows >= 0) & (rows < hgt)).astype(np.intp)
    cols = np.arange(wid)[None, :]
    w = np.asarray(hw, np.intp)[:, None]
    cv = (np.minimum(cols + w, wid - 1) - np.maximum(cols - w, 0) + 1).astype(np.intp)
    return rv, cv


def entropy_score(
    emap: npt.NDArray[np.floating[Any]],
    static_map: npt.NDArray[Any] | None = None,
) -> float:
    """ES = sum(E * S) / (H * W * 8): mean entropy in bits / 8, dynamic pixels counting 0.

    ``static_map`` (1 = static, 0 = dynamic, same HxW as ``emap``) may be None (all static).
    """
    if not isinstance(emap, np.ndarray) or emap.ndim != 2:
        shape = getattr(emap, "shape", None)
        raise ScoringError(f"entropy_score expects a 2-D HxW entropy map, got shape {shape}")
    if emap.size == 0:
        raise ScoringError("entropy_score got an empty entropy map")
    e = emap.astype(np.float64, copy=False)
    if static_map is None:
        return float(e.sum() / (e.size * 8.0))
    if not isinstance(static_map, np.ndarray) or static_map.shape != emap.shape:
        shape = getattr(static_map, "shape", None)
        raise ScoringError(f"static map shape {shape} does not match entropy map shape {emap.shape}")
    return float(np.einsum("ij,ij->", e, static_map.astype(np.float64, copy=False)) / (e.size * 8.0))


class Entropy:
    """Entropy map of a grey frame: ``Entropy(5)(gray) -> HxW float64`` (bits)."""

    def __init__(self, radius: int = 5, *, workers: int = 1, kernel: str = "auto") -> None:
        self.radius = _check_radius(radius)
        self.workers = workers
        self.kernel = entropy_kernel(kernel)

    def __call__(self, gray: npt.NDArray[np.uint8]) -> npt.NDArray[np.float64]:
        return entropy_map(gray, self.radius, workers=self.workers, kernel=self.kernel)

    def __repr__(self) -> str:
        return f"Entropy(radius={self.radius}, workers={self.workers}, kernel={self.kernel!r})"

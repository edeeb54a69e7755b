"""Approximate nearest-neighbour search for big maps: a FAISS inverted-file index (optional extra).

``memlog[faiss]`` installs ``faiss-cpu``. The index is IVF with 8-bit scalar-quantised vectors
(``IndexIVFScalarQuantizer``, inner product): the map is split into ``nlist`` cells by k-means
(trained on ``16 * nlist`` map frames spread evenly over the map), a query scans the ``nprobe``
cells whose centres are most similar to it, and the ``rerank`` best candidates of that scan are
scored again exactly (float64, like :func:`memlog.descriptors.search.match`), so the returned
similarities are exact and only the set of candidates is approximate. The index holds one byte
per descriptor value (a quarter of the float32 map).

:func:`choose` picks exact or approximate search: ``auto`` takes the index when FAISS is
installed, the map has at least :data:`AUTO_MIN_FRAMES` frames and there are at least
``4 * nlist`` queries (building the index then costs well under the exact search it saves;
measured in ``benchmarks/search_bench.py``), and exact search otherwise.
"""

from __future__ import annotations

import importlib
import math
from dataclasses import dataclass
from types import ModuleType

import numpy as np
import numpy.typing as npt

from memlog.configfile import check_ints
from memlog.descriptors.search import F32, I64, Database, _best, _empty, _queries, _rescore
from memlog.errors import ConfigError, DescriptorError
from memlog.progress import info
from memlog.settings import Flag, positive_int, setting

__all__ = ["SEARCH_METHODS", "AUTO_MIN_FRAMES", "SearchConfig", "IVFIndex", "choose", "faiss_module",
           "default_nlist", "default_nprobe"]

SEARCH_METHODS = ("auto", "exact", "ivf")
AUTO_MIN_FRAMES = 100_000  # auto considers the approximate index from this map size
TRAIN_PER_CELL = 16  # k-means training frames per cell
MISSING = "the approximate index needs FAISS: pip install 'memlog[faiss]' (or faiss-cpu)"


def faiss_module() -> ModuleType | None:
    """The ``faiss`` module, or None when the ``memlog[faiss]`` extra is not installed."""
    try:
        return importlib.import_module("faiss")
    except ImportError:
        return None


def default_nlist(n_refs: int) -> int:
    """Cells of the index: the power of two nearest ``4 * sqrt(n_refs)``, at least 1, at most ``n_refs``."""
    if n_refs < 1:
        return 1
    return max(1, min(n_refs, 1 << round(math.log2(4 * math.sqrt(n_refs)))))


def default_nprobe(nlist: int) -> int:
    """Cells scanned per query: ``nlist / 64``, at least 16 (measured recall against exact search: see
    ``benchmarks/search_bench.py`` and ``docs/benchmarks.md``)."""
    return min(nlist, max(16, nlist // 64))


@dataclass(frozen=True)
class SearchConfig:
    """How to search the map: ``method`` auto | exact | ivf; IVF ``nlist``/``nprobe``/``rerank``
    (None: the defaults for the map's size)."""

    method: str = setting("auto", Flag(
        ("--search",), "exact search, or ivf: an approximate FAISS index (needs memlog[faiss]); auto (default): ivf "
        "for maps of >= 100,000 frames with >= 4 x nlist query frames when FAISS is installed", "performance",
        choices=SEARCH_METHODS, default="auto"))
    nlist: int | None = setting(None, Flag(("--nlist",), "ivf: cells of the index (default: ~4 sqrt(map frames))",
                                           "performance", positive_int, metavar="N"))
    nprobe: int | None = setting(None, Flag(("--nprobe",), "ivf: cells scanned per query (default: nlist / 64, "
                                            ">= 16)", "performance", positive_int, metavar="N"))
    rerank: int | None = None

    def __post_init__(self) -> None:
        if self.method not in SEARCH_METHODS:
            raise ConfigError(f"search must be one of {', '.join(SEARCH_METHODS)}, got {self.method!r}")
        check_ints(self, {"nlist": 1, "nprobe": 1, "rerank": 1}, optional=True)
        if self.method == "exact" and (self.nlist or self.nprobe or self.rerank):
            raise ConfigError("nlist/nprobe/rerank set the approximate index; they do not apply to exact search")

    def require_faiss(self) -> None:
        """ConfigError now (before any work) when ``ivf`` was asked for and FAISS is missing."""
        if self.method == "ivf" and faiss_module() is None:
            raise ConfigError(f"--search ivf: {MISSING}")


def choose(cfg: SearchConfig, n_refs: int, n_queries: int) -> str:
    """``"exact"`` or ``"ivf"`` for a map of ``n_refs`` frames and ``n_queries`` queries (see module doc)."""
    if cfg.method != "auto":
        if cfg.method == "ivf" and faiss_module() is None:
            raise ConfigError(f"--search ivf: {MISSING}")
        return cfg.method
    nlist = cfg.nlist or default_nlist(n_refs)
    if n_refs < AUTO_MIN_FRAMES or n_queries < 4 * nlist:
        return "exact"
    if faiss_module() is None:
        info(f"exact search of {n_refs} map frames; {MISSING} to search big maps faster")
        return "exact"
    return "ivf"


class IVFIndex:
    """A FAISS IVF-SQ8 index over a :class:`Database` (see the module doc)."""

    def __init__(self, db: Database, nlist: int | None = None, *, seed: int = 1234) -> None:
        faiss = faiss_module()
        if faiss is None:
            raise ConfigError(MISSING)
        n, dim = db.rows.shape
        if n == 0:
            raise DescriptorError("cannot build an index of an empty map")
        self.db = db
        self.nlist = min(n, nlist or default_nlist(n))
        quantizer = faiss.IndexFlatIP(dim)
        index = faiss.IndexIVFScalarQuantizer(quantizer, dim, self.nlist, faiss.ScalarQuantizer.QT_8bit,
                                              faiss.METRIC_INNER_PRODUCT)
        index.cp.seed = seed
        index.cp.min_points_per_centroid = 1  # we choose the training size; no warning
        train = np.unique(np.linspace(0, n - 1, min(n, TRAIN_PER_CELL * self.nlist)).astype(np.int64))
        index.train(np.ascontiguousarray(db.rows[train]))
        step = max(1, (1 << 24) // max(1, dim))  # add in 64 MiB slices
        for s in range(0, n, step):
            index.add(np.ascontiguousarray(db.rows[s : s + step]))
        self._quantizer = quantizer  # the index refers to it
        self.index = index

    def settings(self, k: int, nprobe: int | None = None, rerank: int | None = None) -> tuple[int, int]:
        """The ``(nprobe, rerank)`` a search for ``k`` neighbours uses (defaults filled in)."""
        n = self.db.rows.shape[0]
        return min(self.nlist, nprobe or default_nprobe(self.nlist)), min(n, max(k, rerank or max(40, 4 * k)))

    def search(self, query: npt.ArrayLike, k: int, nprobe: int | None = None,
               rerank: int | None = None) -> tuple[I64, F32]:
        """The ``k`` best map rows per query (``(indices, similarities)`` like ``match``).

        ``nprobe`` cells are scanned (default :func:`default_nprobe`); the ``rerank`` best
        candidates (default ``max(40, 4 k)``) are scored exactly and the best ``k`` kept.
        """
        if k < 1:
            raise DescriptorError(f"k must be >= 1, got {k}")
        q, _norms = _queries(query)
        if q.shape[0] and q.shape[1] != self.db.rows.shape[1]:
            raise DescriptorError(f"query descriptors are {q.shape[1]}-d but references are "
                                  f"{self.db.rows.shape[1]}-d")
        n = self.db.rows.shape[0]
        kk = min(k, n)
        self.index.nprobe, kc = self.settings(k, nprobe, rerank)
        indices, sims = _empty(q.shape[0], k)
        if q.shape[0] == 0:
            return indices, sims
        _d, cand = self.index.search(q, kc)
        rows = np.repeat(np.arange(q.shape[0], dtype=np.int64), kc)
        cols = cand.astype(np.int64).ravel()
        found = cols >= 0  # FAISS pads with -1 when the scanned cells hold fewer than kc frames
        rows, cols = rows[found], cols[found]
        counts = np.bincount(rows, minlength=q.shape[0])
        vals = _rescore(q, self.db.rows, rows, cols)
        if counts.min() < kk:  # a query whose cells hold fewer than k frames: pad with -inf
            short = np.flatnonzero(counts < kk)
            pad = np.repeat(short, kk - counts[short])
            rows = np.concatenate([rows, pad])
            cols = np.concatenate([cols, np.full(len(pad), -1, np.int64)])
            vals = np.concatenate([vals, np.full(len(pad), -np.inf)])
        best_i, best_v = _best(rows, cols, vals, q.shape[0], kk)
        best_i = np.where(np.isneginf(best_v), -1, best_i)
        indices[:, :kk] = best_i if self.db.index is None else np.where(best_i >= 0, self.db.index[best_i], -1)
        sims[:, :kk] = best_v
        return indices, sims

"""Pipeline step ``localize``: match a query log against a map's reference descriptors.

:func:`localize` describes the query frames the way the map was described, finds the best map
frames of every query frame, writes the match table (Parquet or CSV, with the map topic of each
match and the map file, descriptor and settings as metadata) and optionally an annotated copy
of the query log with a ``T/memlog/match`` channel. The descriptor is the map's (``auto`` means:
whatever the map was built with), and a whitened map's transform, stored in the map file, is
applied to every query frame; cached query descriptors made without it (or with another) are
refused and described again. All query frames are matched together, in blocks
(:func:`memlog.descriptors.search.match`), or through an approximate FAISS index for big maps
(:mod:`memlog.descriptors.approx`; ``search`` picks, ``auto`` by map size and query count). The
search is timed as it runs (``timing_map``: wall time per query); ``time_search`` adds a separate,
repeated timing (batched and one query at a time) for benchmarks. Query descriptors can be cached
(``query_descriptors``): the cache is reused only when it was made from the same query log (path,
size, modification time), window and descriptor, and the run says whether it was reused or refused.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from memlog.configfile import check_ints
from memlog.descriptors.approx import IVFIndex, SearchConfig, choose
from memlog.descriptors.base import Describer, check_compatible
from memlog.descriptors.extract import describe_log
from memlog.descriptors.registry import make_describer
from memlog.descriptors.search import Database, QueryTiming, confidence, match, time_per_query
from memlog.descriptors.table import DescriptorTable
from memlog.descriptors.whitening import WhitenedDescriber
from memlog.errors import ConfigError, DescriptorError
from memlog.io.atomic import check_output
from memlog.io.base import FrameWindow
from memlog.io.records import ReadReport
from memlog.outputs.descriptor_table import read_cached, read_descriptors, stored_dtype, write_descriptors
from memlog.outputs.matches import write_match_log, write_matches

__all__ = ["localize", "LocalizeConfig", "LocalizeResult", "describer_for"]


@dataclass(frozen=True)
class LocalizeConfig:
    """``k`` reference frames per query; which query frames (``window``); how to search the map
    (``search``); ``time_search``: also time the search separately (repeated; for benchmarks)."""

    k: int = 5
    window: FrameWindow = FrameWindow()
    search: SearchConfig = SearchConfig()
    time_search: bool = False

    def __post_init__(self) -> None:
        check_ints(self, {"k": 1})
        if not isinstance(self.search, SearchConfig):
            raise ConfigError(f"search must be a SearchConfig, got {self.search!r}")


def describer_for(table: DescriptorTable) -> Describer:
    """A describer that makes descriptors comparable with ``table`` (same kind and params, and
    the map's own whitening transform when the map is whitened)."""
    d: Describer = make_describer(table.meta.kind, **table.meta.params)
    if table.meta.whitening:
        if table.whitening is None:
            raise DescriptorError(f"the map's descriptors are whitened (sha256 {table.meta.whitening[:12]}…) but the "
                                  "file does not hold the transform; rebuild the map with `memlog map`")
        d = WhitenedDescriber(d, table.whitening)
    check_compatible(table.meta, d.meta())
    return d


@dataclass
class LocalizeResult:
    """What :func:`localize` wrote."""

    output: Path
    n_queries: int
    n_map: int
    k: int
    timing_map: QueryTiming
    annotated: Path | None
    query_descriptors_reused: bool = False
    reports: list[ReadReport] = field(default_factory=list)
    search: dict[str, Any] = field(default_factory=dict)
    search_timing: dict[str, QueryTiming] | None = None

    def to_dict(self) -> dict[str, Any]:
        return {
            "output": str(self.output), "n_queries": self.n_queries, "n_map": self.n_map, "k": self.k,
            "match_seconds_per_query": self.timing_map.to_dict(),
            "search": self.search,
            "search_timing": {k: v.to_dict() for k, v in self.search_timing.items()} if self.search_timing else None,
            "annotated": str(self.annotated) if self.annotated else None,
            "query_descriptors_reused": self.query_descriptors_reused,
        }


def localize(
    map_descriptors: str | os.PathLike[str],
    query_log: str | os.PathLike[str],
    output: str | os.PathLike[str],
    config: LocalizeConfig | None = None,
    *,
    annotate: str | os.PathLike[str] | None = None,
    query_descriptors: str | os.PathLike[str] | None = None,
) -> LocalizeResult:
    """Match every frame of ``query_log`` against the map (see module doc)."""
    cfg = config or LocalizeConfig()
    inputs = [map_descriptors, query_log]
    check_output(output, inputs)
    if annotate is not None:
        check_output(annotate, inputs + [output], flag="--annotate")
    if query_descriptors is not None:
        check_output(query_descriptors, [*inputs, output] + ([annotate] if annotate else []),
                     flag="--query-descriptors")
    cfg.search.require_faiss()
    ref = read_descriptors(map_descriptors)
    if len(ref) == 0:
        raise DescriptorError(f"{map_descriptors}: the map has no descriptors")
    qt = read_cached(query_descriptors, query_log, ref.meta, cfg.window) if query_descriptors else None
    reused = qt is not None
    reports: list[ReadReport] = []
    if qt is None:
        qt, report = describe_log(query_log, describer_for(ref), cfg.window)
        reports.append(report)
        if query_descriptors is not None:
            write_descriptors(query_descriptors, qt)
    k = min(cfg.k, len(ref))
    db = Database.of(ref.descriptors)
    # what the run records about its search (the IVF settings are added below)
    search: dict[str, Any] = {"method": choose(cfg.search, len(ref), len(qt)), "asked": cfg.search.method,
                              "map_dtype": stored_dtype(map_descriptors)}
    t0 = time.perf_counter()
    if search["method"] == "ivf":
        index = IVFIndex(db, cfg.search.nlist)
        search["nlist"] = index.nlist
        search["nprobe"], search["rerank"] = index.settings(k, cfg.search.nprobe, cfg.search.rerank)
        search["build_seconds"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        idx, sims = index.search(qt.descriptors, k, cfg.search.nprobe, cfg.search.rerank)
    else:
        idx, sims = match(qt.descriptors, db, k=k)
    seconds = (time.perf_counter() - t0) / max(1, len(qt))
    timing_map = QueryTiming(seconds, seconds, len(ref), ref.meta.dim, len(qt), 1)
    conf = confidence(sims)
    out = write_matches(
        output, idx, sims, query_ids=qt.frame_index, ref_ids=ref.frame_index,
        query_columns={"query_topic": np.array(qt.topic), "query_log_time_ns": qt.log_time_ns,
                       "confidence": conf.best, "margin": conf.margin, "ratio": conf.ratio},
        ref_columns={"ref_topic": np.array(ref.topic), "ref_log_time_ns": ref.log_time_ns},
        metadata={"map": str(Path(map_descriptors).resolve()), "query_log": str(Path(query_log).resolve()),
                  "descriptor": ref.meta.to_dict(), "k": cfg.k, "window": qt.extra.get("window"),
                  "search": search},
    )
    search_timing = None
    if cfg.time_search and len(qt):
        # the exact search of the whole map, repeated: batched as above, and one query at a time
        search_timing = {"batched": time_per_query(qt.descriptors, db, repeats=3, k=k),
                         "single": time_per_query(qt.descriptors, db, repeats=1, k=k, max_queries=10, batched=False)}
    annotated = None
    if annotate is not None:
        annotated = write_match_log(query_log, annotate, qt, ref, idx, sims, conf.best)
    return LocalizeResult(out, len(qt), len(ref), cfg.k, timing_map, annotated, reused, reports, search,
                          search_timing)


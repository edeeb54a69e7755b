"""Pipeline step ``localize``: match a query log against a map's reference descriptors.

:func:`localize` describes the query frames the way the map was described, finds the best map
frames of every query frame, writes the match table (Parquet or CSV, with the map topic of each
match and the map file, descriptor and settings as metadata) and optionally an annotated copy
of the query log with a ``T/memlog/match`` channel. The descriptor is the map's (``auto`` means:
whatever the map was built with), and a whitened map's transform, stored in the map file, is
applied to every query frame; cached query descriptors made without it (or with another) are
refused and described again. All query frames are matched together, in blocks
(:func:`memlog.descriptors.search.match`), or through an approximate FAISS index for big maps
(:mod:`memlog.descriptors.approx`; ``search`` picks, ``auto`` by map size and query count).

**Sequences (on by default).** The query is a drive, so each frame is matched together with its
neighbours (``sequence``: :class:`memlog.matching.SequenceConfig`, ``length`` frames
before and after, or before only when ``causal``): the single-frame search gives each frame's
best candidates, which vote for places along the map; the best places are scored exactly along
a path at the best relative speed, and ranked by that score. The match table then gives, per
rank, a distinct place (``sequence_score``), and the confidence is the margin of the best place
over the next. A query that is a single image or a log of unordered frames (runs of fewer than
``length + 1`` frames with increasing stamps) is matched frame by frame, and the table
(``matched_by``), the metadata (``sequence.fallback``) and the result say so.
``sequence.length = 0`` is single-frame localization. The search is timed as it runs (``timing_map``: wall time per query); ``time_search`` adds a separate,
repeated timing (batched and one query at a time) for benchmarks. Query descriptors can be cached
(``query_descriptors``): the cache is reused only when it was made from the same query log (path,
size, modification time), window and descriptor, and the run says whether it was reused or refused.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from memlog.configfile import check_ints
from memlog.descriptors.approx import IVFIndex, SearchConfig, choose
from memlog.descriptors.base import Describer, check_compatible
from memlog.descriptors.extract import describe_log
from memlog.descriptors.registry import make_describer
from memlog.descriptors.search import Database, QueryTiming, time_per_query
from memlog.matching import SequenceConfig, has_positions, match_tables
from memlog.descriptors.table import DescriptorTable
from memlog.descriptors.whitening import WhitenedDescriber
from memlog.errors import ConfigError, DescriptorError
from memlog.io.atomic import check_output
from memlog.io.base import FrameWindow
from memlog.io.open import open_log
from memlog.io.records import ReadReport
from memlog.outputs.descriptor_table import read_cached, read_descriptors, stored_dtype, write_descriptors
from memlog.outputs.map_artefact import check_map_pair
from memlog.outputs.matches import write_match_log, write_matches
from memlog.settings import Flag, positive_int, setting
from memlog.progress import info, warning
from memlog.scoring.motion import recorded_still_distance
from memlog.selection.segment import SEGMENT_DEFAULTS

__all__ = ["localize", "LocalizeConfig", "LocalizeResult", "describer_for"]


@dataclass(frozen=True)
class LocalizeConfig:
    """``k`` reference frames (places, with sequences) per query; which query frames (``window``);
    how to search the map (``search``); how to match sequences (``sequence``; ``length`` 0:
    single frames); ``time_search``: also time the search separately (repeated; for benchmarks)."""

    k: int = setting(5, Flag(("-k",), "reference frames per query (default 5)", check=positive_int, default=5))
    window: FrameWindow = FrameWindow()
    search: SearchConfig = SearchConfig()
    time_search: bool = setting(False, Flag(
        ("--time-search",), "(experimental) also time the exact search of the whole map separately (repeated, "
        "batched and one query at a time)", "experimental", action="store_true"))
    sequence: SequenceConfig = SequenceConfig()

    def __post_init__(self) -> None:
        check_ints(self, {"k": 1})
        if not isinstance(self.search, SearchConfig):
            raise ConfigError(f"search must be a SearchConfig, got {self.search!r}")
        if not isinstance(self.sequence, SequenceConfig):
            raise ConfigError(f"sequence must be a SequenceConfig, got {self.sequence!r}")


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
    sequence: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return {
            "output": str(self.output), "n_queries": self.n_queries, "n_map": self.n_map, "k": self.k,
            "match_seconds_per_query": self.timing_map.to_dict(),
            "search": self.search,
            "search_timing": {k: v.to_dict() for k, v in self.search_timing.items()} if self.search_timing else None,
            "annotated": str(self.annotated) if self.annotated else None,
            "query_descriptors_reused": self.query_descriptors_reused,
            "sequence": self.sequence,
        }


def localize(
    map_descriptors: str | os.PathLike[str],
    query_log: str | os.PathLike[str],
    output: str | os.PathLike[str],
    config: LocalizeConfig | None = None,
    *,
    annotate: str | os.PathLike[str] | None = None,
    query_descriptors: str | os.PathLike[str] | None = None,
    map_log: str | os.PathLike[str] | None = None,
) -> LocalizeResult:
    """Match every frame of ``query_log`` against the map (see module doc). ``map_log``: the map
    MCAP the descriptors belong to, checked first (:func:`~memlog.outputs.map_artefact.check_map_pair`)."""
    cfg = config or LocalizeConfig()
    inputs = [map_descriptors, query_log] + ([map_log] if map_log is not None else [])
    check_output(output, inputs)
    if annotate is not None:
        check_output(annotate, inputs + [output], flag="--annotate")
    if query_descriptors is not None:
        check_output(query_descriptors, [*inputs, output] + ([annotate] if annotate else []),
                     flag="--query-descriptors")
    cfg.search.require_faiss()
    if map_log is not None:
        check_map_pair(map_log, map_descriptors)
    ref = read_descriptors(map_descriptors)
    if len(ref) == 0:
        raise DescriptorError(f"{map_descriptors}: the map has no descriptors")
    if cfg.sequence.enabled and cfg.sequence.coordinate == "positions" and not has_positions(ref):
        raise ConfigError(f"--coordinate positions: the map {map_descriptors} has no position for every frame "
                          "(use --coordinate frames or time)")
    still = map_still_distance(ref, map_descriptors, cfg.sequence)
    window = query_window(query_log, cfg.window)
    # the query's patch features, projected by the map's PCA, when the map re-ranks with them
    patches = cfg.sequence.rerank and ref.patch_pca is not None
    if cfg.sequence.rerank and ref.patch_pca is None:
        info(f"{map_descriptors}: the map stores no patch features ({ref.meta.kind} descriptors, or a map written "
             "before memlog stored them): matched without re-ranking")
    qt = read_cached(query_descriptors, query_log, ref.meta, window, still, patches=patches,
                     patch_pca=ref.patch_pca) if query_descriptors else None
    reused = qt is not None
    reports: list[ReadReport] = []
    if qt is None:
        qt, report = describe_log(query_log, describer_for(ref), window, still_distance=still, patches=patches,
                                  patch_pca=ref.patch_pca)
        reports.append(report)
        if query_descriptors is not None:
            write_descriptors(query_descriptors, qt)
    k = min(cfg.k, len(ref))
    db = Database.of(ref.descriptors)
    # what the run records about its search (the IVF settings are added below)
    search: dict[str, Any] = {"method": choose(cfg.search, len(ref), len(qt)), "asked": cfg.search.method,
                              "map_dtype": stored_dtype(map_descriptors)}
    t0 = time.perf_counter()
    index = None
    if search["method"] == "ivf":
        index = IVFIndex(db, cfg.search.nlist)
        search["nlist"] = index.nlist
        n_cand = max(k, cfg.sequence.candidates + 1) if cfg.sequence.enabled else k
        search["nprobe"], search["rerank"] = index.settings(n_cand, cfg.search.nprobe, cfg.search.rerank)
        search["build_seconds"] = time.perf_counter() - t0
        t0 = time.perf_counter()
    res = match_tables(qt, ref, cfg.sequence, k=k, index=index,
                       nprobe=cfg.search.nprobe, rerank=cfg.search.rerank)
    idx, sims = res.indices, res.similarities
    seconds = (time.perf_counter() - t0) / max(1, len(qt))
    timing_map = QueryTiming(seconds, seconds, len(ref), ref.meta.dim, len(qt), 1)
    how = np.where(res.sequence, "causal sequence" if cfg.sequence.causal else "sequence", "single frame")
    seq_scores = np.where(res.sequence[:, None] & (idx >= 0), res.scores, np.nan)
    sequence = {**_sequence_record(res.info, cfg.sequence), "still_distance": still}
    out = write_matches(
        output, idx, sims, query_ids=qt.frame_index, ref_ids=ref.frame_index,
        query_columns={"query_topic": np.array(qt.topic), "query_log_time_ns": qt.log_time_ns,
                       "confidence": res.confidence, "margin": res.margin, "ratio": res.ratio,
                       "matched_by": how, "fallback": res.fallback, "sequence_speed": res.speed,
                       "sequence_window": res.window},
        ref_columns={"ref_topic": np.array(ref.topic), "ref_log_time_ns": ref.log_time_ns},
        rank_columns={"sequence_score": seq_scores,
                      **({} if res.rerank is None else {"rerank_score": res.rerank}),
                      **({} if res.posterior is None else {"place_probability": res.posterior})},
        metadata={"map": str(Path(map_descriptors).resolve()), "query_log": str(Path(query_log).resolve()),
                  "descriptor": ref.meta.to_dict(), "k": cfg.k, "window": qt.extra.get("window"),
                  "search": search, "sequence": sequence},
    )
    if sequence["fallback"]:
        info(sequence["fallback"])
    search_timing = None
    if cfg.time_search and len(qt):
        # the exact search of the whole map, repeated: batched as above, and one query at a time
        search_timing = {"batched": time_per_query(qt.descriptors, db, repeats=3, k=k),
                         "single": time_per_query(qt.descriptors, db, repeats=1, k=k, max_queries=10, batched=False)}
    annotated = None
    if annotate is not None:
        annotated = write_match_log(query_log, annotate, qt, ref, idx, sims, res.confidence,
                                    matched_by=[str(h) for h in how], sequence_score=seq_scores[:, 0],
                                    speed=res.speed)
    return LocalizeResult(out, len(qt), len(ref), cfg.k, timing_map, annotated, reused, reports, search,
                          search_timing, sequence)


def query_window(query_log: str | os.PathLike[str], window: FrameWindow) -> FrameWindow:
    """``window`` with its topics: those asked for, else every camera topic of the query (each
    is matched as a drive of its own against the map)."""
    if window.topics is not None:
        return window
    with open_log(query_log) as reader:
        return replace(window, topics=tuple(reader.check_camera_topics(None)))


def map_still_distance(ref: DescriptorTable, path: str | os.PathLike[str], cfg: SequenceConfig) -> float:
    """The ``still_distance`` the map's stops were found with (its ``extra["stops"]``), so the
    query's stops are found alike; the default for a map that does not say (warning, when its
    stops are left out of the match: a map written before the rule was recorded found them frame
    to frame)."""
    recorded = recorded_still_distance(ref.extra)
    if recorded is not None:
        return recorded
    if ref.moving_index is not None and cfg.enabled and cfg.stops:
        warning(f"{path}: the map's stops were found by an older memlog (frame to frame: a slow crawl was one "
                "stop), the query's are found from each stop's first frame; re-run `memlog map` to find both "
                "alike, or match with --keep-stops")
    return SEGMENT_DEFAULTS.still_distance


def _sequence_record(found: dict[str, Any], cfg: SequenceConfig) -> dict[str, Any]:
    """What the outputs record about sequence matching: the settings asked for, what was used
    (coordinate, speeds searched, the reference's frame spacing) and the fallback, if any."""
    keys = ("coordinate", "coordinate_note", "length_used", "speeds", "speed_step", "n_speeds", "speed_prior", "unit",
            "runs", "max_gap_s", "sequence_queries", "single_queries", "fallback", "fallback_reasons", "stops",
            "standing_rows", "rerank", "hmm", "ensemble")
    out = {"asked": cfg.to_dict(), "length": cfg.length, "mode": "causal" if cfg.causal else "offline",
           "candidates": cfg.candidates, **{k: found.get(k) for k in keys}}
    if not cfg.enabled:
        out["mode"] = "single frames"
    return out


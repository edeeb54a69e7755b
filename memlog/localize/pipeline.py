"""Pipeline step: localize a query log against a map's reference descriptors.

``describe_log`` describes the frames of a log with the map's descriptor kind;
``localize`` finds the best map frames of every query frame (exact search), writes the
match table (Parquet or CSV), optionally an annotated copy of the query log with a
``T/memlog/match`` channel, and times matching one query against the map and against a
database the size of the full (unselected) reference drive.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from memlog.descriptors.base import Describer, make_describer
from memlog.descriptors.extract import build_table, describe_frames
from memlog.descriptors.parquet import DescriptorTable, check_compatible, read_descriptors, write_descriptors
from memlog.errors import DescriptorError
from memlog.io import open_log
from memlog.io.positions import read_track
from memlog.localize.match import QueryTiming, confidence, match, time_per_query, write_matches
from memlog.progress import progress

__all__ = ["describe_log", "localize", "LocalizeResult", "describer_for"]


def describer_for(table: DescriptorTable) -> Describer:
    """A describer that makes descriptors comparable with ``table`` (same kind and params)."""
    d = make_describer(table.meta.kind, **table.meta.params)
    check_compatible(table.meta, d.meta())
    return d


def describe_log(
    log: str | os.PathLike[str],
    describer: Describer,
    *,
    topics: list[str] | None = None,
    stride: int = 1,
    scores: dict[str, dict[int, dict[str, Any]]] | None = None,
) -> DescriptorTable:
    """Descriptors of every (``stride``-th) camera frame of ``log``, with positions when it has them."""
    with open_log(log) as reader:
        cams = topics or reader.camera_topics()
        if topics is None and len(cams) > 1:
            cams = cams[:1]  # one camera per drive unless asked
        track = read_track(reader)
        frames = progress(reader.frames(cams, stride=stride), desc="describe", unit="frame")
        kept, desc = describe_frames(frames, describer, reader)
        return build_table(kept, desc, describer, scores=scores, track=track, extra={"log": str(reader.path)})


@dataclass
class LocalizeResult:
    output: Path
    n_queries: int
    n_map: int
    k: int
    timing_map: QueryTiming
    timing_full: QueryTiming | None
    annotated: Path | None

    def to_dict(self) -> dict[str, Any]:
        return {
            "output": str(self.output), "n_queries": self.n_queries, "n_map": self.n_map, "k": self.k,
            "match_seconds_per_query": self.timing_map.to_dict(),
            "match_seconds_per_query_full_reference": self.timing_full.to_dict() if self.timing_full else None,
            "annotated": str(self.annotated) if self.annotated else None,
        }


def _full_size(table: DescriptorTable) -> int | None:
    n = table.extra.get("frames_in")
    return int(n) if n else None


def localize(
    map_descriptors: str | os.PathLike[str],
    query_log: str | os.PathLike[str],
    output: str | os.PathLike[str],
    *,
    k: int = 5,
    topics: list[str] | None = None,
    stride: int = 1,
    annotate: str | os.PathLike[str] | None = None,
    query_descriptors: str | os.PathLike[str] | None = None,
) -> LocalizeResult:
    """Match every frame of ``query_log`` against the map (see module doc)."""
    ref = read_descriptors(map_descriptors)
    if len(ref) == 0:
        raise DescriptorError(f"{map_descriptors}: the map has no descriptors")
    if query_descriptors is not None and Path(query_descriptors).is_file():
        qt = read_descriptors(query_descriptors)
        check_compatible(ref.meta, qt.meta)
    else:
        describer = describer_for(ref)
        qt = describe_log(query_log, describer, topics=topics, stride=stride)
        if query_descriptors is not None:
            write_descriptors(query_descriptors, qt)
    idx, sims = match(qt.descriptors, ref.descriptors, k=min(k, len(ref)))
    conf = confidence(sims)
    out = write_matches(
        output, idx, sims, query_ids=qt.frame_index, ref_ids=ref.frame_index,
        query_columns={"query_topic": np.array(qt.topic), "query_log_time_ns": qt.log_time_ns,
                       "confidence": conf.best, "margin": conf.margin, "ratio": conf.ratio},
    )
    timing_map = time_per_query(qt.descriptors, ref.descriptors, repeats=3)
    timing_full = None
    n_full = _full_size(ref)
    if n_full and n_full > len(ref):
        rng = np.random.default_rng(0)
        fake = rng.standard_normal((n_full, ref.descriptors.shape[1])).astype(np.float32)
        fake /= np.linalg.norm(fake, axis=1, keepdims=True)
        timing_full = time_per_query(qt.descriptors, fake, repeats=3)
    annotated = None
    if annotate is not None:
        annotated = _annotate(query_log, annotate, qt, ref, idx, sims, conf.best)
    return LocalizeResult(out, len(qt), len(ref), k, timing_map, timing_full, annotated)


def _annotate(query_log: Any, path: Any, qt: DescriptorTable, ref: DescriptorTable, idx: np.ndarray,
              sims: np.ndarray, best: np.ndarray) -> Path:
    """Copy the query log and add ``T/memlog/match`` (schema memlog.Match) per described frame."""
    from memlog.io import McapLogWriter, copy_log
    from memlog.schemas import schema_bytes

    by_frame = {(t, int(i)): r for r, (t, i) in enumerate(zip(qt.topic, qt.frame_index))}
    with open_log(query_log) as reader, McapLogWriter(path, profile=reader.profile) as w:
        copy_log(reader, w)
        sid = w.add_schema("memlog.Match", "jsonschema", schema_bytes("memlog.Match"))
        chans = {t: w.add_channel(f"{t}/memlog/match", "json", sid) for t in sorted(set(qt.topic))}
        for (t, i), r in by_frame.items():
            ms = [{"topic": ref.topic[j], "frame_index": int(ref.frame_index[j]), "similarity": float(s)}
                  for j, s in zip(idx[r], sims[r]) if j >= 0]
            stamp = int(qt.stamp_ns[r])
            w.write_json(chans[t], int(qt.log_time_ns[r]), {
                "timestamp": {"sec": stamp // 1_000_000_000, "nsec": stamp % 1_000_000_000},
                "frame_index": i, "matches": ms, "confidence": float(best[r]),
            })
    return Path(path)



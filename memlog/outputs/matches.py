"""Match tables (the best map frames of every query frame, as Parquet or CSV) and the query log
annotated with a ``T/memlog/match`` channel (``memlog.Match``, in the query's encoding family)."""

from __future__ import annotations

import json
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import pyarrow as pa

from memlog.descriptors.table import DescriptorTable
from memlog.errors import DescriptorError
from memlog.io.atomic import atomic_output
from memlog.io.mcap import McapLogWriter, copy_log
from memlog.io.open import open_log
from memlog.outputs.channels import MATCH, MemlogChannels, family_of

__all__ = ["write_matches", "write_match_log"]


def write_matches(
    path: str | os.PathLike[str],
    indices: npt.ArrayLike,
    similarities: npt.ArrayLike,
    *,
    query_ids: npt.ArrayLike | None = None,
    ref_ids: npt.ArrayLike | None = None,
    query_columns: Mapping[str, npt.ArrayLike] | None = None,
    ref_columns: Mapping[str, npt.ArrayLike] | None = None,
    rank_columns: Mapping[str, npt.ArrayLike] | None = None,
    metadata: Mapping[str, Any] | None = None,
) -> Path:
    """Write matches in long form (one row per query and rank) to ``.parquet`` or ``.csv``.

    Columns: ``query_row``, ``rank`` (0 = best), ``ref_row``, ``similarity``; with
    ``query_ids``/``ref_ids`` (e.g. frame indices, indexed by row) also ``query_id`` and
    ``ref_id``; ``query_columns`` adds per-query values (e.g. ``correct``) to each of its
    rows; ``ref_columns`` (indexed by reference row, e.g. ``ref_topic``) adds the matched frame's
    values; ``rank_columns`` (``[Q, k]`` like ``indices``, e.g. a sequence score) adds the value
    of each (query, rank), NaN written as null. ``metadata`` (JSON-able) goes into the Parquet
    schema metadata as ``memlog.<key>`` (Parquet only). Empty slots (index -1) are not written.
    Atomic (temporary file, then rename).
    """
    idx = np.asarray(indices, dtype=np.int64)
    sim = np.asarray(similarities, dtype=np.float32)
    if idx.ndim != 2 or idx.shape != sim.shape:
        raise DescriptorError(f"indices {idx.shape} and similarities {sim.shape} must both be [Q, k]")
    target = Path(path)
    suffix = target.suffix.lower()
    if suffix not in (".parquet", ".pq", ".csv"):
        raise DescriptorError(f"{target}: match files must end in .parquet or .csv")
    qrow, rank = np.nonzero(idx >= 0)
    ref = idx[qrow, rank]
    cols: dict[str, pa.Array] = {
        "query_row": pa.array(qrow.astype(np.int64)),
        "rank": pa.array(rank.astype(np.int32)),
        "ref_row": pa.array(ref),
        "similarity": pa.array(sim[qrow, rank]),
    }
    if query_ids is not None:
        qid = np.asarray(query_ids)
        if qid.shape != (idx.shape[0],):
            raise DescriptorError(f"query_ids must have {idx.shape[0]} values, got shape {qid.shape}")
        cols["query_id"] = pa.array(qid[qrow])
    if ref_ids is not None:
        rid = np.asarray(ref_ids)
        if rid.ndim != 1 or (ref.size and ref.max() >= rid.shape[0]):
            raise DescriptorError(f"ref_ids ({rid.shape}) does not cover reference row {int(ref.max())}")
        cols["ref_id"] = pa.array(rid[ref])
    for name, values in (ref_columns or {}).items():
        v = np.asarray(values)
        if v.ndim != 1 or (ref.size and ref.max() >= v.shape[0]):
            raise DescriptorError(f"reference column {name} ({v.shape}) does not cover reference row {int(ref.max())}")
        if name in cols:
            raise DescriptorError(f"reference column {name} clashes with a standard column")
        cols[name] = pa.array(v[ref])
    for name, values in (rank_columns or {}).items():
        v = np.asarray(values)
        if v.shape != idx.shape:
            raise DescriptorError(f"rank column {name} must be {idx.shape} like the indices, got shape {v.shape}")
        if name in cols:
            raise DescriptorError(f"rank column {name} clashes with a standard column")
        cols[name] = pa.array(v[qrow, rank], from_pandas=True)
    for name, values in (query_columns or {}).items():
        v = np.asarray(values)
        if v.shape != (idx.shape[0],):
            raise DescriptorError(f"query column {name} must have {idx.shape[0]} values, got shape {v.shape}")
        if name in cols:
            raise DescriptorError(f"query column {name} clashes with a standard column")
        cols[name] = pa.array(v[qrow])
    table = pa.table(cols)
    if metadata:
        table = table.replace_schema_metadata(
            {f"memlog.{k}".encode(): json.dumps(v, sort_keys=True).encode() for k, v in metadata.items()})
    try:
        with atomic_output(target) as tmp:
            if suffix == ".csv":
                import pyarrow.csv as pacsv

                pacsv.write_csv(table, tmp)
            else:
                import pyarrow.parquet as pq

                pq.write_table(table, tmp, compression="zstd")
    except (OSError, pa.ArrowException) as exc:
        raise DescriptorError(f"could not write {target}: {exc}") from None
    return target


def _finite(values: np.ndarray | None, row: int) -> float | None:
    if values is None or not np.isfinite(values[row]):
        return None
    return float(values[row])


def write_match_log(query_log: str | os.PathLike[str], path: str | os.PathLike[str], qt: DescriptorTable,
                    ref: DescriptorTable, idx: np.ndarray, sims: np.ndarray, best: np.ndarray, *,
                    matched_by: Sequence[str] | None = None, sequence_score: np.ndarray | None = None,
                    speed: np.ndarray | None = None) -> Path:
    """Copy the query log and add ``T/memlog/match`` (``memlog.Match``, in the query's encoding
    family: :mod:`memlog.outputs.channels`) per described frame: the matches with their
    similarities, the confidence ``best``, how the frame was matched (``matched_by``, default
    "single frame"), the best place's sequence score and the path's speed (null: none)."""
    by_frame = {(t, int(i)): r for r, (t, i) in enumerate(zip(qt.topic, qt.frame_index))}
    topics = sorted(set(qt.topic))
    with open_log(query_log) as reader, McapLogWriter(path, profile=reader.profile) as w:
        copy_log(reader, w)
        out = MemlogChannels(w, family_of(reader, topics))
        chans = {t: out.add(f"{t}/memlog/match", MATCH) for t in topics}
        for (t, i), r in by_frame.items():
            ms = [{"topic": ref.topic[j], "frame_index": int(ref.frame_index[j]), "similarity": float(s)}
                  for j, s in zip(idx[r], sims[r]) if j >= 0]
            sec, nsec = divmod(int(qt.stamp_ns[r]), 1_000_000_000)
            out.write(chans[t], int(qt.log_time_ns[r]), {
                "timestamp": {"sec": sec, "nsec": nsec}, "frame_index": i, "matches": ms, "confidence": float(best[r]),
                "matched_by": matched_by[r] if matched_by is not None else "single frame",
                "sequence_score": _finite(sequence_score, r), "speed": _finite(speed, r),
            })
    return Path(path)

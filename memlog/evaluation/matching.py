"""How ``memlog evaluate`` matches the query drive against a map and scores it under both protocols.

:class:`Matching` runs the one drive matcher (:func:`memlog.matching.match_tables`, what
``memlog localize`` calls) on a map given as its own descriptor table (read back from the map's
Parquet) or as a mask of the reference drive's rows, and evaluates the result under the map-only and the
paper protocol (:mod:`memlog.evaluation.metrics`); :func:`whitened` puts a drive's table in a map's
descriptor space (its whitening and patch PCA) as ``localize`` puts a query there; :func:`rows_for` and
:func:`truth_rows` re-index a truth file's frame indices to descriptor rows.
"""

from __future__ import annotations

import time
from dataclasses import replace
from typing import Any

import numpy as np

from memlog.descriptors.patches import PatchPCA
from memlog.descriptors.search import time_per_query
from memlog.matching import SequenceConfig, SequenceMatch, match_tables
from memlog.matching.rerank import PairScores
from memlog.descriptors.table import DescriptorTable
from memlog.descriptors.whitening import Whitening
from memlog.evaluation.metrics import Discarded, ProtocolResult, evaluate_map_only, evaluate_paper

__all__ = ["Matching", "whitened", "rows_for", "truth_rows", "protocol_dict"]


def protocol_dict(r: ProtocolResult) -> dict[str, Any]:
    return {"auc": r.auc, "recall@1": r.recall_at.get(1), "recall@5": r.recall_at.get(5),
            "recall@10": r.recall_at.get(10), "precision@100%recall": r.precision_at_full_recall,
            "coverage": r.coverage}


class Matching:
    """How the query drive is matched against a map: by the one drive matcher
    (:func:`memlog.matching.match_tables`, what ``memlog localize`` calls), as
    sequences (the default) or frame by frame. A map is a mask over the reference rows, or the
    map's own descriptor table as ``memlog map`` wrote it (``map_table``: read back from its
    Parquet, so what is measured is the file a user gets). ``ranked`` gives the best places with
    the confidence the PR curves use in column 0 (the margin, one scale for every row)."""

    def __init__(self, q_t: DescriptorTable, ref_t: DescriptorTable, sequence: SequenceConfig, k: int,
                 paper_discarded: Discarded) -> None:
        self.q_t, self.ref_t, self.k, self.paper_discarded = q_t, ref_t, k, paper_discarded
        self.q = q_t.descriptors
        self.seq = sequence
        self.sequence = self.seq.enabled
        self.info: dict[str, Any] = {"matching": "sequence" if self.sequence else "single frame"}
        self._full: dict[bool, tuple[np.ndarray, np.ndarray]] = {}
        self._rows = {int(f): r for r, f in enumerate(ref_t.frame_index)}
        self._pairs: dict[str, PairScores] = {}  # patch pair scores, shared by every mask of the reference

    def _config(self, sequence: bool) -> SequenceConfig:
        return self.seq if sequence else replace(self.seq, length=0, causal=False)

    def _record(self, sm: SequenceMatch) -> None:
        if "sequence" not in self.info and sm.sequence.any():
            self.info.update({"sequence": self.seq.to_dict(),
                              **{k: sm.info.get(k) for k in ("coordinate", "coordinate_note", "max_gap_s", "stops",
                                                             "standing_rows", "length_used", "map_runs",
                                                             "rerank", "hmm", "ensemble")}})
        if "fallback" not in self.info and sm.info.get("fallback"):
            self.info["fallback"] = sm.info["fallback"]
            self.info["fallback_reasons"] = sm.info.get("fallback_reasons")
        self.info.setdefault("sequence_queries", int(sm.sequence.sum()))

    def ranked(self, mask: np.ndarray | None, k: int, sequence: bool | None = None,
               map_table: DescriptorTable | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(indices [Q, k] as reference rows, confidence-first scores [Q, k]) of the map ``mask``
        (None: every row) or ``map_table``."""
        seq = self.sequence if sequence is None else sequence
        if map_table is None and mask is None and k <= self.k and seq in self._full:
            idx, sc = self._full[seq]
            return idx[:, :k], sc[:, :k]
        if map_table is not None:
            sm = match_tables(self.q_t, map_table, self._config(seq), k=k)
            rows = np.array([self._rows.get(int(f), -1) for f in map_table.frame_index], dtype=np.int64)
            idx = np.where(sm.indices >= 0, rows[np.maximum(sm.indices, 0)], -1)
        else:
            sm = match_tables(self.q_t, self.ref_t, self._config(seq), k=k, ref_mask=mask, pair_cache=self._pairs)
            idx = sm.indices
        if seq and (map_table is not None or mask is None):  # what the summary says: the full and memorable maps
            self._record(sm)
        sc = sm.scores.copy()
        sc[:, 0] = sm.confidence
        out = (idx, sc)
        if map_table is None and mask is None and k == self.k:
            self._full[seq] = out
        return out

    def evaluate(self, truth: list[set[int]], mask: np.ndarray, sequence: bool | None = None,
                 map_table: DescriptorTable | None = None) -> tuple[dict[str, Any], ProtocolResult, ProtocolResult]:
        """Both protocols for the map ``mask`` (matched against ``map_table`` when given, the
        map's frames as read back from its file): map-only (only its frames are searched) and the
        paper's (every reference frame searched, a best match outside the map is no match)."""
        seq = self.sequence if sequence is None else sequence
        k = min(self.k, max(1, int(mask.sum())))
        ns = tuple(n for n in (1, 5, 10) if n <= max(k, 1))
        t0 = time.perf_counter()
        idx, sc = self.ranked(mask, max(ns), seq, map_table)
        seconds = (time.perf_counter() - t0) / max(1, len(self.q))
        mo = evaluate_map_only((idx, sc), truth, mask, ns=ns)
        full_idx, full_sc = self.ranked(None, self.k, seq)
        po = evaluate_paper((full_idx[:, : max(ns)], full_sc[:, : max(ns)]), truth, mask, ns=ns,
                            discarded=self.paper_discarded)
        if not seq:  # the search alone, repeated (the sequence time above is one pass)
            seconds = time_per_query(self.q, self.ref_t.descriptors, repeats=3, ref_mask=mask, max_queries=50).seconds_per_query
        out = {"frames": int(mask.sum()), **protocol_dict(mo), "match_seconds_per_query": seconds,
               "paper_protocol": protocol_dict(po)}
        if seq and sequence is None:
            out["single_frame"] = self.evaluate(truth, mask, sequence=False, map_table=map_table)[0]
        return out, mo, po


def rows_for(table: DescriptorTable, n_frames: int) -> np.ndarray:
    """Row of each frame index 0..n-1 in ``table`` (-1 when the frame was not described)."""
    rows = np.full(n_frames, -1, dtype=np.int64)
    ok = table.frame_index < n_frames
    rows[table.frame_index[ok]] = np.nonzero(ok)[0]
    return rows


def truth_rows(truth_frames: list[set[int]], q: DescriptorTable, ref_rows: np.ndarray) -> list[set[int]]:
    """Truth re-indexed from frame indices to descriptor rows (queries = rows of q)."""
    out = []
    for fi in q.frame_index:
        s = truth_frames[int(fi)] if int(fi) < len(truth_frames) else set()
        out.append({int(ref_rows[j]) for j in s if j < len(ref_rows) and ref_rows[j] >= 0})
    return out


def whitened(table: DescriptorTable, whitening: Whitening | None, patch_pca: PatchPCA | None, *,
             reference: bool = False) -> DescriptorTable:
    """``table`` with its descriptors whitened by ``whitening`` and its patches projected by
    ``patch_pca`` (the map's: the space the map's Parquet is in, as ``localize`` puts a query
    there); descriptors unchanged without a whitening. ``reference``: the table is the reference
    drive, so it carries the whitening as a map does (the matcher's whitening ensemble reads it)."""
    table = table.projected(patch_pca)
    if whitening is None:
        return table
    meta = replace(table.meta, dim=whitening.dim_out, whitening=whitening.sha256)
    return replace(table, descriptors=whitening.apply(table.descriptors), meta=meta,
                   whitening=whitening if reference else None)

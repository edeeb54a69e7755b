#!/usr/bin/env python3
"""Patch re-ranking on the camera-resolution Stromovka pair (measurement for the re-ranking stage).

The drive matcher (``match_tables``, what ``memlog localize`` calls) gives each winter query its
best 20 places on a map written by ``memlog map`` (full, half, quarter; the maps and query tables
of ``benchmarks/matcher_defaults.py``); ``rerank_by_patches`` re-ranks them by the patch features
of :mod:`memlog.descriptors.patches` (layer-7 DINOv2 tokens pooled to 8x8, PCA-64 fitted on the
map's patches, float16), the window's frames aligned along each place's path.

    python benchmarks/rerank_table.py            # Markdown table: R@1, R@5, AUC-PR, P@10/50 %R, ms/query

The tokens are computed here from the logs (one more network pass; the map does not store
patches yet), so ms/query counts the matching and the re-ranking, not the network.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from benchmarks.matcher_defaults import PAIRS, SHARED, _map, _query, fmt, metrics  # noqa: E402

PLACES = 20  # places per query re-ranked


def pooled_patches(log: Path, frames: np.ndarray) -> np.ndarray:
    """Pooled layer-7 patches ``[len(frames), 64, 384]`` of the log's frames of these indices."""
    from memlog.descriptors.patches import PATCH_LAYER, pool_patches
    from memlog.descriptors.registry import make_describer
    from memlog.io import open_log

    d = make_describer("dinov2-gem", layer=PATCH_LAYER)
    want = {int(f) for f in frames}
    with open_log(log) as r:
        imgs = {f.index: f.decode_bgr() for f in r.frames() if f.index in want}
    out = [pool_patches(d.tokens([imgs[int(f)] for f in frames[a : a + 16]])) for a in range(0, len(frames), 16)]
    return np.concatenate(out)


def main() -> int:
    import json

    from memlog.descriptors.patches import PatchPCA
    from memlog.descriptors.sequence import (
        SequenceConfig,
        drive_coordinates,
        drive_runs,
        match_tables,
        reference_unit,
        rerank_by_patches,
        resolve_coordinate,
        uses_stops,
    )

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cache", type=Path, default=Path("/tmp/memlog-matcher-defaults"))
    a = ap.parse_args()
    a.cache.mkdir(parents=True, exist_ok=True)
    ref_log, q_log, truth_file = (SHARED / n for n in PAIRS["stromovka"])
    truth = [set(m) for m in json.loads(truth_file.read_text())["matches"]]
    print("| map | matching | R@1 | R@5 | AUC-PR | P@10%R | P@50%R | ms/query |\n|---|---|---|---|---|---|---|---|")
    q_pooled = None
    for which in ("full", "half", "quarter"):
        ref, query = _query(a.cache, "stromovka", _map(a.cache, "stromovka", which))
        if q_pooled is None:
            q_pooled = pooled_patches(q_log, query.frame_index)
        pca = PatchPCA.fit(pooled_patches(ref_log, ref.frame_index))
        rp, qp = pca.apply(pooled_patches(ref_log, ref.frame_index)), pca.apply(q_pooled)
        sets = [truth[int(f)] for f in query.frame_index]
        for name, cfg in (("single frames", SequenceConfig(length=0)), ("sequences (default)", SequenceConfig())):
            t0 = time.perf_counter()
            res = match_tables(query, ref, cfg, k=PLACES)
            t1 = time.perf_counter()
            coord, _note = resolve_coordinate(cfg.coordinate, query, ref)
            stops = uses_stops(cfg, coord)
            qc, rc = drive_coordinates(query, coord, stops), drive_coordinates(ref, coord, stops)
            labels, _gap = drive_runs(query, cfg.max_gap_s)
            rr = rerank_by_patches(res, query.descriptors, ref.descriptors, qp, rp, qc, rc, np.arange(len(ref)),
                                   labels, cfg, 10, reference_unit(ref, rc))
            t2 = time.perf_counter()
            for label, m, ms in ((name, res, t1 - t0), (f"{name} + patch re-rank", rr, t2 - t0)):
                frames = np.where(m.indices >= 0, ref.frame_index[np.maximum(m.indices, 0)], -1)
                row = {**metrics(frames, m.confidence, sets), "ms": ms / len(query) * 1e3}
                print(f"| {which} ({len(ref)}) | {label} | {fmt(row)} |", flush=True)
    print(f"\n(patches stored per map frame: 64 x {pca.dim} float16 = {64 * pca.dim * 2} bytes)")
    return 0


if __name__ == "__main__":
    sys.exit(main())

#!/usr/bin/env python3
"""How far a map's R@1 moves with the frames its whitening is fitted on, with and without the
whitening ensemble (``docs/defaults.md``, "The whitening ensemble").

A map's whitening is fitted on its own kept frames. Here each map is matched with the whitening
``memlog map`` stored ("own") and with ``--refits`` whitenings refitted on random 85 % samples of
the same frames (the same dimension rule, ``min(512, dim, n/2)`` of the whole map), the map's and
the query's descriptors whitened by each: the same map, the same query, the same matcher
(``memlog.matching.match_tables``, what ``memlog localize`` runs), once (``--no-ensemble``) and with
the ensemble (the default). R@1 over every query frame, map-only, truth ±1 place; and, with the
ensemble, over the query's moving frames (each stop's first frame once: a stop's frames share one
decision, so a long stop weighs as one frame there — a steadier figure for comparing matchers).

Maps: ``memlog map`` of the Stromovka autumn drive, frame-aligned, as a drive with stops, and that
drive with odometry (``drive_pair.py``'s ``drive-odometry``: an ``/odom`` topic at each frame's place,
so the map is cut by distance) (``benchmarks/matcher_defaults.py``'s maps, cached in ``--cache``):
every frame, memlog's half and quarter maps and its default size. The descriptors before whitening are described here (DINOv2-GeM;
the query's patch features projected by each map's PCA, as ``localize`` does) and cached beside them.

    python benchmarks/whitening_spread.py          # Markdown table (about 10 minutes on 2 cores)
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from benchmarks.drive_pair import pair_files  # noqa: E402
from benchmarks.matcher_defaults import PAIRS, SHARED, _map, metrics  # noqa: E402

MAPS = ("full", "default", "half", "quarter")


def _raw(cache: Path, log: Path, name: str, patch_pca: Any, still: float | None = None) -> Any:
    """``log`` described without whitening (patches projected by ``patch_pca`` when given; stops
    found with ``still``, the map's rule), cached."""
    from memlog.descriptors.extract import describe_log
    from memlog.descriptors.registry import make_describer
    from memlog.io.base import FrameWindow
    from memlog.outputs.descriptor_table import read_descriptors, write_descriptors

    path = cache / f"{name}.raw.parquet"
    if path.is_file():
        return read_descriptors(path)
    kw = {} if still is None else {"still_distance": still}
    table, _report = describe_log(log, make_describer("dinov2-gem"), FrameWindow(), patches=patch_pca is not None,
                                  patch_pca=patch_pca, **kw)
    write_descriptors(path, table)
    return table


def _whitened(table: Any, raw: Any, w: Any) -> Any:
    """``table`` with the descriptors ``raw`` whitened by ``w`` (a map keeps the transform)."""
    meta = replace(table.meta, dim=w.dim_out, whitening=w.sha256)
    return replace(table, descriptors=w.apply(raw), meta=meta, whitening=w if table.whitening is not None else None)


def main() -> int:
    from memlog.descriptors.whitening import fit_whitening
    from memlog.matching import SequenceConfig, match_tables
    from memlog.outputs.descriptor_table import read_descriptors
    from memlog.steps.localize import map_still_distance

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cache", type=Path, default=Path("/tmp/memlog-matcher-defaults-2"))
    ap.add_argument("--refits", type=int, default=8)
    ap.add_argument("--seed", type=int, default=11)
    a = ap.parse_args()
    a.cache.mkdir(parents=True, exist_ok=True)
    print("| pair | map (frames) | once: own | once: refits | ensemble: own | ensemble: refits "
          "| ensemble: refits, moving frames |\n|---|---|---|---|---|---|---|")
    for pair in ("stromovka", "stromovka-drive", "stromovka-drive-odometry"):
        ref_log, q_log, truth_file = (pair_files(a.cache, "drive-odometry") if pair.endswith("-odometry")
                                      else (SHARED / f for f in PAIRS[pair]))
        truth = [set(m) for m in json.loads(truth_file.read_text())["matches"]]
        ref_raw = _raw(a.cache, ref_log, f"{pair}-reference", None)
        for which in MAPS:
            parquet = _map(a.cache, pair, which, ref=ref_log)
            ref = read_descriptors(parquet)
            still = map_still_distance(ref, parquet, SequenceConfig())
            q_raw = _raw(a.cache, q_log, f"{pair}-{which}-query", ref.patch_pca, still)
            rows = np.searchsorted(ref_raw.frame_index, ref.frame_index)
            raw = ref_raw.descriptors[rows]
            whitenings: list[Any] = [ref.whitening]
            rng = np.random.default_rng(a.seed)
            if ref.whitening is not None:
                for _ in range(a.refits):
                    pick = rng.choice(len(raw), max(32, int(len(raw) * 0.85)), replace=False)
                    whitenings.append(fit_whitening(raw[pick], max_dim=len(raw) // 2))
            mi = q_raw.moving_index
            moving = np.r_[True, mi[1:] != mi[:-1]] if mi is not None and len(mi) else np.ones(len(q_raw), bool)
            cells = []
            for ensemble in (False, True):
                r1, r1_moving = [], []
                for w in whitenings:
                    m = ref if w is None else _whitened(ref, raw, w)
                    q = q_raw if w is None else _whitened(q_raw, q_raw.descriptors, w)
                    res = match_tables(q, m, SequenceConfig(ensemble=ensemble), k=5)
                    frames = np.where(res.indices >= 0, m.frame_index[np.maximum(res.indices, 0)], -1)
                    want = [truth[int(f)] for f in q.frame_index]
                    r1.append(metrics(frames, res.confidence, want)["r1"])
                    r1_moving.append(metrics(frames[moving], res.confidence[moving],
                                             [t for t, keep in zip(want, moving) if keep])["r1"])
                rest = np.array(r1[1:])
                cells += [f"{r1[0]:.3f}", f"{rest.mean():.3f} ± {rest.std():.3f}" if len(rest) else "–"]
            rest = np.array(r1_moving[1:])
            cells.append(f"{rest.mean():.3f} ± {rest.std():.3f}" if len(rest) else f"{r1_moving[0]:.3f} (own)")
            print(f"| {pair} | {which} ({len(ref)}) | " + " | ".join(cells) + " |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

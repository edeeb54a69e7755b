#!/usr/bin/env python3
"""The drive matcher's defaults, measured at camera resolution (Stromovka) and on Nordland.

Every row is matched by ``memlog.matching.match_tables`` — the function ``memlog
localize`` and ``memlog evaluate`` call — on maps written by ``memlog map`` (read back from their
Parquet, as localize reads them) and query descriptors made the way localize makes them
(``describer_for(map)``: the map's descriptor and whitening, patch features projected by the
map's PCA). "default" re-ranks by patch features where the map stores them (DINOv2 maps).

Data (``../shared/data``): Stromovka autumn map / winter query (1024x384, 101 places, DINOv2), the
same places as drives with stops, crawls and fast stretches (``stromovka-drive``),
Nordland summer map / winter query (64x32, 800 places, thumbnails); maps of every frame
(``--keep-fraction 1``) and memlog's half and quarter maps. With ``--variants``, the Nordland
drive variants of ``benchmarks/drives.py`` (a query that stops, crawls and speeds up) against the
summer drive, full and memlog's half map (``benchmarks/drive_maps.py``'s maps).

    python benchmarks/matcher_defaults.py                  # Stromovka and Nordland
    python benchmarks/matcher_defaults.py --variants       # and the Nordland drive variants

Prints Markdown tables: R@1, R@5, AUC-PR, precision at 10 % and 50 % recall, ms per query.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
SHARED = ROOT.parent / "shared" / "data"

#: the settings compared (named configs): single frames, the matcher's defaults before they were
#: measured at camera resolution, a fixed speed, and today's defaults
SETTINGS: dict[str, dict[str, Any]] = {
    "single frames": {"length": 0, "rerank": False},
    "before: speeds 0:3, K 3, no prior": {"speeds": (0.0, 3.0), "candidates": 3, "speed_prior": 0.0,
                                          "rerank": False},
    "speed 1:1, K 10": {"speeds": (1.0, 1.0), "rerank": False},
    "default, --no-rerank": {"rerank": False},
    "default, --no-hmm": {"hmm": False},
    "default": {},
}
PAIRS = {"stromovka": ("stromovka_autumn.mcap", "stromovka_winter.mcap", "stromovka_truth.json"),
         "stromovka-drive": ("stromovka_drive_autumn.mcap", "stromovka_drive_winter.mcap", "stromovka_drive_truth.json"),
         "nordland": ("nordland_dev_summer.mcap", "nordland_dev_winter.mcap", "nordland_dev_truth.json")}
FRACTIONS: dict[str, float | None] = {"full": 1.0, "half": 0.5, "quarter": 0.25, "default": None}  # None: no --keep-fraction


def metrics(indices: np.ndarray, confidence: np.ndarray, truth: list[set[int]]) -> dict[str, float]:
    """R@1, R@5, AUC-PR and the precision at 10 % / 50 % recall (the best precision at a recall
    of at least that), ``indices`` being reference frame indices (-1: none)."""
    from memlog.evaluation.metrics import pr_curve

    ok = np.array([indices[i, 0] >= 0 and int(indices[i, 0]) in s for i, s in enumerate(truth)])
    r5 = np.mean([any(int(j) in s for j in indices[i, :5] if j >= 0) for i, s in enumerate(truth)])
    has = np.array([bool(s) for s in truth])
    curve = pr_curve(confidence, ok & has, has)

    def p_at(r: float) -> float:
        m = curve.recall >= r
        return float(curve.precision[m].max()) if m.any() else 0.0

    return {"r1": float(ok.mean()), "r5": float(r5), "auc": curve.auc, "p10": p_at(0.1), "p50": p_at(0.5)}


def _map(cache: Path, pair: str, which: str, args: Sequence[str] = (), ref: Path | None = None) -> Path:
    """``memlog map`` of the pair's reference (or of the log ``ref``) at a keep fraction, with more
    ``args`` (written once into ``cache``: give each set of ``args`` a cache of its own)."""
    out = cache / f"{pair}-{which}.mcap"
    if not out.with_suffix(".parquet").is_file() or not _current(out.with_suffix(".parquet")):
        from memlog.cli.app import main as memlog

        ref = ref or SHARED / PAIRS[pair][0]
        size = [] if FRACTIONS[which] is None else ["--keep-fraction", str(FRACTIONS[which])]
        if memlog(["-q", "map", str(ref), "-o", str(out), *size, *args]) != 0:
            raise SystemExit(f"memlog map {ref} failed")
    return out.with_suffix(".parquet")


def _current(parquet: Path) -> bool:
    """A cached map stores what today's ``memlog map`` stores (patch features with DINOv2)."""
    from memlog.outputs.descriptor_table import read_descriptors

    t = read_descriptors(parquet)
    return t.patches is not None or not t.meta.kind.startswith("dinov2")


def _query(cache: Path, pair: str, parquet: Path) -> Any:
    """The query's descriptors as localize makes them against the map ``parquet`` (cached)."""
    from memlog.descriptors.extract import describe_log
    from memlog.matching import SequenceConfig
    from memlog.io.base import FrameWindow
    from memlog.outputs.descriptor_table import read_cached, read_descriptors, write_descriptors
    from memlog.steps.localize import describer_for, map_still_distance

    ref = read_descriptors(parquet)
    qlog = SHARED / PAIRS[pair][1]
    still = map_still_distance(ref, parquet, SequenceConfig())
    path = parquet.with_suffix(".query.parquet")
    pat = ref.patch_pca is not None
    qt = read_cached(path, qlog, ref.meta, FrameWindow(), still, patches=pat,
                     patch_pca=ref.patch_pca) if path.is_file() else None
    if qt is None:
        qt, _report = describe_log(qlog, describer_for(ref), FrameWindow(), still_distance=still, patches=pat,
                                   patch_pca=ref.patch_pca)
        write_descriptors(path, qt)
    return ref, qt


def run(query: Any, ref: Any, truth: list[set[int]], settings: dict[str, Any], mask: np.ndarray | None = None
        ) -> dict[str, float]:
    from memlog.matching import SequenceConfig, match_tables

    t0 = time.perf_counter()
    res = match_tables(query, ref, SequenceConfig(**settings), k=10, ref_mask=mask)
    ms = (time.perf_counter() - t0) / max(1, len(query)) * 1e3
    frames = np.where(res.indices >= 0, ref.frame_index[np.maximum(res.indices, 0)], -1)
    sets = [truth[int(f)] for f in query.frame_index]
    return {**metrics(frames, res.confidence, sets), "ms": ms}


def fmt(m: dict[str, float]) -> str:
    return (f"{m['r1']:.3f} | {m['r5']:.3f} | {m['auc']:.3f} | {m['p10']:.2f} | {m['p50']:.2f} | "
            f"{m['ms']:.1f}")


HEADER = ("| data | map | matching | R@1 | R@5 | AUC-PR | P@10%R | P@50%R | ms/query |\n"
          "|---|---|---|---|---|---|---|---|---|")


def tab_pairs(cache: Path, maps: list[str]) -> None:
    print(HEADER)
    for pair, (_r, _q, truth_file) in PAIRS.items():
        truth = [set(m) for m in json.loads((SHARED / truth_file).read_text())["matches"]]
        for which in maps:
            ref, query = _query(cache, pair, _map(cache, pair, which))
            for name, settings in SETTINGS.items():
                print(f"| {pair} | {which} ({len(ref)}) | {name} | {fmt(run(query, ref, truth, settings))} |",
                      flush=True)


def tab_variants(cache: Path) -> None:
    """The Nordland drive variants (thumbnails, whitened on the reference drive) against the
    summer drive: its full map and memlog's half map."""
    from benchmarks import drive_maps as dm
    from benchmarks.sequence_table import truth_sets, whiten

    qs, refs, views = dm.load(cache / "drives")
    scores = dm.cheap_scores(cache / "drives")
    r = refs["base"]
    whiten(r, list(qs.values()))
    half = dm.memlog_mask(dm.score_table(r, views["base"], scores), 0.5)
    print("\n" + HEADER.replace("| data |", "| query drive |"))
    for qn, q in qs.items():
        truth = truth_sets(q, r)
        for which, mask in (("full", None), ("half", half)):
            for name, settings in SETTINGS.items():
                m = run(q.table(), r.table(), [set(s) for s in truth], settings, mask)
                print(f"| winter {qn} | {which} | {name} | {fmt(m)} |", flush=True)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cache", type=Path, default=Path("/tmp/memlog-matcher-defaults-2"))
    ap.add_argument("--maps", nargs="+", default=list(FRACTIONS), choices=list(FRACTIONS))
    ap.add_argument("--variants", action="store_true", help="also the Nordland drive variants")
    a = ap.parse_args()
    a.cache.mkdir(parents=True, exist_ok=True)
    tab_pairs(a.cache, a.maps)
    if a.variants:
        tab_variants(a.cache)
    return 0


if __name__ == "__main__":
    sys.exit(main())

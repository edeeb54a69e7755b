#!/usr/bin/env python3
"""Single frames, sequences and the patch re-rank, per dataset: the README's results table.

Every row is ``memlog.matching.match_tables`` (what ``memlog localize`` and
``memlog evaluate`` call) on maps written by ``memlog map`` and read back from their Parquet —
the re-rank reads only what the map stores (patch features projected by the map's PCA, float16) —
and query tables made as ``localize`` makes them (``benchmarks/matcher_defaults.py``'s maps and
queries, cached in ``--cache``).

Data (``../shared/data``): Stromovka autumn map / winter query (1024x384, DINOv2; maps of every
frame, memlog's half map and its default map — ``--keep-fraction 1 / 0.5``, no size: one frame per
``VIEW_STEP_CAP`` of view change; ``--maps quarter`` adds ``--keep-fraction 0.25``), the same places as drives with stops, crawls and fast stretches
(``stromovka-drive``: ``stromovka_drive_*``, the same maps) and Nordland summer / winter (64x32,
thumbnails: no patch features, so no re-rank and no drive HMM).

    python benchmarks/rerank_table.py        # Markdown table

Columns: R@1, R@5, AUC-PR, precision at 50 % recall (the best precision at a recall of at least
0.5), the map's Parquet bytes per frame (descriptor, patches and columns, compressed), and ms
per query of the matching (the query's network pass not counted).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from benchmarks.matcher_defaults import FRACTIONS, PAIRS, SHARED, _map, _query, run  # noqa: E402

ROWS = {"single frames": {"length": 0, "rerank": False},
        "single frames + re-rank": {"length": 0},
        "sequences": {"rerank": False},
        "sequences + re-rank (--no-hmm)": {"hmm": False},
        "sequences + re-rank + drive HMM (--no-ensemble)": {"ensemble": False},
        "sequences + re-rank + drive HMM + whitening ensemble (default)": {}}
MAPS = {"stromovka": ["full", "half", "default"], "stromovka-drive": ["full", "half", "default"], "nordland": ["full"]}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cache", type=Path, default=Path("/tmp/memlog-matcher-defaults-2"))
    ap.add_argument("--pairs", nargs="+", default=list(MAPS), choices=list(MAPS))
    ap.add_argument("--maps", nargs="+", choices=list(FRACTIONS), help="Stromovka's maps (default full, half, default)")
    ap.add_argument("--map-args", default="", metavar="ARGS",
                    help="more `memlog map` flags, e.g. \"--no-whiten\" (use a --cache of its own)")
    a = ap.parse_args()
    a.cache.mkdir(parents=True, exist_ok=True)
    print("| data | map (frames) | matching | R@1 | R@5 | AUC-PR | P@50%R | map bytes/frame | ms/query |\n"
          "|---|---|---|---|---|---|---|---|---|")
    for pair in a.pairs:
        truth = [set(m) for m in json.loads((SHARED / PAIRS[pair][2]).read_text())["matches"]]
        for which in (a.maps or MAPS[pair]) if pair.startswith("stromovka") else MAPS[pair]:
            parquet = _map(a.cache, pair, which, a.map_args.split())
            ref, query = _query(a.cache, pair, parquet)
            per_frame = parquet.stat().st_size / max(1, len(ref))
            for name, settings in ROWS.items():
                if ref.patches is None and "re-rank" in name:
                    if "default" not in name:
                        continue
                    name = "sequences (default; no patch features: no re-rank, no drive HMM)"
                m = run(query, ref, truth, settings)
                print(f"| {pair} | {which} ({len(ref)}) | {name} | {m['r1']:.3f} | {m['r5']:.3f} | {m['auc']:.3f} | "
                      f"{m['p50']:.2f} | {per_frame / 1024:.1f} KiB | {m['ms']:.1f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

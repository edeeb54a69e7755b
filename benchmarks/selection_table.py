#!/usr/bin/env python3
"""Selection modes against uniform and random maps of the same size, on the shared Nordland slice.

    python benchmarks/selection_table.py [--out DIR] [--fractions 0.25 0.5 0.75] [--descriptor thumbnail]

Runs ``memlog evaluate`` (summer = reference, winter = query, the truth file) once per selection
mode and keep fraction. The reference is scored once with every score (DIR/base/reference.scored.mcap)
and described once; each run reuses those files through hard links. Prints a Markdown table:
R@1 and AUC under the map-only protocol, R@1 and AUC under the paper protocol, coverage.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
SHARED = Path(os.environ.get("MEMLOG_SHARED_DATA", ROOT.parent / "shared" / "data"))


def run(out: Path, select: str, fraction: float, descriptor: str, extra: dict[str, Any]) -> dict[str, Any]:
    from memlog.config import ScoreConfig
    from memlog.evaluate.pipeline import EvalOptions, evaluate

    base = out / "base"
    d = out / (f"{select}-{fraction:g}" + ("-" + "-".join(f"{k}={v}" for k, v in sorted(extra.items())) if extra else ""))
    d.mkdir(parents=True, exist_ok=True)
    for name in ("reference.scored.mcap", f"reference.{descriptor}.parquet", f"query.{descriptor}.parquet"):
        if (base / name).is_file() and not (d / name).exists():
            os.link(base / name, d / name)
    res = evaluate(SHARED / "nordland_dev_summer.mcap", SHARED / "nordland_dev_winter.mcap", d, ScoreConfig(),
                   truth=SHARED / "nordland_dev_truth.json",
                   options=EvalOptions(descriptor=descriptor, select=select, keep_fraction=fraction,
                                       segment=extra, report=False))
    for name in ("reference.scored.mcap", f"reference.{descriptor}.parquet", f"query.{descriptor}.parquet"):
        if not (base / name).exists():
            base.mkdir(parents=True, exist_ok=True)
            os.link(d / name, base / name)
    return res


def row(name: str, r: dict[str, Any]) -> list[str]:
    def f(v: Any, std: Any = None) -> str:
        if v is None:
            return "-"
        return f"{v:.3f}" + (f" ± {std:.3f}" if std is not None else "")
    s, ps = r.get("std", {}), r["paper_protocol"].get("std", {})
    p = r["paper_protocol"]
    return [name, str(r["frames"]), f(r["coverage"], s.get("coverage")), f(r["recall@1"], s.get("recall@1")),
            f(r["auc"], s.get("auc")), f(p["recall@1"], ps.get("recall@1")), f(p["auc"], ps.get("auc"))]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default=str(ROOT / "out" / "nordland"))
    ap.add_argument("--fractions", type=float, nargs="+", default=[0.25, 0.5, 0.75])
    ap.add_argument("--descriptor", default="thumbnail")
    ap.add_argument("--segment", default="{}", help="JSON of extra segment settings to try")
    a = ap.parse_args()
    out = Path(a.out)
    seg_extra = json.loads(a.segment)
    print("| fraction | map | frames | coverage | R@1 (map-only) | AUC (map-only) | R@1 (paper) | AUC (paper) |")
    print("|---|---|---|---|---|---|---|---|")
    for fr in a.fractions:
        paper = run(out, "paper", fr, a.descriptor, {})
        seg = run(out, "segment", fr, a.descriptor, seg_extra)
        rows = [row("full map", paper["full"]), row("paper rule (calibrated)", paper["memorable"]),
                row("segment", seg["memorable"]), row("uniform", paper["uniform"]),
                row(f"random ({paper['random']['seeds']} seeds)", paper["random"])]
        if seg["memorable"]["frames"] != paper["memorable"]["frames"]:
            rows.append(row("uniform (segment size)", seg["uniform"]))
            rows.append(row("random (segment size)", seg["random"]))
        for r in rows:
            print(f"| {fr:g} | " + " | ".join(r) + " |")
        sys.stdout.flush()
    return 0


if __name__ == "__main__":
    sys.exit(main())

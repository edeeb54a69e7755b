#!/usr/bin/env python3
"""Maps of every size on drives as cameras record them, through the CLI as a user runs it.

    python benchmarks/drive_pair.py                      # Markdown table (about 15 minutes on 2 cores)
    python benchmarks/drive_pair.py --pairs drive --keep 0.5 --matcher default
    python benchmarks/drive_pair.py --table candidates --pairs drive aligned --keep 0.5   # (about 70 minutes)

Every row is ``memlog evaluate`` on a shared pair, whose maps are all written by ``memlog map``'s
writer and matched as ``memlog localize`` matches them (``tests/test_drive_pair.py`` checks that
its full and memorable rows equal ``memlog localize`` against the maps ``memlog map`` writes):

* **full**: ``memlog map --keep-fraction 1`` (every frame but the stops' repeats);
* **memorable**: ``memlog map --keep-fraction K`` (memlog's selection), or ``memlog map`` (``default``:
  its default size, one frame per ``VIEW_STEP_CAP`` of the drive's view change);
* **every k-th**, **its start offsets** (mean ± std of R@1 over every k-th frame shifted along the
  drive: ``memlog.selection.phase_masks``; "-" where there is one offset), **by distance** (evenly
  spaced along the travelled distance: the map drive's positions cut as ``memlog map`` cuts them by
  distance, each part's frame nearest its middle; "-" without positions) and **random** (mean of
  ``--seeds`` maps): maps of the memorable map's size.

Pairs (``../shared/data``): ``aligned``, the Stromovka autumn map / winter query, frame i of one is
place i of the other; ``drive``, the same places driven as a camera records a drive, with stops,
crawls and fast stretches, another speed profile on each drive (``stromovka_drive_*``; 1024x384,
DINOv2, patch re-rank); ``nordland``, the Nordland summer / winter slice (64x32, thumbnails: no
patch features, so neither the re-rank nor the drive HMM runs); ``drive-odometry``, the drive pair
with the odometry a robot records beside its camera on the map drive (a ``/odom`` topic at each
frame's place, 8 m apart: :func:`pair_files`), so the map is cut by distance where ``drive``'s is cut
by view change; the query and the matcher are the same, so its full map is ``drive``'s.
``--matcher``: ``default``,
``no-ensemble`` (``--no-ensemble``: the drive HMM in the map's whole whitening only) and ``no-hmm``
(``--no-hmm``).

Columns: R@1 / AUC-PR of each map under the map-only protocol, and the frames of the full and the
memorable map. Outputs are kept in ``--cache`` (each pair's descriptors are reused across rows).

``--table candidates``: does memorability (ResMem) choose better frames than the cheap rule, at camera
resolution? The memorable map of each pair and size written with ``memlog map --candidates K`` (ResMem
chooses between K frames of each segment, the best of them by (MS·SS·ES)^(1/3); K = 1, the default,
takes the frame of the best cheap bound (SS²·ES)^(1/3) nearest the segment's middle and runs no ResMem)
and with every frame a candidate (``all``: the exact best), with and without MS (``all, SS·ES only``:
``[select] weights = [0, 1, 1]`` in a ``--config`` file); default matcher, R@1 / AUC-PR, map-only.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
SHARED = ROOT.parent / "shared" / "data"

PAIRS = {"aligned": ("stromovka_autumn.mcap", "stromovka_winter.mcap", "stromovka_truth.json"),
         "drive": ("stromovka_drive_autumn.mcap", "stromovka_drive_winter.mcap", "stromovka_drive_truth.json"),
         "nordland": ("nordland_dev_summer.mcap", "nordland_dev_winter.mcap", "nordland_dev_truth.json")}
#: pairs whose map drive is a shared one with odometry added (:func:`pair_files`): name -> that pair
ODOMETRY = {"drive-odometry": "drive"}
KEEPS = ["0.5", "default"]  # "default": no --keep-fraction (one frame per VIEW_STEP_CAP of view change)
MATCHERS = {"default": [], "no-ensemble": ["--no-ensemble"], "no-hmm": ["--no-hmm"]}


NO_MS = "[select]\nweights = [0.0, 1.0, 1.0]\n"  # a --config file: selection without MS


def candidate_flags(no_ms: Path) -> dict[str, list[str]]:
    """The candidates table's columns: the flags of ``memlog evaluate`` that choose the memorable map
    (``no_ms``: a config file holding ``NO_MS``)."""
    return {"K = 1 (default)": ["--candidates", "1"], "K = 2": ["--candidates", "2"],
            "all (exact)": ["--candidates", "all"],
            "all, SS·ES only (no MS)": ["--candidates", "all", "--config", str(no_ms)]}


def pair_files(cache: Path, pair: str) -> tuple[Path, Path, Path]:
    """The reference log, query log and truth of ``pair``; an :data:`ODOMETRY` pair's reference is
    its shared map drive with a ``/odom`` topic at each frame's place (the truth's
    ``reference_places``, 8 m apart: :func:`benchmarks.drives.with_odometry`), written into
    ``cache`` once."""
    from benchmarks import drives

    ref, query, truth = (SHARED / f for f in PAIRS[ODOMETRY.get(pair, pair)])
    if pair not in ODOMETRY:
        return ref, query, truth
    odom = cache / f"{ref.stem}.odometry.mcap"
    if not odom.is_file():
        cache.mkdir(parents=True, exist_ok=True)
        drives.with_odometry(ref, json.loads(truth.read_text())["reference_places"], odom)
    return odom, query, truth


def run(cache: Path, pair: str, keep: str, matcher: str, seeds: int, extra: list[str] | None = None,
        outdir: str | None = None) -> dict[str, object]:
    """``memlog evaluate`` of ``pair`` at ``--keep-fraction keep`` (``default``: memlog's default size)
    with the matcher's flags ``MATCHERS[matcher]`` and ``extra`` flags, into ``cache/outdir`` (default:
    ``cache/pair``); its results.json."""
    from memlog.cli.app import main as memlog

    ref, query, truth = pair_files(cache, pair)
    out = cache / (outdir or pair)
    out.mkdir(parents=True, exist_ok=True)
    args = ["-q", "evaluate", "--reference", str(ref), "--query", str(query), "--truth", str(truth), "-o", str(out),
            *([] if keep == "default" else ["--keep-fraction", keep]), "--seeds", str(seeds), "--no-report",
            *MATCHERS[matcher], *(extra or [])]
    t0 = time.perf_counter()
    with contextlib.redirect_stdout(io.StringIO()):  # (evaluate's own table; the row is printed below)
        rc = memlog(args)
    if rc != 0:
        raise SystemExit(f"memlog {' '.join(args)} failed")
    res: dict[str, object] = json.loads((out / "results.json").read_text())
    res["bench_seconds"] = time.perf_counter() - t0
    return res


def cell(row: dict[str, float]) -> str:
    return f"{row['recall@1']:.3f} / {row['auc']:.3f}"


def spread(row: Any) -> str:
    """Mean ± std of R@1 over every k-th frame's start offsets."""
    return "-" if not row else f"{row['recall@1']:.3f} ± {row['std']['recall@1']:.3f} ({len(row['maps'])})"


def candidates_table(cache: Path, pairs: list[str], keeps: list[str]) -> None:
    """The memorable map chosen with and without memorability (:func:`candidate_flags`), default matcher."""
    cache.mkdir(parents=True, exist_ok=True)
    no_ms = cache / "no-ms.toml"
    no_ms.write_text(NO_MS)
    columns = candidate_flags(no_ms)
    print(f"| pair | keep | {' | '.join(columns)} | frames |\n|---|---|{'---|' * len(columns)}---|")
    for pair in pairs:
        for keep in keeps:
            # each column in its own directory: evaluate keeps one staged-score cache per map and settings,
            # so columns sharing a directory would score every frame with ResMem again on each rerun
            got = [run(cache, pair, keep, "default", 1, flags, outdir=f"{pair}-candidates-{i}")
                   for i, flags in enumerate(columns.values())]
            rows = [r["memorable"] for r in got]  # type: ignore[index]
            print(f"| {pair} | {keep} | {' | '.join(cell(m) for m in rows)} | "
                  f"{' / '.join(str(m['frames']) for m in rows)} |", flush=True)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cache", type=Path, default=Path("/tmp/memlog-drive-pair"))
    ap.add_argument("--pairs", nargs="+", default=[*PAIRS, *ODOMETRY], choices=[*PAIRS, *ODOMETRY])
    ap.add_argument("--keep", nargs="+", default=KEEPS,
                    help="sizes of the memorable map: keep fractions, or default (default: 0.5 default)")
    ap.add_argument("--matcher", nargs="+", default=["default", "no-ensemble"], choices=list(MATCHERS),
                    help="the matcher's settings (default: default no-ensemble; Nordland, which has no patch "
                         "features, runs the default only)")
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--table", choices=["maps", "candidates"], default="maps",
                    help="maps: every map row (default); candidates: the memorable map chosen with and without "
                         "memorability (ResMem), --candidates 1, 2 and all")
    a = ap.parse_args()
    if a.table == "candidates":
        candidates_table(a.cache, a.pairs, a.keep)
        return 0
    print("| pair | keep | matcher | full | memorable | every k-th | every k-th: start offsets, R@1 | by distance | "
          "random | frames (full / memorable) | s |\n|---|---|---|---|---|---|---|---|---|---|---|")
    for pair in a.pairs:
        for keep in a.keep:
            for matcher in a.matcher:
                if pair == "nordland" and matcher != "default":
                    continue  # thumbnails: no re-rank, so neither the drive HMM nor its ensemble runs
                r = run(a.cache, pair, keep, matcher, a.seeds)
                rows = {k: r[k] for k in ("full", "memorable", "uniform", "random")}
                print(f"| {pair} | {keep} | {matcher} | {cell(rows['full'])} | {cell(rows['memorable'])} | "
                      f"{cell(rows['uniform'])} | {spread(r.get('uniform_phases'))} | "
                      f"{cell(r['uniform_distance']) if 'uniform_distance' in r else '-'} | {cell(rows['random'])} | "
                      f"{rows['full']['frames']} / "
                      f"{rows['memorable']['frames']} | {r['bench_seconds']:.0f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

#!/usr/bin/env python3
"""Maps that do not hinge on a handful of frames: every map of a drive as a mask of its described
table, over every shared pair, with the spread of each figure.

Each pair's reference drive and query drive are described once (the map's descriptor as ``memlog
map`` chooses it: DINOv2-GeM with patch features at camera resolution, the thumbnail at 64x32),
unwhitened, stops found as ``memlog map`` finds them. A map is a mask over the reference rows:

* ``full``: every frame, a stop's frames once (as ``memlog evaluate``'s full map); ``default`` and ``half``: the frames ``memlog map`` keeps with its default
  size and with ``--keep-fraction 0.5`` (read from the map's Parquet; the selection does not depend
  on the whitening);
* ``every-k``: every k-th frame of the same size from **every** start offset (up to k);
  ``random``: ``--seeds`` random maps of the same size.

``--whiten``: ``drive`` (what ``memlog map`` does now: one whitening and one patch PCA per drive,
fitted on the drive's moving frames, shared by every map of it) or ``kept`` (what it did before:
each map's own, fitted on its kept frames). Every map is matched by ``memlog.matching.match_tables``
(what ``memlog localize`` runs), map-only, truth as the pair's truth file (±1 place).

Pairs (``../shared/data``): ``stromovka`` (frame-aligned, 1024x384), ``stromovka-drive`` (the same
places as drives with stops and speed changes), ``nordland`` (dev summer/winter, 64x32), and two of
``benchmarks/drives.py``'s Nordland drive variants: ``nordland-mixed`` (the summer drive against a
winter query that stops, crawls and speeds up) and ``nordland-recorded`` (both drives standing at
start and end, stopping, crawling and speeding up, each its own way).

    python benchmarks/map_spread.py                        # the maps table (about 15 minutes)
    python benchmarks/map_spread.py --whiten kept          # the same with each map's own whitening
    python benchmarks/map_spread.py --stages               # every matcher stage on and off

The stage table gives, per stage, the mean over the pairs of R@1 with the stage minus R@1
without it, over the memorable map and the every-k-th maps of every offset at default and half
size, with its spread (the standard error of that mean over the pairs). R@1 is given under the
pairs' truth files and under a stop-aware truth: a reference frame of the same stop as a true
frame counts as right (Nordland's truth is by frame index, so a standing train's frame matched
to another frame of its stop, the same place, counts as wrong there).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
SHARED = ROOT.parent / "shared" / "data"

PAIRS = {"stromovka": ("stromovka_autumn.mcap", "stromovka_winter.mcap", "stromovka_truth.json"),
         "stromovka-drive": ("stromovka_drive_autumn.mcap", "stromovka_drive_winter.mcap",
                             "stromovka_drive_truth.json"),
         "nordland": ("nordland_dev_summer.mcap", "nordland_dev_winter.mcap", "nordland_dev_truth.json"),
         "nordland-mixed": ("base", "mixed", None),
         "nordland-recorded": ("recorded", "recorded", None)}
SIZES = {"default": None, "half": 0.5}

#: every stage and option of the matcher, as the settings that turn it off (or change it)
STAGES: dict[str, dict[str, Any]] = {
    "sequences (off: single frames)": {"length": 0},
    "stops (off: --keep-stops)": {"stops": False},
    "speed prior (off: 0)": {"speed_prior": 0.0},
    "window scaled on sparse maps (off)": {"scale_length": False},
    "patch re-rank (off: --no-rerank)": {"rerank": False},
    "drive HMM (off: --no-hmm)": {"hmm": False},
    "whitening ensemble (off: --no-ensemble)": {"ensemble": False},
}


@dataclass
class Pair:
    """One pair: the reference and query drives described (unwhitened), the truth by query row
    (reference rows; ``stop_truth``: each true frame's whole stop), and the memorable maps' masks by size."""

    name: str
    ref: Any
    query: Any
    truth: list[set[int]]
    stop_truth: list[set[int]]
    memorable: dict[str, np.ndarray]


def _logs(cache: Path, name: str) -> tuple[Path, Path, list[set[int]]]:
    """The pair's reference and query logs and its truth (query frame index -> reference frame indices)."""
    ref, query, truth = PAIRS[name]
    if truth is not None:
        data = json.loads((SHARED / truth).read_text())
        return SHARED / ref, SHARED / query, [set(m) for m in data["matches"]]
    from benchmarks import drives

    out = []
    for which, source, v in (("ref", "nordland_dev_summer.mcap", ref), ("query", "nordland_dev_winter.mcap", query)):
        path = cache / f"{name}.{which}.mcap"
        if not path.is_file():
            drives.write_variant(SHARED / source, drives.variant(v), path)
        out.append(path)
    t = drives.truth(drives.variant(query), drives.variant(ref))
    return out[0], out[1], [set(m) for m in t["matches"]]


def _map_frames(cache: Path, name: str, log: Path, size: str) -> tuple[np.ndarray, str]:
    """The frame indices ``memlog map`` keeps at ``size`` and the descriptor it chose (cached)."""
    out = cache / f"{name}.{size}.json"
    if not out.is_file():
        from memlog.cli.app import main as memlog
        from memlog.outputs.descriptor_table import read_descriptors

        mcap = cache / f"{name}.{size}.mcap"
        frac = [] if SIZES[size] is None else ["--keep-fraction", str(SIZES[size])]
        if memlog(["-q", "map", str(log), "-o", str(mcap), *frac]) != 0:
            raise SystemExit(f"memlog map {log} failed")
        t = read_descriptors(mcap.with_suffix(".parquet"))
        out.write_text(json.dumps({"frames": t.frame_index.tolist(), "kind": t.meta.kind}))
    d = json.loads(out.read_text())
    return np.asarray(d["frames"], dtype=np.int64), str(d["kind"])


def _described(cache: Path, log: Path, kind: str, tag: str) -> Any:
    """``log`` described unwhitened with raw patch features (cached)."""
    from memlog.descriptors.extract import describe_log
    from memlog.descriptors.registry import make_describer
    from memlog.io.base import FrameWindow
    from memlog.outputs.descriptor_table import read_descriptors, write_descriptors

    path = cache / f"{tag}.{kind}.raw.parquet"
    if path.is_file():
        return read_descriptors(path)
    table, _ = describe_log(log, make_describer(kind), FrameWindow())
    write_descriptors(path, table)
    return table


def load(cache: Path, name: str) -> Pair:
    ref_log, q_log, truth_frames = _logs(cache, name)
    masks, kind = {}, ""
    for size in SIZES:
        frames, kind = _map_frames(cache, name, ref_log, size)
        masks[size] = frames
    ref = _described(cache, ref_log, kind, f"{name}.ref")
    query = _described(cache, q_log, kind, f"{name}.query")
    rows = {int(f): r for r, f in enumerate(ref.frame_index)}
    truth = [{rows[j] for j in truth_frames[int(f)] if j in rows} if int(f) < len(truth_frames) else set()
             for f in query.frame_index]
    return Pair(name, ref, query, truth, stop_aware(ref, truth),
                {s: np.isin(ref.frame_index, m) for s, m in masks.items()})


def stop_aware(ref: Any, truth: list[set[int]]) -> list[set[int]]:
    """The truth with every reference frame of a true frame's stop (the same moving index) added: a
    frame-indexed truth (Nordland's: frame i is place i, ±1) counts a standing train's frame matched
    to another frame of the same stop as wrong, though it shows the same place."""
    if ref.moving_index is None:
        return truth
    by_mi: dict[int, set[int]] = {}
    for r, m in enumerate(ref.moving_index.tolist()):
        by_mi.setdefault(int(m), set()).add(r)
    return [set().union(*(by_mi[int(ref.moving_index[r])] for r in t)) if t else set() for t in truth]


def moving_rows(table: Any) -> np.ndarray:
    """Rows where the camera moved since the previous row (each stop's first frame counts)."""
    from memlog.matching import standing_rows

    return ~standing_rows(table)


def in_space(pair: Pair, fit_rows: np.ndarray) -> tuple[Any, Any]:
    """Both drives whitened by a whitening, and their patches projected by a patch PCA, fitted on
    the reference rows ``fit_rows`` (as ``memlog map`` fits them)."""
    from memlog.descriptors.patches import PatchPCA
    from memlog.descriptors.whitening import fit_whitening

    ref, q = pair.ref, pair.query
    pca = PatchPCA.fit(ref.patches[fit_rows]) if ref.patches is not None else None
    w = fit_whitening(ref.descriptors[fit_rows]) if fit_rows.sum() >= 32 else None
    out = []
    for t, keep in ((ref, True), (q, False)):
        t = t.projected(pca)
        if w is not None:
            meta = replace(t.meta, dim=w.dim_out, whitening=w.sha256)
            t = replace(t, descriptors=w.apply(t.descriptors), meta=meta, whitening=w if keep else None)
        out.append(t)
    return out[0], out[1]


def r1(pair: Pair, ref: Any, q: Any, mask: np.ndarray, settings: dict[str, Any]) -> tuple[float, float]:
    """R@1 under the pair's truth and under its stop-aware truth."""
    from memlog.matching import SequenceConfig, match_tables

    res = match_tables(q, ref, SequenceConfig(**settings), k=1, ref_mask=mask)
    best = res.indices[:, 0]
    return tuple(float(np.mean([b >= 0 and int(b) in t for b, t in zip(best, truth)]))  # type: ignore[return-value]
                 for truth in (pair.truth, pair.stop_truth))


def maps_of(pair: Pair, seeds: int, offsets: bool = True) -> dict[str, list[np.ndarray]]:
    """Masks by name: full; memorable, every k-th (every offset) and random at each size."""
    from memlog.selection import phase_masks, random_masks

    n = len(pair.ref)
    out: dict[str, list[np.ndarray]] = {"full": [moving_rows(pair.ref)]}
    for size, m in pair.memorable.items():
        k = int(m.sum())
        out[f"{size}: memorable"] = [m]
        out[f"{size}: every-k"] = list(phase_masks(n, k))
        if seeds:
            out[f"{size}: random"] = list(random_masks(n, k, range(seeds)))
    return out


def _space(pair: Pair, whiten: str, mask: np.ndarray, cache: dict[Any, Any]) -> tuple[Any, Any]:
    key = "drive" if whiten == "drive" else mask.tobytes()
    if key not in cache:
        cache[key] = in_space(pair, moving_rows(pair.ref) if whiten == "drive" else mask)
    return cache[key]


def maps_table(pairs: list[str], cache: Path, whiten: str, seeds: int) -> None:
    print(f"whitening: {whiten}\n")
    print("| pair | map (frames) | R@1 mean | std | min | max | maps | stop-aware R@1 mean | std |\n"
          "|---|---|---|---|---|---|---|---|---|")
    for name in pairs:
        pair = load(cache, name)
        spaces: dict[Any, Any] = {}
        t0 = time.perf_counter()
        for label, masks in maps_of(pair, seeds).items():
            both = np.array([r1(pair, *_space(pair, whiten, m, spaces), m, {}) for m in masks])
            vals, stop = both[:, 0], both[:, 1]
            print(f"| {name} | {label} ({int(masks[0].sum())}) | {vals.mean():.3f} | {vals.std():.3f} | "
                  f"{vals.min():.3f} | {vals.max():.3f} | {len(vals)} | {stop.mean():.3f} | {stop.std():.3f} |",
                  flush=True)
        print(f"<!-- {name}: {time.perf_counter() - t0:.0f} s -->", flush=True)


def stages_table(pairs: list[str], cache: Path, whiten: str) -> None:
    """Per stage: mean over pairs of (R@1 with it - R@1 without it), averaged over the memorable
    and every-k-th maps at default and half size, with the standard error over the pairs; under the
    pairs' truth and under the stop-aware truth (the decision: a stage is kept when its mean gain
    under the stop-aware truth is above its spread)."""
    base: dict[str, np.ndarray] = {}
    diffs: dict[str, dict[str, np.ndarray]] = {s: {} for s in STAGES}
    for name in pairs:
        pair = load(cache, name)
        spaces: dict[Any, Any] = {}
        masks = [m for label, ms in maps_of(pair, 0).items() if label != "full" for m in ms]

        def mean_r1(settings: dict[str, Any]) -> np.ndarray:
            return np.mean([r1(pair, *_space(pair, whiten, m, spaces), m, settings) for m in masks], axis=0)
        base[name] = mean_r1({})
        for stage, off in STAGES.items():
            diffs[stage][name] = base[name] - mean_r1(off)
            print(f"<!-- {name} {stage}: {diffs[stage][name][0]:+.3f} / stop-aware {diffs[stage][name][1]:+.3f} -->",
                  flush=True)
    for col, truth in ((1, "stop-aware truth (the decision)"), (0, "the pairs' truth files")):
        print(f"\nwhitening: {whiten}; maps: memorable and every-k-th (every offset), default and half size; {truth}\n")
        print("| stage | " + " | ".join(pairs) + " | mean gain | spread | kept |")
        print("|---|" + "---|" * len(pairs) + "---|---|---|")
        print("| (default R@1) | " + " | ".join(f"{base[p][col]:.3f}" for p in pairs) + " | | | |")
        for stage in STAGES:
            d = np.array([diffs[stage][p][col] for p in pairs])
            se = d.std(ddof=1) / np.sqrt(len(d)) if len(d) > 1 else float("nan")
            print(f"| {stage} | " + " | ".join(f"{v:+.3f}" for v in d) +
                  f" | {d.mean():+.3f} | {se:.3f} | {'yes' if d.mean() > se else 'no'} |", flush=True)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cache", type=Path, default=Path("/tmp/memlog-map-spread"))
    ap.add_argument("--pairs", nargs="+", default=list(PAIRS), choices=list(PAIRS))
    ap.add_argument("--whiten", choices=("drive", "kept"), default="drive")
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--stages", action="store_true")
    a = ap.parse_args()
    if not SHARED.is_dir():
        raise SystemExit(f"{SHARED} not found: the shared data is needed")
    a.cache.mkdir(parents=True, exist_ok=True)
    if a.stages:
        stages_table(a.pairs, a.cache, a.whiten)
    else:
        maps_table(a.pairs, a.cache, a.whiten, a.seeds)
    return 0


if __name__ == "__main__":
    sys.exit(main())

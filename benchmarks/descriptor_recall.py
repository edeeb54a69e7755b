#!/usr/bin/env python3
"""Recall@N / AUC / speed of memlog's descriptors on the Nordland dev slice.

References: ``nordland_dev_summer.mcap``; queries: ``nordland_dev_winter.mcap`` (800 places,
64 x 32 PNG frames); truth: ``nordland_dev_truth.json`` (+-1 frame). Every frame is in the
map (no selection), so the map-only and paper protocols coincide; AUC is the paper's
trapezoid rule over the per-query PR points. ``same>far`` is the share of places whose
winter frame is more similar to its own summer frame than to the summer frame 400 places
away. ``ms/img`` is the time to describe one image (CPU, batch 16, all threads);
``ms/query`` the time to match one query against all references.

DINOv2 kinds that share a preprocessing and a network output (final or middle block) are
computed from one backbone pass per batch (the tokens are pooled once per kind); their
``ms/img`` is the backbone time plus that kind's pooling time, i.e. what ``describe`` costs on
its own. Multi-scale kinds run on their own.

Usage::

    python benchmarks/descriptor_recall.py [--limit 200] [--kinds thumbnail dinov2-cls dinov2-gem]
        [--kinds "dinov2-gem:resize=letterbox"] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from memlog.descriptors.registry import make_describer
from memlog.evaluation.metrics import evaluate_map_only, parse_truth
from memlog.descriptors.search import match, time_per_query

TOPIC = "/camera/image_raw/compressed"
DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def load_frames(path: Path, limit: int | None) -> list[np.ndarray]:
    """Decode the CompressedImage frames of ``TOPIC`` in log order."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    frames: list[np.ndarray] = []
    with open(path, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        for _s, _c, _m, msg in reader.iter_decoded_messages(topics=[TOPIC], log_time_order=True):
            img = cv2.imdecode(np.frombuffer(bytes(msg.data), np.uint8), cv2.IMREAD_COLOR)
            if img is None:
                raise SystemExit(f"{path}: could not decode a frame")
            frames.append(img)
            if limit is not None and len(frames) >= limit:
                break
    return frames


def parse_kind(spec: str) -> tuple[str, str, dict[str, Any]]:
    """``name[:key=value,...]`` -> (label, name, overrides); values parsed as JSON if possible."""
    name, _, rest = spec.partition(":")
    overrides: dict[str, Any] = {}
    for item in filter(None, rest.split(",")):
        key, _, value = item.partition("=")
        try:
            overrides[key] = json.loads(value)
        except ValueError:
            overrides[key] = value
    return spec, name, overrides


def describe_all(kinds: list[tuple[str, str, dict[str, Any]]], images: list[np.ndarray]) -> dict[str, tuple[np.ndarray, float]]:
    """label -> (descriptors, seconds per image)."""
    from memlog.descriptors.dinov2 import DinoV2Describer, pool_tokens, preprocess

    out: dict[str, tuple[np.ndarray, float]] = {}
    groups: dict[tuple[Any, ...], list[tuple[str, Any]]] = {}
    for label, name, overrides in kinds:
        d = make_describer(name, **overrides)
        if isinstance(d, DinoV2Describer) and d.scales == (1.0,):  # one pass of the same output: shared
            groups.setdefault((d.resize, d.batch_size, d.layer), []).append((label, d))
        else:
            t0 = time.perf_counter()
            x = d.describe(images)
            out[label] = (x, (time.perf_counter() - t0) / len(images))
    for (resize, batch, _layer), members in groups.items():
        backbone = members[0][1]
        pooled: dict[str, list[np.ndarray]] = {label: [] for label, _ in members}
        pool_time: dict[str, float] = {label: 0.0 for label, _ in members}
        t_tokens = 0.0
        for start in range(0, len(images), batch):
            t0 = time.perf_counter()
            x, mask = preprocess(images[start : start + batch], resize)
            tok = backbone.forward(x)
            t_tokens += time.perf_counter() - t0
            for label, d in members:
                t1 = time.perf_counter()
                pooled[label].append(pool_tokens(tok, d.pooling, d.gem_p, mask))
                pool_time[label] += time.perf_counter() - t1
        for label, _ in members:
            out[label] = (np.concatenate(pooled[label]), (t_tokens + pool_time[label]) / len(images))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA, help="folder with the nordland_dev_* files")
    ap.add_argument("--kinds", nargs="+", default=["thumbnail", "dinov2-cls", "dinov2-gem"])
    ap.add_argument("--limit", type=int, default=None, help="use only the first N places")
    ap.add_argument("--prepare", action="store_true", help="prepare the DINOv2 model first")
    ap.add_argument("--json", type=Path, default=None, help="also write the results as JSON")
    args = ap.parse_args(argv)

    if args.prepare:
        from memlog.models.dinov2 import prepare_dinov2

        prepare_dinov2()
    refs = load_frames(args.data / "nordland_dev_summer.mcap", args.limit)
    queries = load_frames(args.data / "nordland_dev_winter.mcap", args.limit)
    n_q, n_r = len(queries), len(refs)
    truth = parse_truth(args.data / "nordland_dev_truth.json", 800, 800)[:n_q]
    truth = [{i for i in s if i < n_r} for s in truth]
    kinds = [parse_kind(k) for k in args.kinds]
    print(f"Nordland dev: {n_r} summer references, {n_q} winter queries, chance R@1 ~ {3 / n_r:.4f}", file=sys.stderr)

    ref_desc = describe_all(kinds, refs)
    query_desc = describe_all(kinds, queries)
    rows: list[dict[str, Any]] = []
    full_map = np.ones(n_r, dtype=bool)
    for label, _name, _ in kinds:
        r, t_r = ref_desc[label]
        q, t_q = query_desc[label]
        idx, sim = match(q, r, k=10)
        res = evaluate_map_only((idx, sim), truth, full_map, ns=(1, 5, 10))
        far = (np.arange(n_q) + n_r // 2) % n_r
        same_far = float(np.mean(np.sum(q * r[:n_q], axis=1) > np.sum(q * r[far], axis=1)))
        timing = time_per_query(q, r, repeats=5)
        rows.append({
            "kind": label,
            "dim": int(r.shape[1]),
            "recall@1": res.recall_at[1],
            "recall@5": res.recall_at[5],
            "recall@10": res.recall_at[10],
            "auc": res.auc,
            "same>far": same_far,
            "ms_per_image": 1000 * (t_r * n_r + t_q * n_q) / (n_r + n_q),
            "ms_per_query": 1000 * timing.seconds_per_query,
        })
    header = f"{'kind':34s} {'dim':>5s} {'R@1':>6s} {'R@5':>6s} {'R@10':>6s} {'AUC':>6s} {'same>far':>8s} {'ms/img':>8s} {'ms/query':>8s}"
    print(header)
    print("-" * len(header))
    for row in rows:
        print(f"{row['kind']:34s} {row['dim']:5d} {row['recall@1']:6.3f} {row['recall@5']:6.3f} {row['recall@10']:6.3f} "
              f"{row['auc']:6.3f} {row['same>far']:8.3f} {row['ms_per_image']:8.2f} {row['ms_per_query']:8.3f}")
    if args.json:
        args.json.write_text(json.dumps({"n_refs": n_r, "n_queries": n_q, "results": rows}, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

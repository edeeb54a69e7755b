#!/usr/bin/env python3
"""Maps of drives that stop, crawl and speed up: memlog's selection against every k-th frame.

    python benchmarks/drive_maps.py [--scores SCORED.mcap] [--tables stillness maps candidates]

Reference drives: variants of the shared Nordland summer drive (:mod:`benchmarks.drives`):
``base`` (the drive as recorded; it already stands still at stations, e.g. frames 128-175),
``stops``, ``mixed`` and ``recorded`` (standing at the start and the end, stops, crawls at a
third of the speed, stretches at 2x and 3x) and ``double-rate`` (20 Hz, every place twice).
Queries: variants of the winter drive (``--queries``, default ``base``, the drive as recorded,
and ``mixed`` and ``recorded``, which stop, crawl and speed up as the reference drives of those
names do, with their own noise), truth by source place (+-1 place). Descriptors: the whitened
thumbnail (memlog's ``auto`` for 64x32 frames), whitening fitted on the reference drive; every
map is searched map-only (only its frames) and the query is matched as ``memlog localize`` matches it by default (sequences of +-10 frames,
speeds 0..3, stops left out: both drives along their moving index, a standing query frame taking
its stop's match), with stops kept (``--keep-stops``: along the frame index) and frame by frame.
Each sequence table is followed by R@1 under a stop-aware truth (a stop's frames are one place:
a frame of a standing camera matched to any frame of the right stop is right).

Scores: a variant frame has the scores of its source frame (MS, SS, ES from ``--scores``, an
annotated MCAP of the summer drive scored with ``memlog score --all-scores``; the variant's
noise is 2 grey levels); its view vector (:func:`memlog.scoring.scorer.view_vector`) is computed
from the variant frame itself, noise included, so stops are found from the images as ``memlog
map`` finds them. Without ``--scores`` SS and ES come from memlog's scorer run on the summer
drive here (its cheap stage, cached), MS is missing and only the tables that do not need MS run
(the default map does not: one candidate per segment).

Maps (as many frames as ``--fractions`` of the drive's frames):

* ``memlog``: the default selection (segments by view change, stops left out, the best of one
  candidate per segment: ``memlog map`` with default settings);
* ``memlog, time segments``: the same with segments by time (memlog's default before it
  looked at the drive);
* ``every k-th``: evenly spaced frame indices (and its noise: R@1 of the maps of k-4..k+4 evenly
  spaced frames, whose spacing falls on other frames; and the query's: a 95 % interval of memlog's
  R@1 minus every k-th frame's by a circular bootstrap over blocks of 21 source places, a
  sequence's length, each block bringing every query frame that shows one of its places);
  ``random``: 20 seeds, mean +- std;
* ``candidates`` table: K = 1, 2 and all (exact) candidates per segment (MS choosing between
  them for K >= 2), per query drive and pooled over them.

With several query drives the maps table is followed by R@1 pooled over them (every query frame
of every drive counts once), with the same baselines.

Prints Markdown tables (R@1 / AUC-PR, map-only).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from benchmarks import drives  # noqa: E402
from benchmarks.sequence_table import SHARED, Drive, _describe, table, truth_sets, whiten  # noqa: E402

REFERENCES = ["base", "stops", "mixed", "recorded", "double-rate"]
QUERIES = ["base", "mixed", "recorded"]
GENERATOR = "2"
#: a query variant's noise seed (``base`` keeps the seed of the tables measured before query variants)
QUERY_SEEDS = {"base": 100, "mixed": 101, "recorded": 102}


def load(cache: Path, queries: list[str] = QUERIES) -> tuple[dict[str, Drive], dict[str, Drive], dict[str, np.ndarray]]:
    """(query drives, reference drives, view vectors of each reference drive's frames)."""
    from memlog.io import open_log
    from memlog.scoring.scorer import view_vector

    cache.mkdir(parents=True, exist_ok=True)
    out: dict[str, Drive] = {}
    qs: dict[str, Drive] = {}
    views: dict[str, np.ndarray] = {}
    jobs = ([("winter", q, QUERY_SEEDS.get(q, 110 + i)) for i, q in enumerate(queries)]
            + [("summer", r, 200 + i) for i, r in enumerate(REFERENCES)])
    for drive, name, seed in jobs:
        v = drives.variant(name)
        log = cache / f"g{GENERATOR}-nordland_{drive}_{name}.mcap"
        if not log.is_file():
            drives.write_variant(SHARED / drives.DRIVES[drive], v, log, positions=False, seed=seed)
        d = Drive(_describe(log, cache), v)
        if drive == "winter":
            qs[name] = d
            continue
        out[name] = d
        vpath = cache / f"{log.stem}.views.npy"
        if not vpath.is_file():
            with open_log(log) as r:
                np.save(vpath, np.stack([view_vector(f.decode_bgr()) for f in r.frames()]).astype(np.float32))
        views[name] = np.load(vpath)
    return qs, out, views


def cheap_scores(cache: Path) -> dict[str, np.ndarray]:
    """SS and ES of every summer frame (by frame index = place), computed with memlog's scorer
    (the cheap stage: detector and entropy, no ResMem) and cached; MS missing (NaN)."""
    path = cache / "nordland_summer.cheap-scores.npz"
    if not path.is_file():
        from memlog.io import open_log
        from memlog.scoring.config import ScoreConfig
        from memlog.scoring.scorer import Scorer

        scorer = Scorer(ScoreConfig(all_scores=True))
        ss, es = [], []
        with open_log(SHARED / drives.DRIVES["summer"]) as r:
            for f in r.frames():
                c = scorer.cheap(f.decode_bgr())
                ss.append(round(c.ss, 6))
                es.append(round(float(c.es if c.es is not None else np.nan), 6))
        np.savez(path, ss=np.array(ss), es=np.array(es))
    z = np.load(path)
    return {"ss": z["ss"], "es": z["es"], "ms": np.full(len(z["ss"]), np.nan)}


def source_scores(path: Path | None) -> dict[str, np.ndarray] | None:
    """MS, SS, ES of every summer frame (by frame index = place) from an annotated MCAP."""
    if path is None:
        return None
    from memlog.outputs.annotated import read_scores

    recs = next(iter(read_scores(path).values()))
    n = max(r["frame_index"] for r in recs) + 1
    out = {k: np.full(n, np.nan) for k in ("ms", "ss", "es")}
    for r in recs:
        for k in out:
            if r.get(k) is not None:
                out[k][r["frame_index"]] = float(r[k])
    return out


def score_table(r: Drive, view: np.ndarray, scores: dict[str, np.ndarray] | None) -> Any:
    from memlog.selection import ScoreTable

    p = r.variant.places
    nan = np.full(len(p), np.nan)
    ms, ss, es = ((scores[k][p] for k in ("ms", "ss", "es")) if scores is not None else (nan, np.ones(len(p)), nan))
    if scores is None:
        es = np.ones(len(p))
        ms = np.zeros(len(p))
    return ScoreTable(index=np.arange(len(p)), t_ns=r.stamp_ns - r.stamp_ns[0], ms=ms, ss=ss, es=es, view=view)


def _groups(moving: np.ndarray) -> list[np.ndarray]:
    """Rows of each value of ``moving`` (a stop's frames share one)."""
    _u, inv = np.unique(moving, return_inverse=True)
    order = np.argsort(inv, kind="stable")
    return np.split(order, np.flatnonzero(np.diff(inv[order])) + 1)


def stop_truth(q: Drive, r: Drive) -> list[set[int]]:
    """Truth where a stop's frames are one place: a query frame's matches are the reference
    frames of every stop that holds a match of any frame of its own stop."""
    truth = truth_sets(q, r)
    r_group = np.empty(len(r), np.int64)
    r_groups = _groups(r.moving)
    for g, rows in enumerate(r_groups):
        r_group[rows] = g
    out: list[set[int]] = [set() for _ in truth]
    for rows in _groups(q.moving):
        hit = {int(r_group[j]) for i in rows for j in truth[i]}
        s = {int(j) for g in hit for j in r_groups[g]}
        for i in rows:
            out[i] = s
    return out


def summary(o: tuple[np.ndarray, float, np.ndarray]) -> tuple[float, float, float]:
    """(R@1, AUC-PR, R@1 with a stop's frames as one place) of :func:`outcomes`."""
    correct, auc, loose = o
    return float(correct.mean()), auc, float(loose.mean())


def outcomes(q: Drive, r: Drive, mask: np.ndarray | None, seq: Any) -> tuple[np.ndarray, float, np.ndarray]:
    """Per query frame, whether its best match in the map ``mask`` is right (and with a stop's
    frames as one place), and the AUC-PR; matched as ``memlog localize`` matches (with
    ``seq.stops``: along the moving index, a standing query frame taking its stop's match)."""
    from dataclasses import replace

    from memlog.matching import match_tables
    from memlog.evaluation.metrics import pr_curve

    res = match_tables(q.table(), r.table(), replace(seq, coordinate="frames"), k=1, ref_mask=mask)
    truth = truth_sets(q, r)
    best = res.indices[:, 0]
    correct = np.array([b >= 0 and int(b) in s for b, s in zip(best, truth)])
    curve = pr_curve(res.confidence, correct, np.array([bool(s) for s in truth]))
    loose = np.array([b >= 0 and int(b) in s for b, s in zip(best, stop_truth(q, r))])
    return correct, curve.auc, loose


def paired_interval(pairs: list[tuple[Drive, np.ndarray, np.ndarray]], block: int = 21, n: int = 2000,
                    seed: int = 0) -> tuple[float, float]:
    """95 % interval of R@1(a) - R@1(b) over the query frames of one or more query drives
    (``pairs``: (query drive, per query frame right or not for map a, for map b)) by a block
    bootstrap over the *source places*: blocks of ``block`` consecutive places (a sequence's 21),
    each bringing every query frame of every drive that shows one of its places. Neighbouring
    queries share most of their sequences, a stop's frames are one place, and the query drives
    are re-timings of one winter drive: resampling places keeps all three dependencies together
    (for a query drive that shows every place once, in order, this is the moving-block bootstrap
    over its frames, with circular blocks)."""
    n_places = 1 + max(int(q.variant.places.max()) for q, _a, _b in pairs)
    diff = np.zeros(n_places)
    count = np.zeros(n_places)
    for q, x, y in pairs:
        np.add.at(diff, q.variant.places, np.asarray(x, np.float64) - np.asarray(y, np.float64))
        np.add.at(count, q.variant.places, 1.0)
    # circular blocks (Politis & Romano): every place is equally likely to be drawn, the drive's
    # first and last places too (a stop at the start or the end weighs as much as one mid-drive)
    starts = np.random.default_rng(seed).integers(0, n_places, size=(n, -(-n_places // block)))
    idx = ((starts[:, :, None] + np.arange(block)) % n_places).reshape(n, -1)[:, :n_places]
    lo, hi = np.percentile(diff[idx].sum(axis=1) / count[idx].sum(axis=1), [2.5, 97.5])
    return float(lo), float(hi)


def fmt(v: tuple[float, ...]) -> str:
    return f"{v[0]:.3f} / {v[1]:.3f}"


def fmt_rand(vals: list[tuple[float, ...]]) -> str:
    a = np.asarray(vals)
    return f"{a[:, 0].mean():.3f} ± {a[:, 0].std():.3f} / {a[:, 1].mean():.3f}"


def matchers() -> dict[str, Any]:
    from memlog.matching import SequenceConfig

    return {"sequence": SequenceConfig(), "sequence, stops kept (--keep-stops)": SequenceConfig(stops=False),
            "single": SequenceConfig(length=0)}


def memlog_mask(t: Any, frac: float, shortlist: int | None = 1, **sel: Any) -> np.ndarray:
    from memlog.selection.config import SelectionConfig

    s = SelectionConfig(keep_fraction=frac, **sel).run(t, shortlist=shortlist)
    return np.asarray(s.keep, dtype=bool)


def pooled_r1(results: list[tuple[np.ndarray, float, np.ndarray]]) -> float:
    """R@1 over the query frames of several drives (each :func:`outcomes`), every frame once."""
    return float(np.concatenate([o[0] for o in results]).mean())


def tab_maps(queries: dict[str, Drive], refs: dict[str, Drive], views: dict[str, np.ndarray], scores: Any,
             fracs: list[float], names: list[str]) -> None:
    from memlog.selection import random_masks, uniform_mask
    from memlog.scoring.motion import still_rows

    for mname in names:
        seq = matchers()[mname]
        rows, loose, prow = [], [], []
        for rname, r in refs.items():
            whiten(r, list(queries.values()))
            t = score_table(r, views[rname], scores)
            still = 0 if t.view is None else int(still_rows(t.view).sum())
            for frac in fracs:
                m = memlog_mask(t, frac)
                k = int(m.sum())
                size = f"{frac:g} ({k})"
                maps = {"full": None, "memlog": m, "best bound": memlog_mask(t, frac, centre_tolerance=0.0),
                        "time": memlog_mask(t, frac, segment_by="time"), "every k-th": uniform_mask(len(r), k)}
                # every k-th frame's own noise: the maps of k-4..k+4 evenly spaced frames (the phase of the spacing)
                near = [uniform_mask(len(r), kk) for kk in range(k - 4, k + 5)]
                rand = list(random_masks(len(r), k, range(20)))
                per_q = {}
                for qname, q in queries.items():
                    o = {name: outcomes(q, r, mask, seq) for name, mask in maps.items()}
                    on = [outcomes(q, r, mask, seq) for mask in near]
                    orand = [outcomes(q, r, mask, seq) for mask in rand]
                    per_q[qname] = (q, o, on, orand)
                    got = {name: summary(v) for name, v in o.items()}
                    near_k = [summary(v)[0] for v in on]
                    lo, hi = paired_interval([(q, o["memlog"][0], o["every k-th"][0])])
                    rows.append([qname, rname, len(r), size, fmt(got["full"]), fmt(got["memlog"]),
                                 fmt(got["best bound"]), fmt(got["time"]), fmt(got["every k-th"]),
                                 f"{min(near_k):.3f}–{max(near_k):.3f}",
                                 f"{got['memlog'][0] - got['every k-th'][0]:+.3f} ({lo:+.3f}..{hi:+.3f})",
                                 fmt_rand([summary(v) for v in orand]), still])
                    loose.append([qname, rname, size, f"{got['full'][2]:.3f}", f"{got['memlog'][2]:.3f}",
                                  f"{got['every k-th'][2]:.3f}", f"{np.mean([summary(v)[2] for v in orand]):.3f}"])
                if len(queries) > 1:
                    qs = list(per_q.values())
                    pr = {name: pooled_r1([o[name] for _q, o, _n, _r in qs]) for name in maps}
                    near_p = [pooled_r1([on[i] for _q, _o, on, _r in qs]) for i in range(len(near))]
                    rand_p = np.array([pooled_r1([orand[i] for _q, _o, _n, orand in qs]) for i in range(len(rand))])
                    lo, hi = paired_interval([(q, o["memlog"][0], o["every k-th"][0]) for q, o, _n, _r in qs])
                    prow.append([rname, size, f"{pr['full']:.3f}", f"{pr['memlog']:.3f}", f"{pr['every k-th']:.3f}",
                                 f"{min(near_p):.3f}–{max(near_p):.3f}",
                                 f"{pr['memlog'] - pr['every k-th']:+.3f} ({lo:+.3f}..{hi:+.3f})",
                                 f"{rand_p.mean():.3f} ± {rand_p.std():.3f}"])
        print(f"\n### Maps of drive variants, matched by {mname} (R@1 / AUC-PR, map-only; queries: winter drives)\n")
        print(table(rows, ["query", "reference", "frames", "fraction (frames)", "full map", "memlog",
                           "memlog, best bound (centre tolerance 0)", "memlog, time segments",
                           "every k-th", "every k-th, k±4 frames (R@1 min–max)",
                           "memlog − every k-th (95 % bootstrap over place blocks)", "random (20)", "still frames"]))
        if mname != "single":
            print(f"\nR@1 with a stop's frames as one place (truth: any frame of a stop holding a match of "
                  f"any frame of the query's stop), matched by {mname}:\n")
            print(table(loose, ["query", "reference", "fraction (frames)", "full map", "memlog", "every k-th",
                                "random (20, mean)"]))
        if prow:
            print(f"\nR@1 pooled over the query drives ({', '.join(queries)}: "
                  f"{sum(len(q) for q in queries.values())} query frames, each once), matched by {mname}:\n")
            print(table(prow, ["reference", "fraction (frames)", "full map", "memlog", "every k-th",
                               "every k-th, k±4 frames (min–max)",
                               "memlog − every k-th (95 % bootstrap over place blocks, all drives together)",
                               "random (20)"]))


def tab_candidates(queries: dict[str, Drive], refs: dict[str, Drive], views: dict[str, np.ndarray], scores: Any,
                   fracs: list[float]) -> None:
    if scores is None or np.isnan(scores["ms"]).all():
        print("\n(candidates table: needs --scores)")
        return
    seq = matchers()["sequence"]
    columns: dict[str, tuple[int | None, dict[str, Any]]] = {
        "K = 1 (default, centre rule)": (1, {}), "K = 1, best bound": (1, {"centre_tolerance": 0.0}),
        "K = 2": (2, {}), "K = all (exact)": (None, {}),
        "exact without MS (SS, ES only)": (None, {"weights": (0.0, 1.0, 1.0)})}
    rows, pooled = [], []
    for rname, r in refs.items():
        whiten(r, list(queries.values()))
        t = score_table(r, views[rname], scores)
        for frac in fracs:
            masks = [memlog_mask(t, frac, shortlist=k, **sel) for k, sel in columns.values()]
            per_q = {qname: [outcomes(q, r, m, seq) for m in masks] for qname, q in queries.items()}
            for qname, got in per_q.items():
                rows.append([qname, rname, f"{frac:g}", *(fmt(summary(o)) for o in got)])
            if len(queries) > 1:
                pooled.append([rname, f"{frac:g}", *(f"{pooled_r1([got[i] for got in per_q.values()]):.3f}"
                                                     for i in range(len(masks)))])
    print("\n### Does memorability help choose within a segment? (R@1 / AUC-PR, sequences, map-only)\n")
    print(table(rows, ["query", "reference", "fraction", *columns]))
    if pooled:
        print(f"\nR@1 pooled over the query drives ({', '.join(queries)}):\n")
        print(table(pooled, ["reference", "fraction", *columns]))


def tab_stillness(refs: dict[str, Drive], views: dict[str, np.ndarray]) -> None:
    from memlog.scoring.motion import still_rows

    rows = []
    for rname, r in refs.items():
        v = views[rname].astype(np.float64)
        d = np.r_[np.inf, 1.0 - np.einsum("ij,ij->i", v[1:], v[:-1])]
        repeat = np.r_[False, r.variant.places[1:] == r.variant.places[:-1]]
        still = still_rows(v)
        rows.append([rname, len(r), int(repeat.sum()), f"{np.percentile(d[repeat], 99) if repeat.any() else 0:.5f}",
                     f"{np.percentile(d[~repeat][1:], 5):.4f}", int(still.sum()), int((still & ~repeat).sum())])
    print("\n### Stops found from the images (view vectors within 0.001 of the stop's first frame)\n")
    print(table(rows, ["reference", "frames", "repeated frames (noise only)", "p99 distance, repeats",
                       "p5 distance, moving", "still frames", "of them moving (real stops of the source drive)"]))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cache", type=Path, default=Path("/tmp/memlog-drive-maps"))
    ap.add_argument("--scores", type=Path, help="the summer drive scored with memlog score --all-scores")
    ap.add_argument("--fractions", type=float, nargs="+", default=[0.5, 0.25])
    ap.add_argument("--tables", nargs="+", default=["stillness", "maps", "candidates"])
    ap.add_argument("--queries", nargs="+", default=QUERIES, choices=list(drives.VARIANTS),
                    help=f"winter drive variants matched against every map (default: {' '.join(QUERIES)})")
    ap.add_argument("--matchers", nargs="+", default=list(matchers()), choices=list(matchers()),
                    help="how the maps table matches (default: all three)")
    a = ap.parse_args()
    qs, refs, views = load(a.cache, a.queries)
    scores = source_scores(a.scores) or cheap_scores(a.cache)
    for name in a.tables:
        {"maps": lambda: tab_maps(qs, refs, views, scores, a.fractions, a.matchers),
         "candidates": lambda: tab_candidates(qs, refs, views, scores, a.fractions),
         "stillness": lambda: tab_stillness(refs, views)}[name]()
    return 0


if __name__ == "__main__":
    sys.exit(main())

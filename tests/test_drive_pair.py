"""Drives as a camera records them (the shared Stromovka drive pair: stops, crawls and fast
stretches, 1024x384), through the CLI as a user runs it: every map ``memlog evaluate`` reports is
a map ``memlog map`` writes, matched as ``memlog localize`` matches it.

What is checked against independent expectations:
- ``memlog map --keep-fraction 1`` and ``memlog map`` (the default size) are written and
  ``memlog localize`` matches the winter drive against each; R@1 and the AUC-PR are computed here
  from the match tables and the truth file (R@1 by hand, the AUC by memlog's PR curve on those
  hand-counted hits);
- ``memlog evaluate`` on the same pair reports, for its memorable row, a map of exactly the frames
  the default map keeps, with the same R@1 and AUC (a map is a mask of the drive's one table);
- its every-k-th baseline, written as a map of its frames by the same writer and localized through
  the CLI, gives the row's R@1; its start offsets are every one up to the spacing.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow.parquet as pq
import pytest

from memlog.cli.app import main
from tests.conftest import shared
from tests.test_selection import held_parts


def _scores(matches: Path, truth: list[list[int]]) -> tuple[float, float]:
    """(R@1, AUC-PR) of a match table against the truth, the hits counted here."""
    from memlog.evaluation.metrics import pr_curve

    t = pq.read_table(matches).to_pydict()
    best = {q: (r, c) for q, r, k, c in zip(t["query_id"], t["ref_id"], t["rank"], t["confidence"]) if k == 0}
    hits = np.array([q in best and best[q][0] in set(m) for q, m in enumerate(truth)])
    conf = np.array([best[q][1] if q in best else -np.inf for q in range(len(truth))])
    return float(hits.mean()), pr_curve(conf, hits, np.ones(len(truth), bool)).auc


@pytest.fixture(scope="module")
def drive_pair(tmp_path_factory: pytest.TempPathFactory, drive_pair_evaluation: Path,
               drive_pair_maps: dict[str, tuple[Path, Path]]) -> dict[str, Any]:
    d = tmp_path_factory.mktemp("drive_pair")
    autumn, winter = shared("stromovka_drive_autumn.mcap"), shared("stromovka_drive_winter.mcap")
    truth_file = shared("stromovka_drive_truth.json")
    truth = json.loads(truth_file.read_text())["matches"]
    out: dict[str, Any] = {"dir": d, "autumn": autumn, "winter": winter, "truth_file": truth_file, "truth": truth}
    for name, (parquet, matches) in drive_pair_maps.items():  # `memlog map` (full, default), then `localize`
        out[name] = (parquet, _scores(matches, truth))
    # `memlog evaluate --reference AUTUMN --query WINTER --truth TRUTH -o OUT --seeds 2 --no-report`, run once
    # for the session by the drive_pair_evaluation fixture (tests/conftest.py)
    ev = drive_pair_evaluation / "evaluate"
    out["results"] = json.loads((ev / "results.json").read_text())
    out["eval"] = ev
    out["ran_in"] = drive_pair_evaluation
    return out


def test_the_memorable_row_is_the_map_memlog_map_writes(drive_pair: dict[str, Any]) -> None:
    """evaluate matches the memorable map as a mask of the drive's one described table; `memlog map`
    writes that map (its whitening fitted on the drive), and `memlog localize` against it gives exactly
    the row's R@1 and AUC, computed here from the match table."""
    res = drive_pair["results"]["memorable"]
    parquet, (r1, auc) = drive_pair["default"]
    kept = sorted(pq.read_table(parquet).to_pydict()["frame_index"])
    assert res["frames"] == len(kept)
    assert sorted(res["kept_indices"]) == kept
    assert res["recall@1"] == pytest.approx(r1, abs=1e-9)
    assert res["auc"] == pytest.approx(auc, abs=1e-9)


def test_the_full_row_is_every_place_of_the_drive_once(drive_pair: dict[str, Any]) -> None:
    """The full map is every frame of the drive with a stop's frames once: as many frames as the
    drive has runs of frames at one place (the truth's reference places), give or take a stop whose
    frames are told apart by noise."""
    places = json.loads(drive_pair["truth_file"].read_text())["reference_places"]
    runs = 1 + sum(a != b for a, b in zip(places, places[1:]))
    assert abs(drive_pair["results"]["full"]["frames"] - runs) <= 2


def test_the_full_map_leaves_the_stops_out(drive_pair: dict[str, Any]) -> None:
    """The autumn drive stands at place 20 for 20 frames and at place 71 for 15: a full map keeps
    one view of each stop, not every standing frame (and so fewer frames than the drive has)."""
    places = json.loads(drive_pair["truth_file"].read_text())["reference_places"]
    kept = pq.read_table(drive_pair["full"][0]).to_pydict()["frame_index"]
    at = [places[i] for i in kept]
    assert len(kept) < len(places)
    assert at.count(20) <= 2 and at.count(71) <= 2
    assert set(at) >= {p for p in places if places.count(p) == 1}  # every place driven through once is kept


def test_every_kth_baseline_is_its_written_map(drive_pair: dict[str, Any], tmp_path: Path) -> None:
    """Each baseline is a mask over the drive's described table; written as a map of those frames by
    `memlog map`'s writer (one whitening per drive: the same transform as every other map of the drive)
    and localized through the CLI, it gives the same R@1. The offsets are every k-th frame shifted 0, 1, ...
    frames, as many as the spacing."""
    from mcap.reader import make_reader

    from memlog.steps.map import make_map

    rows = drive_pair["results"]
    ph = rows["uniform_phases"]
    kept = sorted(ph["maps"][0]["kept_indices"])
    n = len(json.loads(drive_pair["truth_file"].read_text())["reference_places"])  # the drive's frames
    assert len(kept) == rows["uniform"]["frames"] == rows["memorable"]["frames"]
    steps = np.diff(kept)
    assert steps.max() - steps.min() <= 1 and steps.min() >= n // len(kept) - 1  # evenly spaced
    # 84 of 139 frames is a spacing of 1.66: two offsets (the last frame wrapping to the first)
    spacing = (n - 1) / (len(kept) - 1)
    assert len(ph["maps"]) == int(np.ceil(spacing))
    assert [sorted(p["kept_indices"]) for p in ph["maps"]] == [sorted((np.asarray(kept) + d) % n)
                                                               for d in range(len(ph["maps"]))]
    assert ph["recall@1"] == pytest.approx(np.mean([p["recall@1"] for p in ph["maps"]]))
    m = tmp_path / "uniform.mcap"
    make_map(drive_pair["autumn"], m, keep_frames={"/camera/image_raw/compressed": kept})
    with open(m, "rb") as f:
        rec = next(x.metadata for x in make_reader(f).iter_metadata() if x.name == "memlog_map")
    assert rec["kept_by"] == "given"
    assert main(["-q", "localize", str(m.with_suffix(".parquet")), str(drive_pair["winter"]), "-o",
                 str(tmp_path / "u.parquet"), "--map", str(m)]) == 0
    r1, _auc = _scores(tmp_path / "u.parquet", drive_pair["truth"])
    assert r1 == pytest.approx(rows["uniform"]["recall@1"], abs=1e-9)
    assert ph["maps"][0]["recall@1"] == pytest.approx(r1, abs=1e-9)
    assert rows["random"]["seeds"] == len(rows["random"]["maps"]) == 2
    assert not (drive_pair["eval"] / "maps").exists()  # no map but the memorable one is written


def _speed_error_near_stops(map_parquet: Path, matches: Path, truth: dict[str, Any], length: int = 10,
                            min_stop: int = 3) -> tuple[float, int]:
    """Median |log2(speed / true speed)| of the speeds ``localize`` reports for the query's moving
    frames within ``length`` moving frames of a stop of at least ``min_stop`` standing frames, and
    their count. The true speed is the truth's: map coordinate (the map's moving index at the
    frame's true place, interpolated where the map has none) over the query's (its place changes),
    between the moving frames before and after."""
    rp, qp = np.asarray(truth["reference_places"]), np.asarray(truth["query_places"])
    m = pq.read_table(map_parquet, columns=["frame_index", "moving_index"]).to_pydict()
    have, first = np.unique(rp[np.asarray(m["frame_index"])], return_index=True)
    g = np.interp(qp, have, np.asarray(m["moving_index"], dtype=np.float64)[first])
    t = pq.read_table(matches).to_pydict()
    speed = {q: s for q, k, s in zip(t["query_id"], t["rank"], t["sequence_speed"]) if k == 0}
    moving = np.r_[True, qp[1:] != qp[:-1]]
    qc = np.cumsum(moving) - 1
    standing_for = np.zeros(len(qp), dtype=np.int64)  # standing frames so far in the current stop
    for i in range(1, len(qp)):
        standing_for[i] = 0 if moving[i] else standing_for[i - 1] + 1
    stops = qc[standing_for == min_stop]
    mov = np.flatnonzero(moving)
    err = []
    for p, i, n in zip(mov[:-2], mov[1:-1], mov[2:]):
        true = (g[n] - g[p]) / (qc[n] - qc[p])
        if np.any(np.abs(stops - qc[i]) <= length) and true > 0 and np.isfinite(speed.get(int(i), np.nan)):
            err.append(abs(np.log2(max(speed[int(i)], 1e-3) / true)))
    return float(np.median(err)), len(err)


def test_the_speeds_around_a_stop_are_the_drives_own(drive_pair_maps: dict[str, tuple[Path, Path]]) -> None:
    """The query stands 25 frames at place 45 (at half the map's pace before, twice after) and 10 at
    place 80: a window across a stop votes a blend of the speeds on its two sides. The re-rank scores
    each frame along the speed its window votes cut at the stops, and ``localize`` reports it: near
    the stops it is within 2^0.15 of the truth's speed for most frames (measured 2^0.10; the whole
    windows' blend: 2^0.21)."""
    truth = json.loads(shared("stromovka_drive_truth.json").read_text())
    parquet, matches = drive_pair_maps["full"]
    err, n = _speed_error_near_stops(parquet, matches, truth)
    assert n >= 30 and err <= 0.15, (err, n)


@pytest.fixture(scope="module")
def odometry_half_map(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``memlog map --keep-fraction 0.5`` of the map drive with the odometry a robot records beside
    its camera (``/odom`` at each frame's place, 8 m apart: :func:`benchmarks.drives.with_odometry`);
    the directory holding ``map.mcap`` and ``map.parquet``."""
    from benchmarks.drives import with_odometry

    d = tmp_path_factory.mktemp("odometry-map")
    places = json.loads(shared("stromovka_drive_truth.json").read_text())["reference_places"]
    log = with_odometry(shared("stromovka_drive_autumn.mcap"), places, d / "autumn-odometry.mcap")
    assert main(["-q", "map", str(log), "-o", str(d / "map.mcap"), "--keep-fraction", "0.5"]) == 0
    return d


def test_a_map_drive_with_odometry_keeps_its_size_and_every_frame_of_its_fast_stretch(odometry_half_map: Path) -> None:
    """The map drive with odometry is cut by distance. Its fast stretch (every other place, 16 m
    between frames) is longer per frame than a part of the path (70 parts of 800 m), so equal parts
    leave some empty; the map still keeps half the drive's frames, every frame of the fast stretch
    among them."""
    places = json.loads(shared("stromovka_drive_truth.json").read_text())["reference_places"]
    kept = pq.read_table(odometry_half_map / "map.parquet").to_pydict()["frame_index"]
    asked = int(np.floor(0.5 * len(places) + 0.5))
    s = 8.0 * np.asarray(places, np.float64)  # the path, as the odometry has it (5 cm noise aside)
    assert held_parts(s, asked) < asked  # equal parts: empty ones
    assert len(kept) == asked
    fast = [i for i in range(1, len(places)) if places[i] - places[i - 1] == 2]
    assert len(fast) == 15 and {places[i] for i in fast} <= {places[i] for i in kept}  # (a repeat of it may stand in)
    stops = [p for p in set(places) if places.count(p) > 2]  # the two stops: one frame each
    assert all(sum(places[i] == p for i in kept) == 1 for p in stops)


def test_the_last_frames_of_a_drive_find_the_end_of_the_map(odometry_half_map: Path, tmp_path: Path) -> None:
    """``memlog localize`` of the winter drive against that map: its last five frames (places
    96-100) each go to the right place. Their windows have frames on one side only, and those
    frames' single-frame candidates rarely hold the map's last places, so the cut windows' votes
    proposed none of them: the drive HMM had no place to continue the path into and sent the last
    three frames back to places 17-21 (with the map's own whitening and with each of 8 refits of
    it; now each window cut by the drive's end also proposes what the same-length window slid along
    the drive votes for: ``memlog.matching.voting``)."""
    truth = json.loads(shared("stromovka_drive_truth.json").read_text())["matches"]
    out = tmp_path / "matches.parquet"
    assert main(["-q", "localize", str(odometry_half_map / "map.parquet"), str(shared("stromovka_drive_winter.mcap")),
                 "-o", str(out), "--map", str(odometry_half_map / "map.mcap")]) == 0
    t = pq.read_table(out).to_pydict()
    best = {q: r for q, r, k in zip(t["query_id"], t["ref_id"], t["rank"]) if k == 0}
    last = range(len(truth) - 5, len(truth))
    assert [best[q] in set(truth[q]) for q in last] == [True] * 5, [(q, best[q], truth[q]) for q in last]

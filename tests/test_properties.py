"""Properties any correct memlog keeps, run through the CLI on camera-resolution data (the shared
Stromovka autumn drive: 101 places of a park path, 1024x384 JPEG, 1 Hz; ``stromovka_winter`` and
``stromovka_truth.json`` for ``evaluate``). Nothing here is compared with a recording of earlier
outputs: every expected value is computed in the test from the input log (read with the mcap
library, not memlog's reader), from the other files of the same run or from a second run.

- determinism: ``score``, ``map`` and ``localize`` run twice on the same input write the same
  score channels, kept frames, descriptor values and match tables;
- round trips: the annotated MCAP holds every input message unchanged plus one score record per
  scored frame; the map MCAP holds exactly the kept frames, byte for byte the input's messages at
  those indices, in the order of its Parquet's rows; the match table has one row per query frame
  and rank, each naming an existing map row; ``results.json`` is JSON whose figures are shares, of
  the memorable map it wrote beside it;
- self-consistency: a drive localized against its own map finds every frame itself (every map
  frame; within one frame for the frames a half map left out);
- independent expectations: the table's similarities are the cosines of the stored descriptors, a
  frame described as a query has the descriptor the map stored for it, and single-frame matching
  returns the brute-force nearest map frames.
"""

from __future__ import annotations

import hashlib
import json
import math
import shutil
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from memlog.cli.app import main
from memlog.outputs.annotated import read_scores
from tests.conftest import shared
from tests.test_score import _records

TOPIC = "/camera/image_raw/compressed"  # the Stromovka logs' one camera topic
SCORES = f"{TOPIC}/memlog/scores"
SCORE_STRIDE = 75  # frames 0 (scored by ResMem, 20 crops) and 75 (rejected by entropy): ~8 s a run
EVAL_STRIDE = 4  # evaluate on every 4th frame of both drives (26 each): ~25 s


class Frame(NamedTuple):
    log_time: int
    publish_time: int
    stamp_ns: int
    data: bytes


def _run(*argv: str | int | Path) -> None:
    args = ["-q", *map(str, argv)]
    assert main(args) == 0, f"memlog {' '.join(args)} failed"


def _camera_messages(path: Path, topic: str = TOPIC) -> list[Frame]:
    """The messages of ``topic`` in log-time order (so item i is frame i), read with the mcap
    library and decoded with mcap_ros2 (the header stamp), not with memlog's reader."""
    out = []
    with open(path, "rb") as fh:
        reader = make_reader(fh, validate_crcs=True, decoder_factories=[DecoderFactory()])
        for _schema, _ch, m, msg in reader.iter_decoded_messages(topics=[topic], log_time_order=True):
            out.append(Frame(m.log_time, m.publish_time, msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec,
                             bytes(m.data)))
    return out


def _decoded(path: Path, topic: str) -> list[tuple[int, Any]]:
    """(log time, decoded message) of each message on ``topic``, in log-time order (mcap_ros2)."""
    with open(path, "rb") as fh:
        reader = make_reader(fh, validate_crcs=True, decoder_factories=[DecoderFactory()])
        return [(m.log_time, msg) for _s, _c, m, msg in reader.iter_decoded_messages(topics=[topic])]


def _topics(path: Path) -> set[str]:
    with open(path, "rb") as fh:
        return {ch.topic for _s, ch, _m in make_reader(fh, validate_crcs=True).iter_messages()}


def _metadata(path: Path) -> dict[str, dict[str, str]]:
    with open(path, "rb") as fh:
        return {m.name: dict(m.metadata) for m in make_reader(fh).iter_metadata()}


def _vectors(table: pa.Table, column: str = "descriptor") -> np.ndarray:
    """A fixed-size-list column as a float64 matrix, one row per table row."""
    col = table.column(column).combine_chunks()
    return np.asarray(col.flatten().to_numpy(zero_copy_only=False), dtype=np.float64).reshape(len(col), -1)


def _unit(x: np.ndarray) -> np.ndarray:
    out: np.ndarray = x / np.linalg.norm(x, axis=1, keepdims=True)
    return out


def _best(matches: dict[str, list[Any]]) -> dict[int, int]:
    """query frame -> its rank-0 map frame."""
    return {q: r for q, r, k in zip(matches["query_id"], matches["ref_id"], matches["rank"]) if k == 0}


def _untimed_scores(path: Path) -> dict[str, list[dict[str, Any]]]:
    """The score records of an annotated MCAP or map log (memlog's reader), their stage timings left out."""
    return {t: [{k: v for k, v in r.items() if k != "timing_ms"} for r in recs]
            for t, recs in read_scores(path).items()}


def _assert_same_columns(a: pa.Table, b: pa.Table, what: str) -> None:
    """Same schema (metadata aside) and every value of every column exactly equal (NaN = NaN,
    nulls in the same rows); list columns (descriptors, patch features) value by value."""
    assert a.schema.remove_metadata() == b.schema.remove_metadata(), what
    assert a.num_rows == b.num_rows, what
    for name in a.column_names:
        x, y = a.column(name).combine_chunks(), b.column(name).combine_chunks()
        assert x.is_null().to_pylist() == y.is_null().to_pylist(), f"{what}: nulls of {name}"
        if pa.types.is_fixed_size_list(x.type):
            x, y = x.flatten(), y.flatten()
        if pa.types.is_floating(x.type):
            np.testing.assert_array_equal(x.to_numpy(zero_copy_only=False), y.to_numpy(zero_copy_only=False),
                                          err_msg=f"{what}: column {name}")
        else:
            assert x.to_pylist() == y.to_pylist(), f"{what}: column {name}"


# ---------------------------------------------------------------------------------------------
# the runs (module-scoped: each is made once, by the first test that needs it)


@pytest.fixture(scope="module")
def autumn() -> Path:
    return shared("stromovka_autumn.mcap")


@pytest.fixture(scope="module")
def autumn_frames(autumn: Path) -> list[Frame]:
    frames = _camera_messages(autumn)
    assert len(frames) == 101 and len({f.log_time for f in frames}) == 101  # (the README's counts; no ties)
    return frames


def _score(autumn: Path, d: Path) -> Path:
    out = d / "scored.mcap"
    _run("score", autumn, "-o", out, "--stride", SCORE_STRIDE)
    return out


@pytest.fixture(scope="module")
def scored(autumn: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``memlog score AUTUMN --stride 75``."""
    return _score(autumn, tmp_path_factory.mktemp("scored"))


@pytest.fixture(scope="module")
def scored_again(autumn: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _score(autumn, tmp_path_factory.mktemp("scored_again"))


def _map(autumn: Path, d: Path, fraction: str) -> Path:
    out = d / "map.mcap"
    _run("map", autumn, "-o", out, "--keep-fraction", fraction)
    return out


@pytest.fixture(scope="module")
def full_map(autumn: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``memlog map AUTUMN --keep-fraction 1``: map.mcap (map.parquet beside it)."""
    return _map(autumn, tmp_path_factory.mktemp("full_map"), "1")


@pytest.fixture(scope="module")
def half_map(autumn: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``memlog map AUTUMN --keep-fraction 0.5``."""
    return _map(autumn, tmp_path_factory.mktemp("half_map"), "0.5")


@pytest.fixture(scope="module")
def half_map_again(autumn: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _map(autumn, tmp_path_factory.mktemp("half_map_again"), "0.5")


class Matches(NamedTuple):
    map: Path  # map.mcap (map.parquet beside it)
    table: Path  # the match table
    query: Path  # the query descriptors localize cached (--query-descriptors)


def _localize(map_mcap: Path, query: Path, d: Path) -> Matches:
    out = Matches(map_mcap, d / "matches.parquet", d / "query.parquet")
    _run("localize", map_mcap.with_suffix(".parquet"), query, "-o", out.table, "--map", map_mcap,
         "--query-descriptors", out.query)
    return out


@pytest.fixture(scope="module")
def full_matches(full_map: Path, autumn: Path, tmp_path_factory: pytest.TempPathFactory) -> Matches:
    """``memlog localize`` of the autumn drive against its own full map (defaults: sequences, re-rank, HMM)."""
    return _localize(full_map, autumn, tmp_path_factory.mktemp("full_matches"))


@pytest.fixture(scope="module")
def half_matches(half_map: Path, autumn: Path, tmp_path_factory: pytest.TempPathFactory) -> Matches:
    return _localize(half_map, autumn, tmp_path_factory.mktemp("half_matches"))


@pytest.fixture(scope="module")
def half_matches_again(half_map: Path, autumn: Path, tmp_path_factory: pytest.TempPathFactory) -> Matches:
    return _localize(half_map, autumn, tmp_path_factory.mktemp("half_matches_again"))


@pytest.fixture(scope="module")
def evaluation(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``memlog evaluate`` of the Stromovka pair (autumn map drive, winter query drive), every 4th
    frame of each, one random seed, no report: its output folder."""
    ref, query, truth = shared("stromovka_autumn.mcap"), shared("stromovka_winter.mcap"), shared("stromovka_truth.json")
    out = tmp_path_factory.mktemp("evaluation") / "evaluate"
    _run("evaluate", "--reference", ref, "--query", query, "--truth", truth, "-o", out, "--stride", EVAL_STRIDE,
         "--seeds", "1", "--no-report")
    return out


# ---------------------------------------------------------------------------------------------
# memlog score


def test_annotated_mcap_holds_every_input_message_and_a_score_per_scored_frame(
        scored: Path, autumn: Path, autumn_frames: list[Frame]) -> None:
    got = _records(scored)  # every message of the output (CRCs validated), sorted
    want = _records(autumn)
    assert [r for r in got if "/memlog/" not in r[0]] == want, "input messages must survive byte for byte"
    assert {r[0] for r in got} == {TOPIC, SCORES, f"{TOPIC}/memlog/annotations"}
    scored_frames = list(range(0, len(autumn_frames), SCORE_STRIDE))  # every 75th frame: 0, 75
    for channel in (SCORES, f"{TOPIC}/memlog/annotations"):  # one message per scored frame, at its log time
        assert [t for t, _msg in _decoded(scored, channel)] == [autumn_frames[i].log_time for i in scored_frames]
    recs = _decoded(scored, SCORES)
    for i, (_t, rec) in zip(scored_frames, recs):
        f = autumn_frames[i]
        assert (rec.frame_index, rec.topic, rec.log_time) == (i, TOPIC, f.log_time)
        assert rec.timestamp.sec * 10**9 + rec.timestamp.nanosec == f.stamp_ns
        for v in (rec.ss, rec.es):
            assert 0.0 <= v <= 1.0
        # the paper's rule, with the thresholds the record says it used (NaN: a stage not run)
        th = rec.thresholds
        assert rec.selected == (rec.rejected_by == "")
        if rec.selected:
            ms_low = rec.ms if math.isfinite(rec.ms) else rec.ms_low
            assert rec.ss >= th.st and rec.es >= th.et and ms_low >= th.mt
        elif rec.rejected_by == "entropy":
            assert rec.ss >= th.st and rec.es < th.et
    # and memlog's own reader gives the same records (frame index, decision)
    assert [(r["frame_index"], r["selected"]) for r in read_scores(scored)[TOPIC]] == \
        [(m.frame_index, m.selected) for _t, m in recs]
    # the data has both kinds: a frame ResMem scored and kept, and one rejected before it
    assert [m.selected for _t, m in recs] == [True, False], [(m.frame_index, m.rejected_by) for _t, m in recs]


def test_score_twice_writes_the_same_score_channels(scored: Path, scored_again: Path) -> None:
    """Every field of every score record is equal (the stage timings aside), and the annotation
    messages are equal byte for byte."""
    a, b = _untimed_scores(scored), _untimed_scores(scored_again)
    assert list(a) == [TOPIC] and len(a[TOPIC]) == 2
    assert a == b
    ann = [[r for r in _records(p) if r[0].endswith("/memlog/annotations")] for p in (scored, scored_again)]
    assert len(ann[0]) == 2 and ann[0] == ann[1]


# ---------------------------------------------------------------------------------------------
# memlog map


@pytest.mark.parametrize("which", ["half_map", "full_map"])
def test_map_log_holds_exactly_the_kept_frames_in_the_order_of_its_parquet(
        which: str, request: pytest.FixtureRequest, autumn_frames: list[Frame]) -> None:
    m: Path = request.getfixturevalue(which)
    p = m.with_suffix(".parquet")
    table = pq.read_table(p)
    rows = table.to_pydict()
    kept = rows["frame_index"]
    at = {f.log_time: i for i, f in enumerate(autumn_frames)}
    in_map = _camera_messages(m)
    # the map's frames, as input frame indices (by log time), are the Parquet's rows in their order
    assert [at[f.log_time] for f in in_map] == kept
    assert kept == sorted(set(kept)) and 0 < len(kept) <= len(autumn_frames)
    for f, i in zip(in_map, kept):  # byte for byte the input's message at that index
        src = autumn_frames[i]
        assert (f.data, f.publish_time, f.stamp_ns) == (src.data, src.publish_time, src.stamp_ns), i
    # the Parquet's rows describe those frames
    assert rows["log_time_ns"] == [autumn_frames[i].log_time for i in kept]
    assert rows["stamp_ns"] == [autumn_frames[i].stamp_ns for i in kept]
    assert set(rows["topic"]) == {TOPIC}
    assert all(b >= a for a, b in zip(rows["moving_index"], rows["moving_index"][1:]))  # along the drive
    desc = _vectors(table)
    assert np.all(np.isfinite(desc)) and np.allclose(np.linalg.norm(desc, axis=1), 1.0, atol=1e-5)  # whitened, unit
    # besides the camera topic only memlog's channels of it, with one score record per kept frame
    assert all(t == TOPIC or t.startswith(f"{TOPIC}/memlog/") for t in _topics(m))
    scores = _decoded(m, SCORES)
    assert [(t, s.frame_index) for t, s in scores] == [(autumn_frames[i].log_time, i) for i in kept]
    # the pair records each other: the Parquet names the map by its bytes' sha256
    md = pq.read_schema(p).metadata
    assert md[b"memlog.map_sha256"].decode() == hashlib.sha256(m.read_bytes()).hexdigest()
    meta = _metadata(m)
    assert meta["memlog_map_descriptors"]["descriptors_file"] == p.name
    assert (int(meta["memlog_map"]["frames_in"]), int(meta["memlog_map"]["frames_kept"])) == \
        (len(autumn_frames), len(kept))
    if which == "half_map":  # about half: 101 frames, --keep-fraction 0.5
        assert abs(len(kept) - 0.5 * len(autumn_frames)) <= 1, len(kept)


def test_map_twice_keeps_the_same_frames_and_descriptors(half_map: Path, half_map_again: Path) -> None:
    """The same frames, byte for byte, and every Parquet value (descriptors, patch features, scores,
    positions along the drive) and its metadata (the whitening, the patch projection) equal; only
    the map file each Parquet names (and so its sha256) differs."""
    assert _camera_messages(half_map) == _camera_messages(half_map_again)  # the kept frames, byte for byte
    assert _untimed_scores(half_map) == _untimed_scores(half_map_again)  # and their score records
    a, b = pq.read_table(half_map.with_suffix(".parquet")), pq.read_table(half_map_again.with_suffix(".parquet"))
    _assert_same_columns(a, b, "map.parquet")
    ma, mb = (dict(t.schema.metadata) for t in (a, b))
    link = {b"memlog.map_sha256", b"memlog.map_file", b"memlog.extra"}
    assert set(ma) == set(mb) and {k: ma[k] for k in set(ma) - link} == {k: mb[k] for k in set(mb) - link}
    ea, eb = json.loads(ma[b"memlog.extra"]), json.loads(mb[b"memlog.extra"])
    assert ea.pop("map") != eb.pop("map") and ea == eb  # (each names its own map file)


# ---------------------------------------------------------------------------------------------
# memlog localize


@pytest.mark.parametrize("which", ["half_matches", "full_matches"])
def test_match_table_has_every_query_frame_at_every_rank_naming_map_rows(
        which: str, request: pytest.FixtureRequest, autumn_frames: list[Frame]) -> None:
    run: Matches = request.getfixturevalue(which)
    ref = pq.read_table(run.map.with_suffix(".parquet")).to_pydict()
    t = pq.read_table(run.table).to_pydict()
    n_map, n_q = len(ref["frame_index"]), len(autumn_frames)
    k = min(5, n_map)  # -k defaults to 5
    assert len(t["rank"]) == n_q * k
    by_query: dict[int, list[int]] = {}
    for row in range(len(t["rank"])):
        q = t["query_id"][row]
        assert t["query_topic"][row] == TOPIC and t["query_log_time_ns"][row] == autumn_frames[q].log_time
        r = t["ref_row"][row]
        assert 0 <= r < n_map
        assert (t["ref_id"][row], t["ref_log_time_ns"][row], t["ref_topic"][row]) == \
            (ref["frame_index"][r], ref["log_time_ns"][r], ref["topic"][r])
        assert -1.0 - 1e-5 <= t["similarity"][row] <= 1.0 + 1e-5
        by_query.setdefault(q, []).append(row)
    assert sorted(by_query) == list(range(n_q))  # every query frame, once each ...
    for q, rows in by_query.items():  # ... at ranks 0..k-1, each rank a distinct map frame
        assert sorted(t["rank"][r] for r in rows) == list(range(k))
        assert len({t["ref_row"][r] for r in rows}) == k
        assert len({t["query_row"][r] for r in rows}) == 1
    assert set(t["matched_by"]) <= {"sequence", "causal sequence", "single frame"}


def test_localize_twice_writes_the_same_match_table(half_matches: Matches, half_matches_again: Matches) -> None:
    """Every column of the match table exactly equal, and the query descriptors it described."""
    _assert_same_columns(pq.read_table(half_matches.table), pq.read_table(half_matches_again.table), "matches")
    _assert_same_columns(pq.read_table(half_matches.query), pq.read_table(half_matches_again.query),
                         "query descriptors")


def test_a_drive_against_its_full_map_finds_every_frame_itself(full_matches: Matches,
                                                                 autumn_frames: list[Frame]) -> None:
    """The full map of a sparse route keeps every frame (no stops: consecutive frames are metres
    apart), and each frame of the same drive is matched to itself, at cosine similarity 1 (the
    same image described alike). Asked: within one frame (R@1 1.0 at the truth files' ±1)."""
    kept = pq.read_table(full_matches.map.with_suffix(".parquet")).to_pydict()["frame_index"]
    assert kept == list(range(len(autumn_frames)))
    t = pq.read_table(full_matches.table).to_pydict()
    best = _best(t)
    assert sum(abs(r - q) <= 1 for q, r in best.items()) == len(autumn_frames)  # R@1 (±1) = 1.0
    assert {q: r for q, r in best.items() if r != q} == {}  # every frame exactly itself
    sims = [s for k, s in zip(t["rank"], t["similarity"]) if k == 0]
    assert min(sims) >= 1 - 1e-5


def test_a_drive_against_its_half_map_finds_its_kept_frames_and_their_neighbours(
        half_map: Path, half_matches: Matches, autumn_frames: list[Frame]) -> None:
    """Against the half map of the same drive: every kept frame is matched to itself (asked:
    within one frame) at similarity 1, and every other frame to a map frame within one frame of it."""
    kept = pq.read_table(half_map.with_suffix(".parquet")).to_pydict()["frame_index"]
    t = pq.read_table(half_matches.table).to_pydict()
    best = _best(t)
    wrong_kept = {q: best[q] for q in kept if best[q] != q}
    assert not wrong_kept, f"kept frames matched elsewhere (query: map frame): {wrong_kept}"
    sim0 = {q: s for q, k, s in zip(t["query_id"], t["rank"], t["similarity"]) if k == 0}
    assert min(sim0[q] for q in kept) >= 1 - 1e-5
    far = {q: r for q, r in best.items() if abs(r - q) > 1}
    assert not far, f"frames matched more than one frame away (query: map frame): {far}"


# ---------------------------------------------------------------------------------------------
# independent expectations of the match table


@pytest.mark.parametrize("which", ["half_matches", "full_matches"])
def test_similarities_are_the_cosines_of_the_stored_descriptors(which: str, request: pytest.FixtureRequest) -> None:
    """Each row's ``similarity`` is the cosine of the query frame's descriptor (as localize cached it,
    in the map's whitening) and the map row's descriptor, recomputed here in float64; and a frame
    the map kept is described as a query exactly as the map stored it."""
    run: Matches = request.getfixturevalue(which)
    ref, qt = pq.read_table(run.map.with_suffix(".parquet")), pq.read_table(run.query)
    R, Q = _unit(_vectors(ref)), _unit(_vectors(qt))
    q_index = qt.column("frame_index").to_pylist()
    assert q_index == sorted(q_index) and len(q_index) == 101
    t = pq.read_table(run.table).to_pydict()
    assert all(q_index[qr] == q for qr, q in zip(t["query_row"], t["query_id"]))
    want = np.einsum("ij,ij->i", Q[t["query_row"]], R[t["ref_row"]])
    np.testing.assert_allclose(np.asarray(t["similarity"], dtype=np.float64), want, rtol=0, atol=1e-5)
    row_of = {f: i for i, f in enumerate(q_index)}
    ref_frames = ref.column("frame_index").to_pylist()
    np.testing.assert_allclose(_vectors(qt)[[row_of[f] for f in ref_frames]], _vectors(ref), rtol=0, atol=1e-6)


def test_single_frame_matches_are_the_brute_force_nearest_map_frames(half_matches: Matches, half_map: Path,
                                                                     autumn: Path, tmp_path: Path) -> None:
    """``localize --sequence 0 --no-rerank --no-hmm --no-ensemble`` (each frame alone, by its
    descriptor) gives each query frame the k map frames of highest cosine similarity, best first,
    as a brute-force search over the stored descriptors finds them (the query descriptors cached
    by ``half_matches`` are reused, so nothing is described again)."""
    cache = tmp_path / "query.parquet"
    shutil.copyfile(half_matches.query, cache)
    out = tmp_path / "single.parquet"
    _run("localize", half_map.with_suffix(".parquet"), autumn, "-o", out, "--map", half_map, "--query-descriptors",
         cache, "--sequence", "0", "--no-rerank", "--no-hmm", "--no-ensemble", "-k", "5")
    R = _unit(_vectors(pq.read_table(half_map.with_suffix(".parquet"))))
    Q = _unit(_vectors(pq.read_table(cache)))
    S = Q @ R.T
    t = pq.read_table(out).to_pydict()
    assert set(t["matched_by"]) == {"single frame"}
    got = np.full((len(Q), 5), -1)
    for qr, k, rr in zip(t["query_row"], t["rank"], t["ref_row"]):
        got[qr, k] = rr
    assert np.all(got >= 0)
    top = -np.sort(-S, axis=1)[:, :5]  # the 5 highest similarities of each query, best first
    np.testing.assert_allclose(np.take_along_axis(S, got, axis=1), top, rtol=0, atol=1e-6)
    # and the very frames, wherever a rank's similarity is not within 1e-6 of its neighbours' (no near-tie)
    order = np.argsort(-S, axis=1, kind="stable")[:, :5]
    gap = -np.diff(-np.sort(-S, axis=1)[:, :6], axis=1) > 1e-6  # rank j's similarity above rank j+1's
    clear = gap & np.c_[np.ones(len(S), bool), gap[:, :-1]]
    assert clear.mean() > 0.9 and np.array_equal(got[clear], order[clear])


# ---------------------------------------------------------------------------------------------
# memlog evaluate

FIGURES = {"auc", "recall@1", "recall@5", "recall@10", "coverage", "precision@100%recall", "paper_auc",
           "paper_recall@1"}


def _walk(value: Any, path: str = "") -> list[tuple[str, dict[str, Any]]]:
    """Every dict of ``value`` with its path."""
    out = []
    if isinstance(value, dict):
        out.append((path, value))
        for k, v in value.items():
            out += _walk(v, f"{path}/{k}")
    elif isinstance(value, list):
        for i, v in enumerate(value):
            out += _walk(v, f"{path}[{i}]")
    return out


def test_evaluate_results_are_shares_of_the_memorable_map_it_wrote(evaluation: Path) -> None:
    """results.json is strict JSON; every figure (AUC, recalls, coverage, precision, the sweeps'
    figures) lies in [0, 1], recall@1 <= recall@5 <= recall@10, under the map-only protocol at most
    the coverage; the memorable map it reports is the map.mcap/map.parquet beside it (frames, kept
    indices), the baselines are maps of its size, and every map holds frames of the window."""
    def no_constant(name: str) -> None:
        raise AssertionError(f"results.json holds {name}, which is not JSON")

    res = json.loads((evaluation / "results.json").read_text(), parse_constant=no_constant)
    n_figures = 0
    for path, d in _walk(res):
        for key in FIGURES & set(d):
            v = d[key]
            assert isinstance(v, (int, float)) and not isinstance(v, bool) and 0.0 <= v <= 1.0, (path, key, v)
            n_figures += 1
        if {"recall@1", "recall@5", "recall@10"} <= set(d) and not path.endswith("/std"):
            assert d["recall@1"] <= d["recall@5"] + 1e-12 and d["recall@5"] <= d["recall@10"] + 1e-12, path
            if "coverage" in d and "paper_protocol" not in path:  # a query is right only with a true place in the map
                assert d["recall@10"] <= d["coverage"] + 1e-12, path
    assert n_figures > 50
    window = list(range(0, 101, EVAL_STRIDE))  # the reference frames evaluate read: every 4th
    mem = res["memorable"]
    table = pq.read_table(evaluation / "map.parquet").to_pydict()
    in_map = _camera_messages(evaluation / "map.mcap")
    assert mem["frames"] == len(table["frame_index"]) == len(in_map) == len(mem["kept_indices"])
    assert sorted(mem["kept_indices"]) == table["frame_index"]
    assert set(table["frame_index"]) <= set(window)
    assert res["map_size"]["frames_in"] == len(window) and res["map_size"]["frames_kept"] == mem["frames"]
    assert 0 < res["full"]["frames"] <= len(window)
    for name in ("uniform", "random"):
        assert res[name]["frames"] == mem["frames"], name

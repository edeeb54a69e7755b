"""Tests of memlog.descriptors.search and memlog.outputs.matches: exact search against brute force,
batched = one by one, confidence, timing, output."""

from __future__ import annotations

import contextlib
import csv
import logging
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from memlog.errors import DescriptorError
from memlog.descriptors import search
from memlog.descriptors.search import Database, confidence, match, time_per_query, topk
from memlog.outputs.matches import write_matches


def _unit(rng: np.random.Generator, n: int, d: int) -> np.ndarray:
    x = rng.normal(size=(n, d)).astype(np.float32)
    return x / np.linalg.norm(x, axis=1, keepdims=True)


def _brute(q: np.ndarray, r: np.ndarray, k: int, mask: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    sim = q.astype(np.float64) @ r.astype(np.float64).T
    if mask is not None:
        sim[:, ~mask] = -np.inf
    order = np.argsort(-sim, axis=1, kind="stable")[:, :k]
    return order, np.take_along_axis(sim, order, axis=1)


@pytest.mark.parametrize("block_rows", [None, 1, 7, 1000])
@pytest.mark.parametrize("k", [1, 5, 37])
def test_match_equals_brute_force(block_rows: int | None, k: int) -> None:
    rng = np.random.default_rng(k)
    q, r = _unit(rng, 23, 16), _unit(rng, 37, 16)
    idx, sim = match(q, r, k=k, block_rows=block_rows)
    bi, bs = _brute(q, r, k)
    np.testing.assert_array_equal(idx, bi)
    np.testing.assert_allclose(sim, bs, atol=1e-5)
    assert idx.dtype == np.int64 and sim.dtype == np.float32


@pytest.mark.parametrize("block_rows", [None, 3])
def test_match_with_ref_mask(block_rows: int | None) -> None:
    rng = np.random.default_rng(1)
    q, r = _unit(rng, 15, 8), _unit(rng, 50, 8)
    mask = rng.random(50) < 0.3
    n_map = int(mask.sum())
    idx, sim = match(q, r, k=n_map + 3, ref_mask=mask, block_rows=block_rows)
    bi, bs = _brute(q, r, n_map, mask)
    np.testing.assert_array_equal(idx[:, :n_map], bi)
    np.testing.assert_allclose(sim[:, :n_map], bs, atol=1e-5)
    assert np.all(mask[idx[:, :n_map]])
    # fewer database rows than k: padded with -1 / -inf
    assert np.all(idx[:, n_map:] == -1) and np.all(np.isneginf(sim[:, n_map:]))


def test_match_empty_mask_and_errors() -> None:
    rng = np.random.default_rng(2)
    q, r = _unit(rng, 3, 4), _unit(rng, 5, 4)
    idx, sim = match(q, r, k=2, ref_mask=np.zeros(5, bool))
    assert np.all(idx == -1) and np.all(np.isneginf(sim))
    with pytest.raises(DescriptorError):
        match(q, _unit(rng, 5, 3))
    with pytest.raises(DescriptorError):
        match(q, r, k=0)
    with pytest.raises(DescriptorError):
        match(q, r, ref_mask=np.ones(4, bool))
    with pytest.raises(DescriptorError):
        match(np.full((1, 4), np.nan), r)


def test_match_single_row_and_ties() -> None:
    r = np.eye(3, dtype=np.float32)[[0, 1, 0, 2]]  # rows 0 and 2 are identical
    idx, sim = match(np.array([1.0, 0.0, 0.0]), r, k=3)
    np.testing.assert_array_equal(idx, [[0, 2, 1]])  # tie broken by lower index
    np.testing.assert_allclose(sim, [[1.0, 1.0, 0.0]])


def _dyadic(rng: np.random.Generator, n: int, d: int) -> np.ndarray:
    """Rows of small multiples of 1/8: every float32 product and sum of them is exact, in any order,
    so the similarities do not depend on how the BLAS blocks the product, and ties are real."""
    return (rng.integers(-4, 5, size=(n, d)) / 8.0).astype(np.float32)


@pytest.fixture
def small_tiles(monkeypatch: pytest.MonkeyPatch) -> None:
    """Tiles of a few hundred similarities and groups of 4 columns: many tiles, the group bound used."""
    monkeypatch.setattr(search, "MAX_BLOCK_ELEMS", 600)
    monkeypatch.setattr(search, "GROUP", 4)


@pytest.mark.parametrize("tiles", [False, True])
def test_batched_equals_one_by_one_exactly(tiles: bool, request: pytest.FixtureRequest) -> None:
    if tiles:
        request.getfixturevalue("small_tiles")
    rng = np.random.default_rng(11)
    for unit, (q, r) in enumerate([(_dyadic(rng, 40, 12), _dyadic(rng, 300, 12)),
                                   (_unit(rng, 40, 64), _unit(rng, 300, 64))]):
        r[100] = r[7]  # duplicate map frames: tied similarities, broken by the lower index
        r[250] = r[7]
        q[3] = r[7]
        all_at_once = match(q, r, k=6)
        one_by_one = [match(q[i], r, k=6) for i in range(len(q))]
        np.testing.assert_array_equal(all_at_once[0], np.concatenate([o[0] for o in one_by_one]))
        np.testing.assert_array_equal(all_at_once[1], np.concatenate([o[1] for o in one_by_one]))
        for rows in (1, 3, 17, 1000):
            blocked = match(q, r, k=6, block_rows=rows)
            np.testing.assert_array_equal(blocked[0], all_at_once[0])
            np.testing.assert_array_equal(blocked[1], all_at_once[1])
        if unit:  # the query is map frame 7, which appears three times
            assert list(all_at_once[0][3, :3]) == [7, 100, 250]
        bi, bs = _brute(q, r, 6)
        np.testing.assert_array_equal(all_at_once[0], bi)
        np.testing.assert_allclose(all_at_once[1], bs, rtol=0, atol=1e-6)


def test_dyadic_ties_against_brute_force(small_tiles: None) -> None:
    """Many exact ties (values on a coarse grid): the order is similarity desc, then reference index."""
    rng = np.random.default_rng(12)
    q, r = _dyadic(rng, 30, 3), _dyadic(rng, 400, 3)
    for k in (1, 5, 60):
        idx, sim = match(q, r, k=k, block_rows=7)
        bi, bs = _brute(q, r, k)
        np.testing.assert_array_equal(idx, bi)
        np.testing.assert_array_equal(sim, bs.astype(np.float32))  # exact values: no rounding at all


def test_blank_queries_tie_with_every_frame() -> None:
    rng = np.random.default_rng(15)
    q, r = _unit(rng, 6, 16), _unit(rng, 50, 16)
    q[[1, 4]] = 0.0  # blank frames describe to zero vectors
    idx, sim = match(q, r, k=4)
    np.testing.assert_array_equal(idx[[1, 4]], [[0, 1, 2, 3]] * 2)
    assert np.all(sim[[1, 4]] == 0)
    bi, _bs = _brute(q, r, 4)
    np.testing.assert_array_equal(idx, bi)
    mask = np.arange(50) >= 45
    np.testing.assert_array_equal(match(q, r, k=8, ref_mask=mask)[0][1], [45, 46, 47, 48, 49, -1, -1, -1])


def test_database_reuse_and_refusals() -> None:
    rng = np.random.default_rng(13)
    q, r = _unit(rng, 5, 8), _unit(rng, 20, 8)
    db = Database.of(r)
    np.testing.assert_array_equal(match(q, db, k=3)[0], match(q, r, k=3)[0])
    mask = rng.random(20) < 0.5
    masked = Database.of(r, mask)
    np.testing.assert_array_equal(match(q, masked, k=3)[0], match(q, r, k=3, ref_mask=mask)[0])
    with pytest.raises(DescriptorError, match="ref_mask"):
        match(q, db, k=3, ref_mask=mask)
    with pytest.raises(DescriptorError, match="NaN or infinite"):
        Database.of(np.where(np.arange(20)[:, None] == 13, np.inf, r))
    with pytest.raises(DescriptorError, match="too large"):
        match(q * 1e10, r * 1e10)
    with pytest.raises(DescriptorError, match="8-d"):
        match(_unit(rng, 2, 4), db)


def test_topk_matches_match() -> None:
    rng = np.random.default_rng(5)
    q, r = _unit(rng, 9, 6), _unit(rng, 21, 6)
    mask = rng.random(21) < 0.6
    a = match(q, r, k=4, ref_mask=mask)
    b = topk(q @ r.T, k=4, ref_mask=mask)
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_allclose(a[1], b[1], atol=1e-6)


def test_confidence_measures() -> None:
    sims = np.array([[0.9, 0.5], [0.8, 0.8], [0.7, -np.inf]], dtype=np.float32)
    c = confidence(sims)
    np.testing.assert_allclose(c.best, [0.9, 0.8, 0.7])
    np.testing.assert_allclose(c.margin[:2], [0.4, 0.0], atol=1e-6)
    # ratio d1/d2 with d = sqrt(2 - 2 s): sqrt(0.2)/sqrt(1.0)
    assert c.ratio[0] == pytest.approx(np.sqrt(0.2), rel=1e-5)
    assert c.ratio[1] == pytest.approx(1.0)
    assert np.isnan(c.margin[2]) and np.isnan(c.ratio[2])
    assert np.all(np.isnan(confidence(sims[:, :1]).margin))


def test_time_per_query() -> None:
    rng = np.random.default_rng(6)
    q, r = _unit(rng, 10, 32), _unit(rng, 500, 32)
    mask = np.zeros(500, bool)
    mask[:50] = True
    full = time_per_query(q, r, repeats=3)
    small = time_per_query(q, r, repeats=3, ref_mask=mask)
    assert full.n_refs == 500 and small.n_refs == 50 and full.dim == 32 and full.n_queries == 10
    assert 0 < full.min_seconds_per_query <= full.seconds_per_query < 1.0
    assert set(full.to_dict()) >= {"seconds_per_query", "n_refs", "batched"}
    single = time_per_query(q, Database.of(r), repeats=2, max_queries=4, batched=False)
    assert not single.batched and single.n_queries == 4 and single.repeats == 2 and full.batched


def test_topk_ties_nan_and_group_bound(small_tiles: None) -> None:
    rng = np.random.default_rng(14)
    sim = np.round(rng.random((9, 200)) * 8) / 8  # many ties
    sim[2, :] = np.nan  # no match at all
    sim[4, 150:] = np.nan
    idx, val = topk(sim, k=12)
    filled = np.where(np.isnan(sim), -np.inf, sim)
    order = np.lexsort((np.broadcast_to(np.arange(200), filled.shape), -filled), axis=-1)[:, :12]
    np.testing.assert_array_equal(idx, order)
    np.testing.assert_array_equal(val, np.take_along_axis(filled, order, axis=1).astype(np.float32))


@pytest.mark.parametrize("suffix", [".parquet", ".csv"])
def test_write_matches(tmp_path: Path, suffix: str) -> None:
    idx = np.array([[2, 0], [1, -1]])
    sim = np.array([[0.9, 0.5], [0.7, -np.inf]], dtype=np.float32)
    path = write_matches(tmp_path / f"m{suffix}", idx, sim, query_ids=[10, 11], ref_ids=[100, 101, 102],
                         query_columns={"correct": np.array([True, False])})
    if suffix == ".csv":
        with open(path, newline="") as fh:
            rows = list(csv.DictReader(fh))
        assert [r["ref_id"] for r in rows] == ["102", "100", "101"]
        assert [r["rank"] for r in rows] == ["0", "1", "0"]
        assert [r["correct"] for r in rows] == ["true", "true", "false"]
    else:
        t = pq.read_table(path).to_pydict()
        assert t["query_row"] == [0, 0, 1] and t["ref_row"] == [2, 0, 1]
        assert t["query_id"] == [10, 10, 11] and t["ref_id"] == [102, 100, 101]
        assert t["similarity"] == pytest.approx([0.9, 0.5, 0.7])
    assert [p.name for p in tmp_path.iterdir()] == [f"m{suffix}"]  # no temporary file left
    with pytest.raises(DescriptorError):
        write_matches(tmp_path / "m.txt", idx, sim)


# -- sequences through the command line (memlog localize) -----------------------------------------

def _nordland_map(path: Path, step: int = 1) -> Path:
    """The Nordland summer drive as a map (whitened thumbnail, the transform fitted on every frame as
    `memlog map` does), keeping every ``step``-th frame with its frame index in the drive."""
    from memlog.descriptors.extract import describe_log
    from memlog.descriptors.registry import make_describer
    from memlog.descriptors.table import DescriptorTable
    from memlog.descriptors.whitening import WhitenedDescriber, fit_whitening
    from memlog.outputs.descriptor_table import write_descriptors
    from tests.conftest import shared

    d = make_describer("thumbnail")
    t, _ = describe_log(shared("nordland_dev_summer.mcap"), d)
    w = fit_whitening(t.descriptors)
    keep = np.arange(0, len(t), step)
    table = DescriptorTable([t.topic[i] for i in keep], t.frame_index[keep], t.log_time_ns[keep], t.stamp_ns[keep],
                            w.apply(t.descriptors)[keep], WhitenedDescriber(d, w).meta(), extra=t.extra, whitening=w,
                            moving_index=None if t.moving_index is None else t.moving_index[keep])
    return write_descriptors(path, table)


def _recall_at_1(matches: Path) -> float:
    import json

    from tests.conftest import shared

    truth = json.loads(shared("nordland_dev_truth.json").read_text())["matches"]
    t = pq.read_table(matches).to_pydict()
    best = [(q, r) for q, r, k in zip(t["query_id"], t["ref_id"], t["rank"]) if k == 0]
    return sum(r in truth[q] for q, r in best) / len(truth)


@pytest.fixture(scope="module")
def nordland_maps(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("maps")
    return {"full": _nordland_map(d / "full.parquet"), "quarter": _nordland_map(d / "quarter.parquet", 4)}


def test_cli_localizes_the_winter_drive_as_sequences(nordland_maps: dict[str, Path], tmp_path: Path) -> None:
    import json

    from memlog.cli.app import main
    from memlog.io import open_log
    from memlog.outputs.channels import MATCH, decode_record
    from tests.conftest import shared

    winter = str(shared("nordland_dev_winter.mcap"))
    full = str(nordland_maps["full"])
    assert main(["-q", "localize", full, winter, "-o", str(tmp_path / "seq.parquet"),
                 "--annotate", str(tmp_path / "seq.mcap")]) == 0
    assert main(["-q", "localize", full, winter, "-o", str(tmp_path / "single.parquet"), "--sequence", "0"]) == 0
    assert main(["-q", "localize", full, winter, "-o", str(tmp_path / "kept.parquet"), "--keep-stops"]) == 0
    seq, single = _recall_at_1(tmp_path / "seq.parquet"), _recall_at_1(tmp_path / "single.parquet")
    # measured: single frames 0.318 (the README's whitened full map), sequences 0.766 (stops left
    # out), 0.850 along the frame index (--keep-stops: both Nordland drives stand at the same frames)
    assert single < 0.35 and seq > 0.72, (single, seq)
    assert _recall_at_1(tmp_path / "kept.parquet") == pytest.approx(0.850, abs=0.002)
    t = pq.read_table(tmp_path / "seq.parquet")
    meta = json.loads(t.schema.metadata[b"memlog.sequence"])
    kept_meta = json.loads(pq.read_table(tmp_path / "kept.parquet").schema.metadata[b"memlog.sequence"])
    # the winter drive stands at stations: those frames take their stop's match
    assert meta["stops"] is True and meta["standing_rows"] > 100 and meta["asked"]["stops"] is True
    assert kept_meta["stops"] is False and kept_meta["standing_rows"] == 0 and kept_meta["asked"]["stops"] is False
    assert meta["length"] == 10 and meta["mode"] == "offline" and meta["candidates"] == 10
    assert meta["coordinate"] == "frames" and meta["speeds"] == pytest.approx([1 / 3, 3.0]) and meta["fallback"] is None
    assert meta["speed_prior"] == 1.0 and meta["length_used"] == 10 and meta["sequence_queries"] == 800
    assert meta["coordinate_note"] == "no positions in both drives: matched in frames"
    rows = t.to_pydict()
    assert set(rows["matched_by"]) == {"sequence"} and all(s is not None for s in rows["sequence_score"])
    first = [i for i, k in enumerate(rows["rank"]) if k == 0]
    second = {rows["query_row"][i]: i for i, k in enumerate(rows["rank"]) if k == 1}
    for i in first[:50]:  # the confidence is the margin of the best place's score over the next place's
        j = second[rows["query_row"][i]]
        assert rows["confidence"][i] == pytest.approx(rows["sequence_score"][i] - rows["sequence_score"][j])
        assert abs(rows["ref_id"][i] - rows["ref_id"][j]) > 1  # ranks are different places
    single_rows = pq.read_table(tmp_path / "single.parquet").to_pydict()
    assert set(single_rows["matched_by"]) == {"single frame"} and set(single_rows["sequence_score"]) == {None}
    assert json.loads(pq.read_table(tmp_path / "single.parquet").schema.metadata[b"memlog.sequence"])["mode"] == \
        "single frames"
    # the annotated log carries the same confidence, the score and how each frame was matched
    with open_log(tmp_path / "seq.mcap") as log:
        topic = "/camera/image_raw/compressed/memlog/match"
        msgs = {m["frame_index"]: m for m in (decode_record(MATCH, x.channel, x.data) for x in log.messages([topic]))}
    assert len(msgs) == 800
    for i in first[:50]:
        m = msgs[rows["query_id"][i]]
        assert m["matched_by"] == "sequence" and m["sequence_score"] == pytest.approx(rows["sequence_score"][i])
        assert m["confidence"] == pytest.approx(rows["confidence"][i]) and m["speed"] is not None
        assert m["matches"][0]["frame_index"] == rows["ref_id"][i]


def test_cli_causal_and_sparse_maps(nordland_maps: dict[str, Path], tmp_path: Path) -> None:
    import json

    from memlog.cli.app import main
    from tests.conftest import shared

    winter = str(shared("nordland_dev_winter.mcap"))
    quarter = str(nordland_maps["quarter"])
    assert main(["-q", "localize", quarter, winter, "-o", str(tmp_path / "q.parquet")]) == 0
    assert main(["-q", "localize", quarter, winter, "-o", str(tmp_path / "q1.parquet"), "--sequence", "0"]) == 0
    # a quarter map: a place's frame is kept only every 4th frame; measured 0.106 single, 0.410 sequences
    seq, single = _recall_at_1(tmp_path / "q.parquet"), _recall_at_1(tmp_path / "q1.parquet")
    assert single < 0.15 and seq > 0.35, (single, seq)
    assert set(pq.read_table(tmp_path / "q.parquet").to_pydict()["ref_id"]) <= set(range(0, 800, 4))
    assert main(["-q", "localize", str(nordland_maps["full"]), winter, "-o", str(tmp_path / "c.parquet"),
                 "--causal", "--sequence", "5", "--speeds", "0.5:2", "--sequence-k", "5"]) == 0
    t = pq.read_table(tmp_path / "c.parquet")
    meta = json.loads(t.schema.metadata[b"memlog.sequence"])
    assert meta["mode"] == "causal" and meta["length"] == 5 and meta["speeds"] == [0.5, 2.0]
    assert meta["candidates"] == 5
    rows = t.to_pydict()
    by_query = {q: how for q, how in zip(rows["query_id"], rows["matched_by"])}
    # the message counts every frame matched frame by frame, the standing ones that took such a match too
    n_single = sum(how == "single frame" for how in by_query.values())
    assert n_single > 5 and f"{n_single} frame(s): fewer frames of its run before it" in meta["fallback"], \
        meta["fallback"]
    assert meta["fallback_reasons"] == {"causal-start": n_single}
    # the winter drive stands still for its first frames (pixel-identical here): a stop is one place, its
    # frames take its first frame's match, and a causal window needs 5 moving frames before the query frame
    from memlog.io import open_log

    with open_log(winter) as r:
        pixels = [f.decode_bgr() for f, _ in zip(r.frames(), range(30))]
    moved = np.cumsum([0] + [not np.array_equal(a, b) for a, b in zip(pixels, pixels[1:])])
    assert moved[5] == 0  # the check below is about stops
    assert [by_query[i] for i in range(30)] == ["causal sequence" if m >= 5 else "single frame" for m in moved]
    top = {q: ref for q, ref, rank in zip(rows["query_id"], rows["ref_id"], rows["rank"]) if rank == 0}
    assert all(top[i] == top[0] for i in range(30) if moved[i] == 0)
    assert _recall_at_1(tmp_path / "c.parquet") > 0.5  # measured 0.60


@contextlib.contextmanager
def _said() -> Iterator[list[str]]:
    """What memlog's logger says (at INFO and above) inside the block."""
    from memlog.progress import LOGGER

    class Keep(logging.Handler):
        def __init__(self) -> None:
            super().__init__(logging.INFO)
            self.said: list[str] = []

        def emit(self, record: logging.LogRecord) -> None:
            self.said.append(record.getMessage())

    keep, level = Keep(), LOGGER.level
    LOGGER.addHandler(keep)
    LOGGER.setLevel(logging.INFO)  # (a CLI test before may have left it at WARNING: -q)
    try:
        yield keep.said
    finally:
        LOGGER.removeHandler(keep)
        LOGGER.setLevel(level)


def test_localize_says_what_it_matched_frame_by_frame_once(nordland_maps: dict[str, Path], tmp_path: Path) -> None:
    """The fallback is said once, by the step, with the count the outputs record (the sequence
    matcher returns it and does not log it too: the CLI showed it twice)."""
    import json

    from memlog.matching import SequenceConfig
    from memlog.steps.localize import LocalizeConfig, localize
    from tests.conftest import shared

    with _said() as kept:
        localize(nordland_maps["full"], shared("nordland_dev_winter.mcap"), tmp_path / "c.parquet",
                 LocalizeConfig(sequence=SequenceConfig(causal=True, length=5)))
    meta = json.loads(pq.read_table(tmp_path / "c.parquet").schema.metadata[b"memlog.sequence"])
    said = [m for m in kept if "matched frame by frame" in m]
    assert meta["single_queries"] > 5 and said == [meta["fallback"]], said
    assert said[0].startswith(f"{meta['single_queries']} of 800 frames matched frame by frame")


def test_the_query_s_stops_are_found_as_the_map_s(nordland_maps: dict[str, Path], tmp_path: Path) -> None:
    """localize finds the query's stops with the still_distance the map recorded (both drives run
    along moving indices found alike), re-describes a cached query whose stops were found
    otherwise, and warns about a map that does not say how its stops were found."""
    import json

    from memlog.descriptors.extract import describe_log
    from memlog.descriptors.registry import make_describer
    from memlog.descriptors.table import DescriptorTable
    from memlog.descriptors.whitening import WhitenedDescriber
    from memlog.outputs.descriptor_table import read_descriptors, write_descriptors
    from memlog.scoring.motion import stop_rule
    from memlog.selection.segment import SEGMENT_DEFAULTS
    from memlog.steps.localize import localize
    from tests.conftest import shared

    winter = shared("nordland_dev_winter.mcap")
    full = read_descriptors(nordland_maps["full"])
    assert full.extra["stops"] == stop_rule(SEGMENT_DEFAULTS.still_distance)
    # the same map with stops found with still_distance 0 (none: the moving index is the frame index)
    t0, _ = describe_log(shared("nordland_dev_summer.mcap"), make_describer("thumbnail"), still_distance=0.0)
    assert t0.extra["stops"] == stop_rule(0.0) and np.array_equal(t0.moving_index, t0.frame_index)

    def variant(name: str, extra: dict[str, object]) -> Path:
        assert full.whitening is not None
        return write_descriptors(tmp_path / name, DescriptorTable(
            full.topic, full.frame_index, full.log_time_ns, full.stamp_ns, full.descriptors,
            WhitenedDescriber(make_describer("thumbnail"), full.whitening).meta(), extra=extra,
            whitening=full.whitening, moving_index=t0.moving_index if extra.get("stops") else full.moving_index))

    no_stops = variant("no_stops.parquet", t0.extra)
    cache = tmp_path / "query.parquet"
    first = localize(no_stops, winter, tmp_path / "a.parquet", query_descriptors=cache)
    q = read_descriptors(cache)
    assert not first.query_descriptors_reused and q.extra["stops"] == stop_rule(0.0)
    assert np.array_equal(q.moving_index, q.frame_index)  # the winter drive's stations are not stops here
    assert first.sequence["still_distance"] == 0.0 and first.sequence["standing_rows"] == 0
    # against the map with the default rule the cached query is not reused: its stops are found again
    second = localize(nordland_maps["full"], winter, tmp_path / "b.parquet", query_descriptors=cache)
    q = read_descriptors(cache)
    assert not second.query_descriptors_reused and q.extra["stops"] == full.extra["stops"]
    assert second.sequence["standing_rows"] > 100 and (q.moving_index < q.frame_index).any()
    assert localize(nordland_maps["full"], winter, tmp_path / "c.parquet",
                    query_descriptors=cache).query_descriptors_reused

    # a map written before the rule was recorded: matched with the default rule, and said so
    old = variant("old.parquet", {k: v for k, v in full.extra.items() if k != "stops"})
    with _said() as kept:
        res = localize(old, winter, tmp_path / "d.parquet", query_descriptors=cache)
    said = [m for m in kept if "found by an older memlog" in m]
    assert len(said) == 1 and str(old) in said[0] and "--keep-stops" in said[0], kept
    assert res.query_descriptors_reused and res.sequence["still_distance"] == SEGMENT_DEFAULTS.still_distance
    b, d = (pq.read_table(tmp_path / n).to_pydict() for n in ("b.parquet", "d.parquet"))
    assert b["ref_id"] == d["ref_id"]  # the same moving indices as the map with the default rule
    assert json.loads(pq.read_table(tmp_path / "d.parquet").schema.metadata[b"memlog.sequence"])[
        "still_distance"] == SEGMENT_DEFAULTS.still_distance


def test_cli_a_single_image_is_matched_as_a_frame(nordland_maps: dict[str, Path], tmp_path: Path) -> None:
    import json

    from memlog.cli.app import main
    from tests.conftest import shared

    out = tmp_path / "one.parquet"
    assert main(["-q", "localize", str(nordland_maps["full"]), str(shared("nordland_dev_winter.mcap")), "-o", str(out),
                 "--start", "+10", "--end", "+10.05"]) == 0  # one frame of the 10 Hz drive
    t = pq.read_table(out)
    meta = json.loads(t.schema.metadata[b"memlog.sequence"])
    assert meta["sequence_queries"] == 0 and meta["single_queries"] == 1 and "a single image" in meta["fallback"]
    assert set(t.to_pydict()["matched_by"]) == {"single frame"}


@pytest.mark.parametrize("flags, message", [
    (["--sequence", "-1"], "--sequence: must be a whole number >= 0"),
    (["--sequence", "2.5"], "--sequence: expected a whole number"),
    (["--sequence", "ten"], "--sequence: expected a whole number"),
    (["--sequence", "0", "--causal"], "--causal set(s) how sequences are matched, but --sequence 0"),
    (["--sequence", "0", "--speeds", "0:2", "--sequence-k", "4"], "--speeds, --sequence-k set(s)"),
    (["--sequence", "0", "--keep-stops"], "--keep-stops set(s) how sequences are matched"),
    (["--speeds", "3:1"], "--speeds: must be MIN:MAX with 0 <= MIN <= MAX"),
    (["--speeds=-1:2"], "--speeds: must be MIN:MAX"),
    (["--speeds", "1:2:3"], "--speeds: expected MIN:MAX"),
    (["--sequence-k", "0"], "--sequence-k: must be a whole number >= 1"),
    (["--coordinate", "metres"], "--coordinate: invalid choice"),
    (["--max-gap", "0"], "--max-gap: must be > 0"),
])
def test_cli_bad_sequence_flags_are_usage_errors_before_any_work(flags: list[str], message: str, tmp_path: Path,
                                                                 capsys: pytest.CaptureFixture[str]) -> None:
    from memlog.cli.app import main

    # neither input exists: had any work started, the error would be about them, not the flag
    try:
        rc = main(["localize", str(tmp_path / "no-map.parquet"), str(tmp_path / "no-query.mcap"),
                   "-o", str(tmp_path / "m.parquet"), *flags])
    except SystemExit as exc:  # argparse's own value checks exit 2 directly
        rc = exc.code
    assert rc == 2
    assert message in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


def test_cli_positions_without_positions_in_the_map(nordland_maps: dict[str, Path], tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    from memlog.cli.app import main

    rc = main(["localize", str(nordland_maps["full"]), str(tmp_path / "no-query.mcap"), "-o", str(tmp_path / "m.parquet"),
               "--coordinate", "positions"])
    assert rc == 2 and "no position for every frame" in capsys.readouterr().err

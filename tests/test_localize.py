"""Tests of memlog.descriptors.search and memlog.outputs.matches: exact search against brute force, confidence, timing, output."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from memlog.errors import DescriptorError
from memlog.descriptors.search import confidence, match, time_per_query, topk
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
    assert set(full.to_dict()) >= {"seconds_per_query", "n_refs"}


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

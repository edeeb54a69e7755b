"""Patch features and the patch re-ranking (memlog.descriptors.patches, sequence.rerank_by_patches)
against values computed another way: pooling by loops, a frame against itself and a shifted copy,
and a re-ranking whose answer is known."""

from __future__ import annotations

import numpy as np
import pytest

from memlog.descriptors.patches import GRID, PatchPCA, pair_scores, pool_patches
from memlog.matching import SequenceConfig, SequenceMatch, rerank_by_patches
from memlog.errors import DescriptorError


def _unit(x: np.ndarray) -> np.ndarray:
    return (x / np.linalg.norm(x, axis=-1, keepdims=True)).astype(np.float32)


def test_pooling_averages_each_2x2_block_of_the_grid() -> None:
    rng = np.random.default_rng(0)
    tokens = rng.normal(size=(2, 1 + 256, 5)).astype(np.float32)
    got = pool_patches(tokens)
    grid = tokens[:, 1:].reshape(2, 16, 16, 5)
    for b in range(2):
        for r in range(GRID):
            for c in range(GRID):
                want = grid[b, 2 * r : 2 * r + 2, 2 * c : 2 * c + 2].mean(axis=(0, 1))
                np.testing.assert_allclose(got[b, r * GRID + c], want, rtol=1e-5, atol=1e-6)
    with pytest.raises(DescriptorError):
        pool_patches(tokens[:, :200])


def test_the_patch_pca_projects_centres_and_round_trips() -> None:
    rng = np.random.default_rng(1)
    basis = _unit(rng.normal(size=(3, 20)))
    x = rng.normal(size=(50, 64, 3)) @ basis * np.array([5.0, 3.0, 1.0])[None, None, :1] + 7.0
    pca = PatchPCA.fit(x, dim=3)
    assert pca.dim == 3
    np.testing.assert_allclose(pca.mean, x.reshape(-1, 20).mean(axis=0), atol=1e-9)
    y = pca.apply(x[:4])
    assert y.dtype == np.float16 and y.shape == (4, 64, 3)
    np.testing.assert_allclose(np.linalg.norm(y.astype(np.float32), axis=-1), 1.0, atol=2e-3)
    again = PatchPCA.from_json(pca.to_json())
    assert again.sha256 == pca.sha256
    np.testing.assert_array_equal(again.apply(x[:4]), y)
    tampered = pca.to_json().replace('"sha256": "', '"sha256": "0')
    with pytest.raises(DescriptorError, match="sha256"):
        PatchPCA.from_json(tampered)


def test_pair_scores_count_patches_that_match_in_place() -> None:
    rng = np.random.default_rng(2)
    a = _unit(rng.normal(size=(64, 32)))
    grid = a.reshape(GRID, GRID, 32)
    shifted = np.roll(grid, 1, axis=1)  # the view turned by one cell: column c shows what c - 1 showed
    shifted[:, 0] = _unit(rng.normal(size=(GRID, 32)))  # and a new column comes in
    other = _unit(rng.normal(size=(64, 32)))
    q = np.stack([a, a, a])
    r = np.stack([a, shifted.reshape(64, 32), other])
    got = pair_scores(q, r, [0, 1, 2], [0, 1, 2])
    assert got[0] == 64  # every patch with itself, offset 0
    assert got[1] == 56  # the 7 columns seen again, all at the one offset (+1 cell)
    assert got[2] < 16  # unrelated patches: mutual pairs by chance, at scattered offsets
    # half the patches moved elsewhere: the half in place counts (the median offset is theirs, 0), the
    # moved ones only where they landed within a cell of where they were
    scrambled = a.copy()
    moved = rng.permutation(64)[:32]
    to = rng.permutation(moved)
    scrambled[to] = a[moved]
    near = np.sum((np.abs(to % GRID - moved % GRID) <= 1) & (np.abs(to // GRID - moved // GRID) <= 1))
    assert pair_scores(a[None], scrambled[None], [0], [0])[0] == 32 + near


def test_rerank_puts_the_place_whose_patches_match_first() -> None:
    """Single frames: query q's candidates are map rows in some order; the map row whose patches
    equal the query's must come first, the margin is its score minus the next place's."""
    rng = np.random.default_rng(3)
    n_map, n_q = 30, 4
    r_patches = _unit(rng.normal(size=(n_map, 64, 16))).astype(np.float16)
    truth = np.array([7, 12, 20, 25])
    q_patches = r_patches[truth].copy()
    q_desc = _unit(rng.normal(size=(n_q, 8)))
    r_desc = _unit(rng.normal(size=(n_map, 8)))
    cand = np.array([[3, 15, 7, 28], [12, 2, 5, 9], [1, 20, 22, 18], [4, 25, 26, 0]])
    res = SequenceMatch(cand, np.zeros(cand.shape), np.zeros(cand.shape, np.float32), np.zeros(n_q),
                        np.full(n_q, np.nan), np.ones(n_q, np.int64), np.zeros(n_q, bool), np.zeros(n_q),
                        np.array(["single"] * n_q), {"length_used": 0})
    rc = np.arange(n_map, dtype=np.float64)
    out = rerank_by_patches(res, q_desc, r_desc, q_patches, r_patches, np.arange(n_q, dtype=np.float64), rc,
                            np.arange(n_map), np.arange(n_q), SequenceConfig(length=0), 3, 1.0)
    np.testing.assert_array_equal(out.indices[:, 0], truth)
    assert out.indices.shape == (n_q, 3) and out.rerank is not None
    assert np.all(out.rerank[:, 0] == 64)
    expect_margin = 64 - np.array([pair_scores(q_patches, r_patches, [i], [out.indices[i, 1]])[0]
                                   for i in range(n_q)])  # the next candidate is another place here
    np.testing.assert_array_equal(out.margin, expect_margin)
    np.testing.assert_array_equal(out.confidence, expect_margin)
    # the other candidates keep their order behind it when their scores tie
    assert set(out.indices[1]) <= set(cand[1])

"""The patch re-rank wired through memlog: patch features from the describer's own network pass,
stored with the map (Parquet round trip, PCA fitted on the kept frames), projected for a query
with the map's PCA, and the drive matcher's re-rank — each checked against values computed
another way (the tokens of block 7 pooled by hand, a PCA from an SVD, pair scores by brute force).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from memlog.descriptors.base import DescriptorMeta
from memlog.descriptors.patches import GRID, PATCH_LAYER, PatchPCA, PatchPCAFitter, PatchStore, pair_scores, pool_patches
from memlog.matching import RERANK_PLACES, SequenceConfig, match_tables
from memlog.descriptors.table import DescriptorTable
from memlog.errors import DescriptorError
from memlog.outputs.descriptor_table import read_descriptors, write_descriptors

P = GRID * GRID


def _unit(x: np.ndarray) -> np.ndarray:
    return (x / np.linalg.norm(x, axis=-1, keepdims=True)).astype(np.float32)


def _tables(n_ref: int = 60, n_q: int = 40, dim: int = 16, pdim: int = 12, seed: int = 0
            ) -> tuple[DescriptorTable, DescriptorTable, PatchPCA]:
    """A map and a query drive along it (query frame i near map frame i + 5), with raw patches:
    the map's projected by a PCA fitted on them, the query's left raw."""
    rng = np.random.default_rng(seed)
    places = _unit(rng.normal(size=(n_ref, dim)))
    ref_patch = rng.normal(size=(n_ref, P, pdim))
    q_rows = np.arange(n_q) + 5
    q_desc = _unit(places[q_rows] + 0.9 * rng.normal(size=(n_q, dim)))
    q_patch = ref_patch[q_rows] + 0.6 * rng.normal(size=(n_q, P, pdim))
    pca = PatchPCA.fit(ref_patch, dim=8)
    meta = DescriptorMeta("test", "1", dim, None, {})

    def table(desc: np.ndarray, patches: np.ndarray, p: PatchPCA | None) -> DescriptorTable:
        n = len(desc)
        idx = np.arange(n)
        return DescriptorTable(["/cam"] * n, idx, idx * 100_000_000, idx * 100_000_000, desc, meta,
                               moving_index=idx, patches=p.apply(patches) if p is not None else patches,
                               patch_pca=p)

    return table(places, ref_patch, pca), table(q_desc, q_patch, None), pca


def test_the_patch_pca_from_moments_equals_an_svd() -> None:
    rng = np.random.default_rng(3)
    x = rng.normal(size=(30, P, 10)) * np.linspace(3, 0.2, 10) + 4.0
    fitter = PatchPCAFitter(10)
    for a in range(0, 30, 7):  # batch by batch
        fitter.add(x[a : a + 7])
    pca = fitter.fit(dim=4)
    assert pca is not None
    flat = x.reshape(-1, 10)
    _u, _s, vt = np.linalg.svd(flat - flat.mean(axis=0), full_matrices=False)
    for got, want in zip(pca.components, vt[:4]):
        assert abs(abs(float(got @ want)) - 1.0) < 1e-9  # the same directions (up to sign)
    assert PatchPCAFitter(10).fit() is None


def test_the_patch_store_gives_back_every_row_projected(tmp_path: Path) -> None:
    rng = np.random.default_rng(4)
    x = rng.normal(size=(37, P, 10)).astype(np.float16)
    store = PatchStore()
    for a in range(0, 37, 5):
        store.add(x[a : a + 5])
    pca = PatchPCA.fit(x, dim=6)
    np.testing.assert_array_equal(store.projected(pca, block=8), pca.apply(x))
    store.close()
    with pytest.raises(DescriptorError):
        s2 = PatchStore()
        s2.add(x[:2])
        s2.add(rng.normal(size=(1, P, 9)))


def test_patches_and_their_pca_round_trip_through_parquet(tmp_path: Path) -> None:
    ref, query, pca = _tables()
    write_descriptors(tmp_path / "m.parquet", ref)
    back = read_descriptors(tmp_path / "m.parquet")
    assert back.patch_pca is not None and back.patch_pca.sha256 == pca.sha256
    assert back.patches is not None
    np.testing.assert_array_equal(back.patches, ref.patches)
    write_descriptors(tmp_path / "q.parquet", query)  # raw patches (a cached evaluate table)
    q = read_descriptors(tmp_path / "q.parquet")
    assert q.patch_pca is None and q.patches is not None
    np.testing.assert_array_equal(q.patches, np.asarray(query.patches, dtype=np.float16))
    # the query in the map's space: projected by the map's PCA
    np.testing.assert_array_equal(q.projected(back.patch_pca).patches, pca.apply(q.patches))
    # a table without patches reads without them
    plain = DescriptorTable(ref.topic, ref.frame_index, ref.log_time_ns, ref.stamp_ns, ref.descriptors, ref.meta)
    write_descriptors(tmp_path / "p.parquet", plain)
    assert read_descriptors(tmp_path / "p.parquet").patches is None


def test_a_tampered_patch_pca_is_refused(tmp_path: Path) -> None:
    import pyarrow.parquet as pq

    ref, _query, _pca = _tables()
    write_descriptors(tmp_path / "m.parquet", ref)
    t = pq.read_table(tmp_path / "m.parquet")
    md = dict(t.schema.metadata)
    md[b"memlog.patch_pca"] = md[b"memlog.patch_pca"].replace(b'"sha256": "', b'"sha256": "f')
    pq.write_table(t.replace_schema_metadata(md), tmp_path / "bad.parquet")
    with pytest.raises(DescriptorError, match="bad.parquet"):
        read_descriptors(tmp_path / "bad.parquet")


def test_single_frames_are_reranked_by_brute_force_pair_scores() -> None:
    ref, query, pca = _tables()
    cfg = SequenceConfig(length=0)
    plain = match_tables(query, ref, SequenceConfig(length=0, rerank=False), k=RERANK_PLACES)
    res = match_tables(query, ref, cfg, k=5)
    assert res.info["rerank"]["by"] == "patches" and res.info["rerank"]["patch_pca"] == pca.sha256
    qp = pca.apply(np.asarray(query.patches))
    assert res.rerank is not None
    for q in range(len(query)):
        # the re-ranked places are the descriptor match's best RERANK_PLACES, ordered by their pair score
        cand = [int(c) for c in plain.indices[q] if c >= 0]
        want = {c: int(pair_scores(qp, ref.patches, [q], [c])[0]) for c in cand}
        best = sorted(cand, key=lambda c: -want[c])[:5]
        assert [want[int(c)] for c in res.indices[q]] == [want[c] for c in best]
        np.testing.assert_array_equal(res.rerank[q], [want[int(c)] for c in res.indices[q]])
        # the confidence is the re-rank's margin: best minus the best other place
        others = [want[c] for c in cand if abs(c - int(res.indices[q, 0])) > cfg.exclude]
        assert res.confidence[q] == pytest.approx(res.rerank[q, 0] - max(others))
    # the re-rank helps here (the query's patches are the true place's, noisier descriptors)
    truth = np.arange(len(query)) + 5
    assert (res.indices[:, 0] == truth).mean() > (plain.indices[:, 0] == truth).mean()


def test_rerank_off_or_impossible_leaves_the_descriptor_match_and_says_why() -> None:
    ref, query, _pca = _tables()
    off = match_tables(query, ref, SequenceConfig(rerank=False), k=5)
    assert off.rerank is None and "--no-rerank" in off.info["rerank"]["off"]
    bare = DescriptorTable(ref.topic, ref.frame_index, ref.log_time_ns, ref.stamp_ns, ref.descriptors, ref.meta,
                           moving_index=ref.moving_index)
    none = match_tables(query, bare, SequenceConfig(), k=5)
    assert none.rerank is None and "no patch features" in none.info["rerank"]["off"]
    np.testing.assert_array_equal(none.indices, off.indices)
    other = PatchPCA.fit(np.random.default_rng(9).normal(size=(5, P, 12)), dim=8)
    q_other = query.projected(other)  # projected by another map's PCA: not comparable
    res = match_tables(q_other, ref, SequenceConfig(), k=5)
    assert res.rerank is None and "PCA" in res.info["rerank"]["off"]


def test_sequences_are_reranked_and_keep_their_rows() -> None:
    ref, query, _pca = _tables(seed=1)
    res = match_tables(query, ref, SequenceConfig(length=3, hmm=False), k=5)
    off = match_tables(query, ref, SequenceConfig(length=3, rerank=False), k=RERANK_PLACES)
    assert res.rerank is not None and res.indices.shape == (len(query), 5) and res.posterior is None
    assert "--no-hmm" in res.info["hmm"]["off"]
    # the drive HMM (the default) orders the same re-ranked places by their probability along the drive
    hmm = match_tables(query, ref, SequenceConfig(length=3), k=5)
    assert hmm.posterior is not None and hmm.info["hmm"]["posterior"] == "forward-backward"
    for q in range(len(query)):
        assert set(res.indices[q].tolist()) <= set(off.indices[q].tolist())  # the same places, re-ordered
        assert set(hmm.indices[q].tolist()) <= set(off.indices[q].tolist())
        assert np.all(np.diff(res.rerank[q]) <= 1e-12)  # best first
        assert np.all(np.diff(hmm.posterior[q]) <= 1e-12) and 0 <= hmm.confidence[q] <= 1
    np.testing.assert_array_equal(res.sequence, off.sequence)


def test_dinov2_patches_come_from_the_same_pass_as_block_7_tokens_pooled() -> None:
    from memlog.descriptors.registry import make_describer
    from memlog.descriptors.whitening import WhitenedDescriber, fit_whitening

    rng = np.random.default_rng(5)
    imgs = [rng.integers(0, 255, (96, 256, 3), dtype=np.uint8) for _ in range(3)]
    d = make_describer("dinov2-gem")
    desc, patches = d.describe_patches(imgs)
    np.testing.assert_allclose(desc, d.describe(imgs), atol=1e-6)
    block7 = make_describer("dinov2-gem", layer=PATCH_LAYER).tokens(imgs)
    assert patches is not None and patches.shape == (3, P, 384)
    np.testing.assert_allclose(patches, pool_patches(block7), rtol=1e-4, atol=1e-4)
    white = fit_whitening(rng.normal(size=(40, 384)).astype(np.float32), max_dim=8)
    wd = WhitenedDescriber(d, white)
    wdesc, wpatches = wd.describe_patches(imgs)
    assert wd.gives_patches and wpatches is not None
    np.testing.assert_allclose(wdesc, white.apply(desc), atol=1e-5)
    np.testing.assert_allclose(wpatches, patches, atol=1e-6)
    thumb = make_describer("thumbnail")
    assert not thumb.gives_patches and thumb.describe_patches(imgs)[1] is None


@pytest.mark.parametrize("seed", range(5))
def test_stop_runs_cut_after_each_long_stop(seed: int) -> None:
    """Against a loop over the rows: a new run at each run's start and at the first moving row
    after at least ``min_stop`` standing rows of the same run."""
    from memlog.matching.coordinates import stop_runs

    rng = np.random.default_rng(seed)
    labels = np.repeat(np.arange(4), rng.integers(1, 30, size=4))
    standing = rng.random(len(labels)) < 0.6
    standing[np.r_[True, labels[1:] != labels[:-1]]] = False  # a run's first row never stands
    for min_stop in (1, 3):
        want, run, streak = [], -1, 0
        for i in range(len(labels)):
            if i == 0 or labels[i] != labels[i - 1] or (not standing[i] and streak >= min_stop):
                run += 1
            streak = streak + 1 if standing[i] else 0
            want.append(run)
        got = stop_runs(labels, standing, min_stop)
        cuts = len(set(want)) > len(set(labels.tolist()))
        assert (got is None) == (not cuts)
        if got is not None:
            assert got.tolist() == want


def test_the_rerank_takes_its_speeds_from_windows_cut_at_the_query_stops() -> None:
    """Each sequence row is re-ranked along the speed the descriptor stage gives it with the query's
    runs cut after every stop of SPEED_STOP standing frames (computed here by match_sequences on
    runs cut by hand); without such a stop, along its own window's speed."""
    from memlog.matching import match_sequences
    from memlog.matching.matcher import SPEED_STOP

    ref, query, _pca = _tables(n_ref=90, n_q=60, seed=2)
    mi = np.r_[np.arange(20), np.full(SPEED_STOP, 19), np.arange(20, 60 - SPEED_STOP)]  # one stop after row 19
    query = DescriptorTable(query.topic, query.frame_index, query.log_time_ns, query.stamp_ns, query.descriptors,
                            query.meta, moving_index=mi, patches=query.patches)
    cfg = SequenceConfig(hmm=False)
    res = match_tables(query, ref, cfg, k=5)
    standing = np.r_[False, mi[1:] == mi[:-1]]
    cut = (np.arange(60) >= 20 + SPEED_STOP).astype(np.int64)
    whole = match_sequences(query.descriptors, mi.astype(float), ref.descriptors, ref.moving_index.astype(float), cfg,
                            k=5, standing=standing)
    own = match_sequences(query.descriptors, mi.astype(float), ref.descriptors, ref.moving_index.astype(float), cfg,
                          k=1, runs=cut, standing=standing)
    both = whole.sequence & own.sequence
    assert both.sum() > 40 and "cut at the query's stops" in res.info["rerank"]["speeds"]
    assert (own.speed[both] != whole.speed[both]).any()  # the cut windows vote other speeds near the stop
    np.testing.assert_allclose(res.speed[both], own.speed[both])
    # a stop one frame shorter cuts nothing: the windows' own speeds
    short = np.r_[np.arange(20), np.full(SPEED_STOP - 1, 19), np.arange(20, 61 - SPEED_STOP)]
    query = DescriptorTable(query.topic, query.frame_index, query.log_time_ns, query.stamp_ns, query.descriptors,
                            query.meta, moving_index=short, patches=query.patches)
    res = match_tables(query, ref, cfg, k=5)
    whole = match_sequences(query.descriptors, short.astype(float), ref.descriptors, ref.moving_index.astype(float),
                            cfg, k=5, standing=np.r_[False, short[1:] == short[:-1]])
    assert res.info["rerank"]["speeds"] == "the windows' own"
    np.testing.assert_allclose(res.speed[whole.sequence], whole.speed[whole.sequence])

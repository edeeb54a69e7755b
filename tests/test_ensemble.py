"""The whitening ensemble (:mod:`memlog.matching.ensemble`): a small map's drive matched in several
whitened dimensions, each query frame's places ranked by their mean probability along the drive.

Checked against independent expectations:
- :func:`combine` on hand-made members: the mean probability (a place a member did not propose
  counts 0 there), each place's columns from the first member that proposed it;
- the leading dimensions of a whitened descriptor, renormalised, are the descriptor whitened to
  that many dimensions (a whitening fitted with that ``max_dim``);
- on the shared Stromovka drive pair, ``memlog localize`` (the CLI, as a user runs it) gives every
  query frame the place that matching the drive once per dimension with the ensemble off, and
  averaging the place probabilities here, gives; ``--no-ensemble`` gives the whole whitening's.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from memlog.cli.app import main
from memlog.descriptors.whitening import fit_whitening
from memlog.matching import SequenceConfig, match_tables
from memlog.matching.config import SequenceMatch
from memlog.matching.ensemble import combine, ensemble_dims, leading
from memlog.matching.rerank import RERANK_PLACES
from tests.conftest import shared


def _member(idx: list[list[int]], post: list[list[float]], score: float) -> SequenceMatch:
    i = np.array(idx, dtype=np.int64)
    n_q, k = i.shape
    return SequenceMatch(i, np.full((n_q, k), score), np.zeros((n_q, k), np.float32), np.zeros(n_q),
                         np.full(n_q, score), np.ones(n_q, np.int64), np.ones(n_q, bool), np.zeros(n_q),
                         np.array([""] * n_q), {"who": score}, np.full((n_q, k), score), np.array(post, float))


def test_combine_ranks_places_by_their_mean_probability() -> None:
    a = _member([[3, 5, -1], [0, 1, 2]], [[0.6, 0.4, 0.0], [0.5, 0.3, 0.2]], 1.0)
    b = _member([[5, 7, 3], [2, 1, 0]], [[0.7, 0.2, 0.1], [0.9, 0.1, 0.0]], 2.0)
    q = np.eye(8, 4, dtype=np.float32)[:2]
    r = np.eye(8, 4, dtype=np.float32)
    out = combine([a, b], q, r)
    # row 0: 5 -> (0.4 + 0.7) / 2, 3 -> (0.6 + 0.1) / 2, 7 -> 0.2 / 2
    assert out.indices[0].tolist() == [5, 3, 7]
    np.testing.assert_allclose(out.posterior[0], [0.55, 0.35, 0.1])
    # row 1: 2 -> 0.55, 0 -> 0.25, 1 -> 0.2
    assert out.indices[1].tolist() == [2, 0, 1]
    np.testing.assert_allclose(out.posterior[1], [0.55, 0.25, 0.2])
    # columns from the first member that proposed the place: 7 only from b
    assert out.scores[0].tolist() == [1.0, 1.0, 2.0] and out.rerank is not None and out.rerank[0, 2] == 2.0
    # similarities in the whole whitening: q . r of the place
    np.testing.assert_allclose(out.similarities, (q @ r.T)[np.arange(2)[:, None], out.indices])
    assert out.info == {"who": 1.0} and out.speed.tolist() == [1.0, 1.0]


def test_leading_dimensions_are_a_smaller_whitening() -> None:
    rng = np.random.default_rng(3)
    x = rng.normal(size=(60, 20)) @ rng.normal(size=(20, 20))
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    whole = fit_whitening(x)
    for d in ensemble_dims(whole)[1:]:
        small = fit_whitening(x, max_dim=d)
        np.testing.assert_allclose(leading(whole.apply(x), d), small.apply(x), atol=1e-5)
    assert ensemble_dims(whole) == [20, 16, 12, 8] and whole.dim_out == 20  # min(dim_in, n // 2)


@pytest.fixture(scope="module")
def localized(tmp_path_factory: pytest.TempPathFactory, drive_pair_maps: dict[str, tuple[Path, Path]]
              ) -> dict[str, Path]:
    """`memlog localize` of the winter drive against the default map, keeping its query descriptors,
    and again with --no-ensemble."""
    d = tmp_path_factory.mktemp("ensemble")
    parquet, _ = drive_pair_maps["default"]
    winter = shared("stromovka_drive_winter.mcap")
    out = {"map": parquet, "q": d / "q.parquet"}
    for name, extra in (("on", ["--query-descriptors", str(out["q"])]), ("off", ["--no-ensemble"])):
        out[name] = d / f"{name}.parquet"
        assert main(["-q", "localize", str(parquet), str(winter), "-o", str(out[name]), *extra]) == 0
    return out


def _best(matches: Path) -> dict[int, int]:
    t = pq.read_table(matches).to_pydict()
    return {q: r for q, r, k in zip(t["query_id"], t["ref_id"], t["rank"]) if k == 0}


def test_localize_averages_the_place_probabilities_of_each_dimension(localized: dict[str, Path]) -> None:
    from memlog.outputs.descriptor_table import read_descriptors

    ref = read_descriptors(localized["map"])
    query = read_descriptors(localized["q"])
    assert ref.whitening is not None
    dims = ensemble_dims(ref.whitening)
    assert len(dims) == 4 and dims[0] == ref.whitening.dim_out
    off = SequenceConfig(ensemble=False)
    total = np.zeros((len(query), len(ref)))
    for d in dims:  # each member by hand: the tables cut to d dimensions, matched once
        r = replace(ref, descriptors=leading(ref.descriptors, d), whitening=None, meta=replace(ref.meta, dim=d))
        q = replace(query, descriptors=leading(query.descriptors, d), meta=replace(query.meta, dim=d))
        m = match_tables(q, r, SequenceConfig(), k=RERANK_PLACES)
        assert m.info["ensemble"] == {"off": "the map is not whitened"} and m.posterior is not None
        rows, cols = np.nonzero(m.indices >= 0)
        np.add.at(total, (rows, m.indices[rows, cols]), m.posterior[rows, cols])
    want = {int(qf): int(ref.frame_index[np.argmax(total[i])]) for i, qf in enumerate(query.frame_index)}
    got = _best(localized["on"])
    assert got == want
    # the ensemble is what changed the answers: --no-ensemble is the whole whitening matched once
    once = match_tables(query, ref, off, k=1)
    assert _best(localized["off"]) == {int(qf): int(ref.frame_index[i]) for qf, i in
                                       zip(query.frame_index, once.indices[:, 0])}
    assert sum(got[q] != _best(localized["off"])[q] for q in got) > 0

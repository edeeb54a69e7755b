"""The whitening ensemble (:mod:`memlog.matching.ensemble`): a small map's drive matched in several
whitened dimensions, every member's re-ranked places decided by one drive HMM.

Checked against independent expectations:
- :func:`union` on hand-made members: every member's places, each with its mean re-rank score over
  the members that proposed it, the highest summed score kept first, each place's columns from the
  first member that proposed it;
- the leading dimensions of a whitened descriptor, renormalised, are the descriptor whitened to
  that many dimensions (a whitening fitted with that ``max_dim``);
- on the shared Stromovka drive pair, ``memlog localize`` (the CLI, as a user runs it) gives every
  query frame the place that re-ranking the drive once per dimension without the HMM, uniting the
  members' places here in plain Python and running the drive HMM (:func:`place_probabilities`) once
  over them gives; ``--no-ensemble`` gives the whole whitening's.
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
from memlog.matching.ensemble import ensemble_dims, leading, union
from memlog.matching.rerank import RERANK_PLACES
from tests.conftest import shared


def _member(idx: list[list[int]], rerank: list[list[float]], score: float) -> SequenceMatch:
    i = np.array(idx, dtype=np.int64)
    n_q, k = i.shape
    return SequenceMatch(i, np.full((n_q, k), score), np.zeros((n_q, k), np.float32), np.zeros(n_q),
                         np.full(n_q, score), np.ones(n_q, np.int64), np.ones(n_q, bool), np.zeros(n_q),
                         np.array([""] * n_q), {"who": score}, np.array(rerank, float))


def test_union_keeps_every_members_places_with_their_mean_rerank_score() -> None:
    a = _member([[3, 5, -1], [0, 1, 2]], [[6.0, 4.0, np.nan], [5.0, 3.0, 2.0]], 1.0)
    b = _member([[5, 7, 3], [2, 1, 0]], [[7.0, 2.0, 1.0], [9.0, 1.0, 0.5]], 2.0)
    c = _member([[9, 8, 7], [4, 5, 6]], [[8.0, 8.0, 8.0], [1.0, 1.0, 1.0]], 3.0)
    q = np.eye(10, 4, dtype=np.float32)[:2]
    r = np.eye(10, 4, dtype=np.float32)
    out = union([a, b, c], q, r)
    # row 0 summed: 5 -> 11, 7 -> 10, 8 -> 8, 9 -> 8, 3 -> 7; three columns kept, 8 before 9 on the tie
    assert out.indices[0].tolist() == [5, 7, 8]
    np.testing.assert_allclose(out.rerank[0], [11 / 2, 10 / 2, 8.0])  # mean over the members proposing it
    # row 1 summed: 2 -> 11, 0 -> 5.5, 1 -> 4 (then 4, 5, 6 -> 1, cut)
    assert out.indices[1].tolist() == [2, 0, 1]
    np.testing.assert_allclose(out.rerank[1], [5.5, 2.75, 2.0])
    # a place's descriptor score from the first member that proposed it: 7 from b, 8 from c
    assert out.scores[0].tolist() == [1.0, 2.0, 3.0] and out.posterior is None
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


def _by_hand_union(members: list[SequenceMatch], width: int) -> tuple[np.ndarray, np.ndarray]:
    """Each row's places over the members (at most ``width``: highest summed re-rank score first),
    with their mean re-rank score over the members that proposed them, in plain Python."""
    n_q = members[0].indices.shape[0]
    idx, score = np.full((n_q, width), -1), np.full((n_q, width), -np.inf)
    for i in range(n_q):
        seen: dict[int, list[float]] = {}
        for m in members:
            assert m.rerank is not None
            for j, s in zip(m.indices[i], m.rerank[i]):
                if j >= 0:
                    seen.setdefault(int(j), []).append(float(s))
        ranked = sorted(seen, key=lambda j: (-sum(seen[j]), j))[:width]
        idx[i, :len(ranked)] = ranked
        score[i, :len(ranked)] = [sum(seen[j]) / len(seen[j]) for j in ranked]
    return idx, score


def test_localize_decides_every_members_places_with_one_drive_hmm(localized: dict[str, Path]) -> None:
    from memlog.matching.coordinates import drive_coordinates, drive_runs
    from memlog.matching.drive_hmm import place_probabilities
    from memlog.matching.paths import _run_bounds
    from memlog.outputs.descriptor_table import read_descriptors

    ref = read_descriptors(localized["map"])
    query = read_descriptors(localized["q"])
    assert ref.whitening is not None and drive_runs(ref)[0].max() == 0  # the map is one run
    dims = ensemble_dims(ref.whitening)
    assert len(dims) == 4 and dims[0] == ref.whitening.dim_out
    members = []
    for d in dims:  # each member by hand: the tables cut to d dimensions, re-ranked without the HMM
        r = replace(ref, descriptors=leading(ref.descriptors, d), whitening=None, meta=replace(ref.meta, dim=d))
        q = replace(query, descriptors=leading(query.descriptors, d), meta=replace(query.meta, dim=d))
        members.append(match_tables(q, r, SequenceConfig(hmm=False), k=RERANK_PLACES))
        assert members[-1].info["hmm"] == {"off": "turned off (--no-hmm)"} and members[-1].posterior is None
    idx, score = _by_hand_union(members, RERANK_PLACES)
    # one drive HMM over those places, in the drive's frame coordinates (stops left out)
    qc, rc = drive_coordinates(query, "frames", True), drive_coordinates(ref, "frames", True)
    lo, hi = _run_bounds(drive_runs(query)[0], qc)
    steps = np.diff(np.sort(rc))
    info = members[0].info
    post, owner = place_probabilities(score, np.where(idx >= 0, rc[np.maximum(idx, 0)], 0.0), qc, lo, hi,
                                      pace=float(info["pace"]), spacing=float(np.median(steps[steps > 0])),
                                      vmax=float(info["speeds"][1]), causal=False)
    want = {int(qf): int(ref.frame_index[idx[o, np.argmax(post[o])]]) for qf, o in zip(query.frame_index, owner)}
    got = _best(localized["on"])
    assert got == want
    # the ensemble is what changed the answers: --no-ensemble is the whole whitening matched once
    once = match_tables(query, ref, SequenceConfig(ensemble=False), k=1)
    assert _best(localized["off"]) == {int(qf): int(ref.frame_index[i]) for qf, i in
                                       zip(query.frame_index, once.indices[:, 0])}
    assert sum(got[q] != _best(localized["off"])[q] for q in got) > 0

"""The drive HMM (``memlog.matching.drive_hmm``): each frame's place decided with its neighbours'.

Checked against values computed another way: the posterior (and, causal, the filtered) place
probabilities against a brute-force sum over every path of a small chain, written here from the
model's definition (emission ``beta * score``; a move of ``d`` after a query step ``dq`` at speed
``max(d, spacing / 2) / (pace dq)`` between 0 and ``vmax dq + spacing`` costs ``speed_cost |log2
speed|``, plus a jump of ``jump_cost`` from anywhere to anywhere); an outlier frame corrected by its
neighbours; standing frames and separate runs.
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from memlog.matching.drive_hmm import BETA, JUMP_COST, SPEED_COST, place_probabilities


def _log_trans(x0: float, x1: float, dq: float, pace: float, spacing: float, vmax: float) -> float:
    d = x1 - x0
    p = math.exp(-JUMP_COST)
    if -1e-9 <= d <= vmax * dq + spacing:
        p += math.exp(-SPEED_COST * abs(math.log2(max(d, spacing / 2) / (pace * dq))))
    return math.log(p)


def _brute(score: np.ndarray, x: np.ndarray, qc: np.ndarray, upto: int | None = None, *, pace: float = 1.0,
           spacing: float = 1.0, vmax: float = 3.0) -> np.ndarray:
    """Marginal place probabilities of frame ``upto`` (None: of every frame, from the whole chain)
    by summing over every path of the first ``upto + 1`` frames (or all)."""
    n, k = score.shape
    last = n if upto is None else upto + 1
    out = np.zeros((last, k))
    for path in itertools.product(range(k), repeat=last):
        lp = sum(BETA * score[t, path[t]] for t in range(last))
        lp += sum(_log_trans(x[t - 1, path[t - 1]], x[t, path[t]], qc[t] - qc[t - 1], pace, spacing, vmax)
                  for t in range(1, last))
        w = math.exp(lp)
        for t in range(last):
            out[t, path[t]] += w
    out /= out.sum(axis=1, keepdims=True)
    return out


def _chain(seed: int, n: int = 5, k: int = 3) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    qc = np.cumsum(rng.integers(1, 3, size=n)).astype(float)
    x = np.sort(rng.uniform(0, 12, size=(n, k)), axis=1) + np.arange(n)[:, None]
    score = rng.normal(size=(n, k))
    return score, x, qc


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_posterior_equals_the_sum_over_every_path(seed: int) -> None:
    score, x, qc = _chain(seed)
    n = len(qc)
    post, owner = place_probabilities(score, x, qc, np.zeros(n, np.int64), np.full(n, n), pace=1.0, spacing=1.0,
                                      vmax=3.0, causal=False)
    np.testing.assert_allclose(post, _brute(score, x, qc), atol=1e-9)
    np.testing.assert_array_equal(owner, np.arange(n))
    # causal: frame t's probabilities use the frames up to t only (filtered)
    filt, _ = place_probabilities(score, x, qc, np.zeros(n, np.int64), np.full(n, n), pace=1.0, spacing=1.0,
                                  vmax=3.0, causal=True)
    for t in range(n):
        np.testing.assert_allclose(filt[t], _brute(score, x, qc, upto=t)[t], atol=1e-9)


def test_a_missing_place_has_probability_zero() -> None:
    score, x, qc = _chain(4)
    score[2, 1] = -np.inf
    n = len(qc)
    post, _ = place_probabilities(score, x, qc, np.zeros(n, np.int64), np.full(n, n), pace=1.0, spacing=1.0,
                                  vmax=3.0, causal=False)
    assert post[2, 1] == 0.0
    np.testing.assert_allclose(post.sum(axis=1), 1.0)


def test_an_outlier_frame_is_decided_by_its_neighbours() -> None:
    """A drive along places 0, 1, 2, ... at speed 1; frame 5's own best place is far away (a look-alike)."""
    n = 10
    qc = np.arange(n, dtype=float)
    x = np.stack([qc, qc + 40.0], axis=1)  # candidate 0: the true place, candidate 1: a place far on
    score = np.tile([3.0, 0.0], (n, 1))
    score[5] = [1.0, 3.5]  # frame 5 alone prefers the look-alike
    post, _ = place_probabilities(score, x, qc, np.zeros(n, np.int64), np.full(n, n), pace=1.0, spacing=1.0,
                                  vmax=3.0, causal=False)
    assert post[5, 0] > 0.9 and np.all(post[:, 0] > 0.9)


def test_standing_frames_are_their_stops_first_frame_and_runs_are_separate() -> None:
    score, x, qc = _chain(3, n=4)
    # rows 0..3 a run with a stop (row 2 stands at row 1's coordinate), rows 4..7 a second run
    qc1 = np.array([qc[0], qc[1], qc[1], qc[2]])
    s1 = np.vstack([score[0], score[1], score[1] + 5.0, score[2]])  # a standing row's own scores are not used
    x1 = np.vstack([x[0], x[1], x[1], x[2]])
    s2 = np.random.default_rng(8).normal(size=(4, 3))
    x2 = np.sort(np.random.default_rng(9).uniform(0, 9, size=(4, 3)), axis=1)
    qc2 = np.arange(4, dtype=float)
    sc = np.vstack([s1, s2])
    xx = np.vstack([x1, x2])
    qq = np.r_[qc1, qc2]
    lo = np.r_[np.zeros(4), np.full(4, 4)].astype(np.int64)
    hi = np.r_[np.full(4, 4), np.full(4, 8)].astype(np.int64)
    post, owner = place_probabilities(sc, xx, qq, lo, hi, pace=1.0, spacing=1.0, vmax=3.0, causal=False)
    np.testing.assert_array_equal(owner, [0, 1, 1, 3, 4, 5, 6, 7])
    moving = [0, 1, 3]
    np.testing.assert_allclose(post[moving], _brute(score[:3], x[:3], qc[:3]), atol=1e-9)
    np.testing.assert_allclose(post[4:], _brute(s2, x2, qc2), atol=1e-9)  # the second run alone

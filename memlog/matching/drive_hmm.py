"""The drive's most likely path through every frame's candidate places (a hidden Markov model).

The sequence matcher and the patch re-rank give each query frame a short list of candidate places
(the re-rank's places, best first) and a score for each: how well the patches of the frame's
window match along that place's path. Each frame decides alone, and on a drive that stops,
crawls and speeds up a window that straddles a change of speed scores the wrong place best now
and then. Consecutive frames of a drive are not independent: the place of the next frame lies a
little further along the map. :func:`place_probabilities` therefore decides every frame's place
with its neighbours', as a hidden Markov model over each query run
(:func:`memlog.matching.match_tables` ranks the places by it):

* **states**: the frame's candidate places (map rows, at most :data:`memlog.matching.RERANK_PLACES`);
* **emissions**: ``beta`` times the place's re-rank score (mean patch pairs along its path);
* **transitions**: between a place at coordinate ``x`` for one frame and ``x'`` for the next, the
  query having moved ``dq``: the speed ``(x' - x) / dq`` may lie between 0 and ``vmax`` (the
  matcher's largest speed, plus one map spacing), and costs ``speed_cost`` per doubling or halving
  against the drives' pace; a place nearer than half a map spacing counts as half a spacing on
  (on a sparse map, the nearest map frame stays the same for several query frames). Any other
  move, a relocalisation, costs ``jump_cost``.

Offline, each frame's place probabilities are the posterior marginals (forward-backward over the
whole run); causal (``SequenceConfig.causal``), the filtered ones (the forward pass alone: the
decision for a frame uses only frames up to it). The places are ranked by that probability; the
margin, the confidence, is the best place's probability minus the best other place's (outside
``exclude``): 0 to 1, one scale for every row. Standing frames are one state (their stop's first
frame decides them, as in the matcher). Runs (recording gaps, topics, out-of-order frames) are
separate chains.

Measured on the Stromovka pairs (frame-aligned and the drive pair with stops) and chosen there:
``docs/defaults.md`` (``benchmarks/drive_pair.py``).
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

__all__ = ["place_probabilities", "SPEED_COST", "JUMP_COST", "BETA"]

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]

SPEED_COST = 0.5  # log-probability per doubling or halving of the speed against the pace
JUMP_COST = 6.0  # log-probability of a move the speed range does not allow (a relocalisation)
BETA = 0.75  # emission: log-probability per unit of re-rank score (mean patch pairs along the path; docs/defaults.md)


def _logsumexp(a: F64, axis: int) -> F64:
    m = np.max(a, axis=axis, keepdims=True)
    m = np.where(np.isfinite(m), m, 0.0)
    with np.errstate(divide="ignore"):
        out: F64 = np.log(np.sum(np.exp(a - m), axis=axis)) + np.squeeze(m, axis=axis)
    return out


def _transitions(x0: F64, x1: F64, dq: float, pace: float, spacing: float, vmax: float,
                 speed_cost: float, jump_cost: float) -> F64:
    """Log-probabilities ``[K0, K1]`` of moving from the places at ``x0`` to those at ``x1``."""
    d = x1[None, :] - x0[:, None]  # (dq > 0: standing frames are one state)
    with np.errstate(invalid="ignore", divide="ignore"):
        v = np.maximum(d, 0.5 * spacing) / (pace * dq)
        t = -speed_cost * np.abs(np.log2(v))
        t = np.where((d >= -1e-9) & (d <= vmax * dq + spacing), t, -np.inf)
    t = np.where(np.isnan(t), -np.inf, t)
    out: F64 = np.logaddexp(t, -jump_cost)
    return out


def _chain(emit: F64, x: F64, qc: F64, pace: float, spacing: float, vmax: float, causal: bool,
           speed_cost: float, jump_cost: float) -> F64:
    """Place probabilities ``[T, K]`` of one run's frames (posterior, or filtered when ``causal``)."""
    n = emit.shape[0]
    fwd = np.empty_like(emit)
    fwd[0] = emit[0] - _logsumexp(emit[:1], axis=1)
    trans = [np.zeros((0, 0))] + [_transitions(x[t - 1], x[t], float(qc[t] - qc[t - 1]), pace, spacing, vmax,
                                               speed_cost, jump_cost) for t in range(1, n)]
    for t in range(1, n):
        f = _logsumexp(fwd[t - 1][:, None] + trans[t], axis=0) + emit[t]
        fwd[t] = f - _logsumexp(f[None, :], axis=1)  # normalised each step (no underflow on long runs)
    post = fwd
    if not causal:
        bwd = np.zeros_like(emit)
        for t in range(n - 2, -1, -1):
            b = _logsumexp(trans[t + 1] + (emit[t + 1] + bwd[t + 1])[None, :], axis=1)
            bwd[t] = b - _logsumexp(b[None, :], axis=1)
        post = fwd + bwd
    post = post - _logsumexp(post, axis=1)[:, None]
    out: F64 = np.where(np.isfinite(emit), np.exp(post), 0.0)
    return out


def place_probabilities(score: F64, x: F64, qc: F64, run_lo: I64, run_hi: I64, *, pace: float, spacing: float,
                        vmax: float, causal: bool, speed_cost: float = SPEED_COST, jump_cost: float = JUMP_COST,
                        beta: float = BETA) -> tuple[F64, I64]:
    """Each query row's place probabilities along the drive (module doc) and the row that
    decides it (``owner``: a standing row's stop's first row, else itself).

    ``score`` ``[Q, K]``: the re-rank score of each row's candidate places (-inf: no place);
    ``x`` ``[Q, K]``: their map coordinates; ``qc``: the query rows' coordinates (drive order);
    ``run_lo`` / ``run_hi``: first and one-past-last row of each row's run; ``pace``: the speed
    of a query driven at the map's pace; ``spacing``: the map's median coordinate step;
    ``vmax``: the largest speed the matcher searched."""
    n_q = score.shape[0]
    emit = np.where(np.isfinite(score), beta * score, -np.inf)
    post = np.zeros(score.shape)
    owner = np.arange(n_q, dtype=np.int64)
    for a in np.unique(run_lo):
        rows = np.arange(a, int(run_hi[a]))
        # standing frames (the coordinate does not move) are their stop's first frame: one state
        first = rows[np.r_[True, np.diff(qc[rows]) > 0]]
        owner[rows] = first[np.searchsorted(first, rows, side="right") - 1]
        post[first] = _chain(emit[first], x[first], qc[first], pace, spacing, vmax, causal, speed_cost, jump_cost)
    return post, owner

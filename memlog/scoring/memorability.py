"""Memorability map and score MS of a frame (SPEC "Memorability map", reference conventions).

The 1135 x 1135 BGR frame is cut into a row-major 5 x 5 grid of 227 x 227 RGB crops (float32
/255, NCHW, no mean/std), each crop is scored by ResMem giving the 5 x 5 matrix M, M is
upsampled to 1135 x 1135 with ``cv2.resize(..., INTER_LINEAR)`` and MS = sum(map * S) / 1135^2.

Because the upsampling is linear in M, MS = sum_k w_k M_k with weights
w = A^T S A / 1135^2, where A (1135 x 5) is the interpolation matrix of ``cv2.resize`` (its
bilinear resize is separable: map = A M A^T). With a threshold MT, crops are scored in small
batches by decreasing weight and scoring stops as soon as the bounds (unscored crops at 0 or
at 1; ResMem outputs lie in 0..1) decide MS >= MT; crops of weight 0 (fully dynamic) are never
scored.

:class:`FastMemorability` (fast mode) puts an int8 surrogate in front: its crop scores, with
their measured error bounds, settle the frames whose MS is far from MT without the exact model.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from memlog.errors import ScoringError
from memlog.models.resmem import (
    FRAME,
    GRID,
    check_crops,
    check_static_map,
    crop_weights,
    crops_from_frame,
    resmem_onnx_path,
    run_crops,
)
from memlog.models.runtime import make_session

__all__ = [
    "memorability_matrix",
    "memorability_map",
    "memorability_score",
    "MemorabilityResult",
    "Memorability",
    "FastMemorability",
    "DECISION_MARGIN",
]

#: Margin by which bounds must clear MT before an early decision (float rounding of MS).
DECISION_MARGIN = 1e-6

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]


def memorability_matrix(session: Any, crops: F32, *, batch: int = 25) -> F32:
    """Score all 25 crops (in batches of ``batch``) and return the 5 x 5 matrix M (float32)."""
    check_crops(crops)
    if crops.shape[0] != GRID * GRID:
        raise ScoringError(f"need {GRID * GRID} crops, got {crops.shape[0]}")
    if batch < 1:
        raise ScoringError(f"batch must be >= 1, got {batch}")
    scores = np.concatenate([run_crops(session, crops[i:i + batch]) for i in range(0, len(crops), batch)])
    return scores.reshape(GRID, GRID)


def _check_prior(prior: tuple[npt.NDArray[Any], npt.NDArray[Any]] | None) -> tuple[F64, F64]:
    """Per-crop bounds (lo, hi) as two flat float64 arrays of 25 (default: 0 and 1)."""
    if prior is None:
        return np.zeros(GRID * GRID), np.ones(GRID * GRID)
    lo, hi = (np.asarray(p, dtype=np.float64).reshape(-1) for p in prior)
    if lo.shape != (GRID * GRID,) or hi.shape != (GRID * GRID,):
        raise ScoringError(f"prior bounds must hold {GRID * GRID} values each, got {lo.shape} and {hi.shape}")
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)) and np.all(lo <= hi)):
        raise ScoringError("prior bounds must be finite with lo <= hi")
    return lo, hi


def _check_matrix(m: npt.NDArray[Any]) -> None:
    if not isinstance(m, np.ndarray) or m.shape != (GRID, GRID):
        raise ScoringError(f"M must be a {GRID}x{GRID} array, got {getattr(m, 'shape', None)}")
    if not np.all(np.isfinite(m)):
        raise ScoringError("M has non-finite entries (unscored crops?)")


def memorability_map(m: npt.NDArray[Any]) -> F64:
    """Bilinear upsampling of M to 1135 x 1135 (``cv2.resize``, INTER_LINEAR, float64)."""
    _check_matrix(m)
    return np.asarray(
        cv2.resize(m.astype(np.float64), (FRAME, FRAME), interpolation=cv2.INTER_LINEAR), dtype=np.float64
    )


def memorability_score(m: npt.NDArray[Any], s: npt.NDArray[Any] | None = None) -> float:
    """MS = sum(map * S) / 1135^2 (S = all static when None)."""
    up = memorability_map(m)
    if s is None:
        return float(up.sum() / (FRAME * FRAME))
    return float((up * check_static_map(s)).sum() / (FRAME * FRAME))


@dataclass(frozen=True)
class MemorabilityResult:
    """Outcome of scoring one frame.

    ``m``: 5 x 5 scores, NaN for crops that were not scored. ``exact``: every crop of non-zero
    weight was scored, so ``ms`` is MS and ``ms_low == ms == ms_high``; otherwise MS lies in
    [``ms_low``, ``ms_high``] and ``ms`` is None, or (fast mode) the surrogate's estimate.
    ``passed``: MS >= threshold (None without one). ``n_scored``: crops run through the exact
    model; ``n_surrogate``: crops run through the fast surrogate (fast mode only).
    """

    m: F32
    ms: float | None
    ms_low: float
    ms_high: float
    exact: bool
    n_scored: int
    passed: bool | None
    n_surrogate: int = 0


class Memorability:
    """ResMem on onnxruntime (CPU) scoring 1135 x 1135 frames."""

    def __init__(
        self, onnx_path: Path | None = None, *, threads: int | None = None, batch: int = 5, device: str = "auto"
    ) -> None:
        """Open the prepared ResMem ONNX model (default: :func:`resmem_onnx_path`).

        ``threads``: intra-op threads (None: onnxruntime's default, all cores). ``batch``:
        default number of crops per inference call. ``device``: where it runs
        (:func:`memlog.models.runtime.choose_providers`).
        """
        if batch < 1:
            raise ScoringError(f"batch must be >= 1, got {batch}")
        self.path = resmem_onnx_path() if onnx_path is None else Path(onnx_path)
        self.batch = batch
        self.session = make_session(self.path, threads=threads, device=device, what="the ResMem model")

    def score_crops(self, crops: F32) -> F32:
        """Scores (N,) of crops [N,3,227,227] float32, in one inference call."""
        check_crops(crops)
        return run_crops(self.session, crops)

    def __call__(
        self,
        bgr1135: npt.NDArray[Any],
        static_map: npt.NDArray[Any] | None = None,
        threshold: float | None = None,
        batch: int | None = None,
        *,
        prior: tuple[npt.NDArray[Any], npt.NDArray[Any]] | None = None,
        crops: F32 | None = None,
        known: npt.NDArray[Any] | None = None,
    ) -> MemorabilityResult:
        """Score a frame; with ``threshold`` stop as soon as MS >= threshold is decided.

        ``prior``: per-crop bounds (lo, hi), 25 values each, known to contain the crop scores
        (default 0 and 1, the range of ResMem's sigmoid). Crops are scored in order of
        decreasing weight x (hi - lo), so the bound on MS shrinks fastest. ``crops``: the
        frame's :func:`crops_from_frame`, when the caller already has them. ``known``: crop
        scores from an earlier call (5 x 5, NaN where not scored), which are not run again, so a
        frame stopped early can be finished. ``n_scored`` of the result counts known crops too.
        """
        bs = self.batch if batch is None else batch
        if bs < 1:
            raise ScoringError(f"batch must be >= 1, got {bs}")
        if threshold is not None and not np.isfinite(threshold):
            raise ScoringError(f"threshold must be finite, got {threshold}")
        if crops is None:
            crops = crops_from_frame(bgr1135)
        else:
            check_crops(crops)
        w = crop_weights(static_map).reshape(-1)
        lo, hi = _check_prior(prior)
        m = np.full(GRID * GRID, np.nan, dtype=np.float32)
        if known is not None:
            kn = np.asarray(known, dtype=np.float32).reshape(-1)
            if kn.shape != (GRID * GRID,):
                raise ScoringError(f"known crop scores must hold {GRID * GRID} values, got {kn.shape}")
            m[:] = kn
        have = ~np.isnan(m)
        order = [int(k) for k in np.argsort(-(w * (hi - lo)), kind="stable") if w[k] > 0 and not have[k]]
        done = float(np.dot(w[have], m[have].astype(np.float64)))  # sum of w_k M_k over scored crops
        left_lo = float(np.dot(w[order], lo[order]))  # bounds on the unscored crops' share
        left_hi = float(np.dot(w[order], hi[order]))
        n = int(have.sum())
        start = n
        while n - start < len(order):
            if threshold is not None:
                if done + left_lo >= threshold + DECISION_MARGIN:
                    return self._result(m, done + left_lo, done + left_hi, n, True)
                if done + left_hi < threshold - DECISION_MARGIN:
                    return self._result(m, done + left_lo, done + left_hi, n, False)
            idx = order[n - start:n - start + bs]
            m[idx] = run_crops(self.session, crops[idx])
            done += float(np.dot(w[idx], m[idx].astype(np.float64)))
            left_lo -= float(np.dot(w[idx], lo[idx]))
            left_hi -= float(np.dot(w[idx], hi[idx]))
            n += len(idx)
        full = np.where(np.isnan(m), 0.0, m).reshape(GRID, GRID)
        ms = memorability_score(full, static_map)
        passed = None if threshold is None else ms >= threshold
        return MemorabilityResult(m.reshape(GRID, GRID), ms, ms, ms, True, n, passed)

    @staticmethod
    def _result(m: F32, low: float, high: float, n: int, passed: bool) -> MemorabilityResult:
        return MemorabilityResult(m.reshape(GRID, GRID), None, low, high, False, n, passed)


class FastMemorability:
    """Fast mode: an int8 surrogate of ResMem, refined with the exact model only where needed.

    Every crop of non-zero weight is scored by the surrogate (one batch, its mean error
    ``bias`` subtracted), giving an estimate of MS. Two error bounds, both measured when the
    surrogate was built (see :mod:`memlog.models.quantize`), decide what happens next:

    * ``delta``, the frame-level bound on |MS(surrogate) - MS|: when the estimate is further
      than ``delta`` from the threshold, the surrogate's decision stands (no exact crop);
    * ``epsilon``, the per-crop bound: otherwise the exact model scores crops (the most
      uncertain first) with every unscored crop known to lie within ``epsilon`` of its
      surrogate score, until ``MS >= threshold`` is decided — as exact mode would decide it.

    Without a threshold the surrogate's MS is the result (``exact=False``, bounds +-``delta``).
    With ``refine=False`` the surrogate's estimate decides every frame alone (the exact model is
    never run: fastest, but decisions within ``delta`` of the threshold may differ).
    """

    def __init__(self, surrogate: Path | Memorability, exact: Memorability, epsilon: float,
                 delta: float | None = None, bias: float = 0.0, *, refine: bool = True,
                 threads: int | None = None, device: str = "auto",
                 frame_fit: dict[str, float] | None = None) -> None:
        """``surrogate``: the int8 ONNX file (or an open :class:`Memorability`); ``exact``: the
        fp32 model; ``epsilon``/``delta``: the surrogate's per-crop and per-frame error
        bounds (``delta`` defaults to ``epsilon``, which bounds the frame error too) once
        ``bias`` (its mean error) is subtracted from its crop scores."""
        delta = epsilon if delta is None else delta
        for name, v in (("epsilon", epsilon), ("delta", delta)):
            if not (np.isfinite(v) and 0.0 <= v <= 1.0):
                raise ScoringError(f"{name} must be within [0, 1], got {v}")
        self.surrogate = (surrogate if isinstance(surrogate, Memorability)
                          else Memorability(surrogate, threads=threads, batch=GRID * GRID, device=device))
        self.exact = exact
        self.epsilon = float(epsilon)
        self.delta = float(delta)
        self.bias = float(bias)
        self.refine = bool(refine)
        self.batch = exact.batch
        self.frame_fit = frame_fit

    def __call__(
        self,
        bgr1135: npt.NDArray[Any],
        static_map: npt.NDArray[Any] | None = None,
        threshold: float | None = None,
        batch: int | None = None,
    ) -> MemorabilityResult:
        """Score a frame like :meth:`Memorability.__call__` (same result fields)."""
        if threshold is not None and not np.isfinite(threshold):
            raise ScoringError(f"threshold must be finite, got {threshold}")
        if threshold is not None and self.frame_fit is not None and (static_map is None or bool(np.all(static_map))):
            # tier 0: the whole frame through the int8 model, one inference; decides frames whose
            # estimate is further than its measured error from the threshold
            from memlog.models.quantize import frame_crop

            f = self.frame_fit
            est0 = float(np.clip(f["a"] * float(self.surrogate.score_crops(frame_crop(bgr1135))[0]) + f["b"], 0.0, 1.0))
            low0, high0 = max(0.0, est0 - f["delta"]), min(1.0, est0 + f["delta"])
            if low0 >= threshold + DECISION_MARGIN or high0 < threshold - DECISION_MARGIN:
                m0 = np.full((GRID, GRID), np.nan, dtype=np.float32)
                return MemorabilityResult(m0, est0, low0, high0, False, 0, low0 >= threshold + DECISION_MARGIN, 1)
        crops = crops_from_frame(bgr1135)
        w = crop_weights(static_map).reshape(-1)
        todo = np.flatnonzero(w > 0)
        est = np.full(GRID * GRID, np.nan, dtype=np.float32)
        if todo.size:
            est[todo] = np.clip(self.surrogate.score_crops(crops[todo]) - np.float32(self.bias), 0.0, 1.0)
        filled = np.where(np.isnan(est), 0.0, est).astype(np.float64)
        ms_est = float(np.dot(w, filled))
        ss = float(w.sum())
        low, high = max(0.0, ms_est - self.delta), min(ss, ms_est + self.delta)
        n_sur = int(todo.size)
        if threshold is None or not self.refine:
            passed = None if threshold is None else ms_est >= threshold
            return MemorabilityResult(est.reshape(GRID, GRID), ms_est, low, high, False, 0, passed, n_sur)
        if low >= threshold + DECISION_MARGIN or high < threshold - DECISION_MARGIN:
            passed = low >= threshold + DECISION_MARGIN
            return MemorabilityResult(est.reshape(GRID, GRID), ms_est, low, high, False, 0, passed, n_sur)
        lo = np.clip(filled - self.epsilon, 0.0, 1.0)
        hi = np.clip(filled + self.epsilon, 0.0, 1.0)
        r = self.exact(bgr1135, static_map, threshold, batch, prior=(lo, hi), crops=crops)
        if r.exact:
            return replace(r, n_surrogate=n_sur)
        m = np.where(np.isnan(r.m.reshape(-1)), est, r.m.reshape(-1))
        ms = float(np.clip(np.dot(w, np.where(np.isnan(m), 0.0, m)), r.ms_low, r.ms_high))
        return replace(r, m=m.reshape(GRID, GRID).astype(np.float32), ms=ms, n_surrogate=n_sur)

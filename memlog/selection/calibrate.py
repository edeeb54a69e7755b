"""Calibrate the paper's three thresholds to keep about a given fraction of the frames.

In one sentence: *each threshold is the same quantile q of its criterion's scores, with q
searched (bisection) until the joint pass rate is F.*

Details. For q in [0, 1], ``mt(q) = np.quantile(finite MS, q)`` (numpy's default
"linear" method), likewise ``st(q)`` and ``et(q)``; the joint pass rate ``p(q)`` is the
fraction of *all* N frames with ``ms >= mt and ss >= st and es >= et`` (NaN fails). p is
non-increasing in q, so bisection finds the q where it crosses F; of the two bracketing
values the one whose rate is nearer F is returned (a tie keeps more frames). Because the
test is ``>=``, a criterion that is tied everywhere (SS == 1.0 on every frame) gives the
threshold 1.0 and keeps every frame. p is a step function: several frames can cross at the
same q (ties, or one frame per criterion at the same rank), so the achieved rate is the
nearest achievable one, and F outside [p(1), p(0)] is unreachable; both cases are
reported in ``note``.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from memlog.errors import SelectionError
from memlog.selection._checks import fraction, positive_int
from memlog.selection.paper import PaperConfig, select_paper
from memlog.selection.table import ScoreTable, Selection

__all__ = ["CalibrateConfig", "Calibration", "calibrate", "select_calibrated"]


@dataclass(frozen=True)
class CalibrateConfig:
    """Target keep fraction F in (0, 1] and the bisection's iteration cap."""

    keep_fraction: float = 0.1
    max_iter: int = 64

    def __post_init__(self) -> None:
        fraction("keep_fraction", self.keep_fraction)
        positive_int("max_iter", self.max_iter)

    def to_dict(self) -> dict[str, Any]:
        """Settings as a plain dict."""
        return asdict(self)


@dataclass(frozen=True)
class Calibration:
    """Result of :func:`calibrate`: the quantile ``q``, thresholds and achieved fraction."""

    keep_fraction: float
    q: float
    mt: float
    st: float
    et: float
    achieved: float
    n_kept: int
    n_frames: int
    reachable: bool
    note: str | None = None

    @property
    def thresholds(self) -> dict[str, float]:
        """``{"mt": ..., "st": ..., "et": ...}``."""
        return {"mt": self.mt, "st": self.st, "et": self.et}

    def paper_config(self) -> PaperConfig:
        """The thresholds as a :class:`PaperConfig` (to apply them to another table)."""
        return PaperConfig(mt=self.mt, st=self.st, et=self.et)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict."""
        return asdict(self)


def _finite_sorted(x: NDArray[np.float64]) -> NDArray[np.float64]:
    return np.sort(x[np.isfinite(x)])


def calibrate(
    table: ScoreTable, keep_fraction: float, *, max_iter: int = 64
) -> Calibration:
    """Find the common quantile q whose thresholds keep about ``keep_fraction`` of the frames.

    Raises SelectionError when the table is empty or a criterion has no finite score
    (no threshold can be derived); an unreachable F gives the nearest achievable rate
    with a ``note``.
    """
    f = fraction("keep_fraction", keep_fraction)
    iters = positive_int("max_iter", max_iter)
    n = table.n
    if n == 0:
        raise SelectionError("cannot calibrate thresholds on an empty score table")
    cols = (table.ms, table.ss, table.es)
    sorted_cols = [_finite_sorted(c) for c in cols]
    for name, v in zip(("memorability", "staticity", "entropy"), sorted_cols):
        if v.size == 0:
            raise SelectionError(f"cannot calibrate thresholds: no frame has a finite {name} score")

    def thresholds(q: float) -> tuple[float, float, float]:
        mt, st, et = (float(np.quantile(v, q)) for v in sorted_cols)
        return mt, st, et

    def count(q: float) -> int:
        mt, st, et = thresholds(q)
        with np.errstate(invalid="ignore"):
            ok = (table.ms >= mt) & (table.ss >= st) & (table.es >= et)
        return int(np.count_nonzero(ok))

    target = f * n
    c_lo, c_hi = count(0.0), count(1.0)
    note: str | None = None
    reachable = True
    if c_lo <= target:
        q, c = 0.0, c_lo
        if c_lo < target:
            reachable = False
            note = (
                f"keep fraction {f:g} unreachable: at most {c_lo}/{n} frames "
                "({:.4g}) have all three scores; thresholds are the minima".format(c_lo / n)
            )
    elif c_hi >= target:
        q, c = 1.0, c_hi
        if c_hi > target:
            reachable = False
            note = (
                f"keep fraction {f:g} unreachable: {c_hi}/{n} frames ({c_hi / n:.4g}) "
                "tie at the maxima of all three scores; thresholds are the maxima"
            )
    else:
        lo, hi = 0.0, 1.0  # invariant: count(lo) > target > count(hi) ... or == at lo
        for _ in range(iters):
            mid = 0.5 * (lo + hi)
            if mid <= lo or mid >= hi:
                break
            cm = count(mid)
            if cm >= target:
                lo, c_lo = mid, cm
                if cm == target:
                    break
            else:
                hi, c_hi = mid, cm
        if abs(c_lo - target) <= abs(c_hi - target):
            q, c = lo, c_lo
        else:
            q, c = hi, c_hi
    if note is None and abs(c - target) > 1.0:
        note = (
            f"keep fraction {f:g} not hit exactly: nearest achievable is {c}/{n} "
            f"({c / n:.4g}); several frames cross the thresholds at the same quantile (ties)"
        )
    mt, st, et = thresholds(q)
    return Calibration(
        keep_fraction=f,
        q=q,
        mt=mt,
        st=st,
        et=et,
        achieved=c / n,
        n_kept=c,
        n_frames=n,
        reachable=reachable,
        note=note,
    )


def select_calibrated(table: ScoreTable, config: CalibrateConfig | None = None) -> Selection:
    """Calibrate thresholds on ``table`` (see :func:`calibrate`) and apply the paper rule."""
    cfg = config if config is not None else CalibrateConfig()
    cal = calibrate(table, cfg.keep_fraction, max_iter=cfg.max_iter)
    sel = select_paper(table, cal.paper_config())
    sel.mode = "calibrated"
    sel.info["calibration"] = cal.to_dict()
    return sel

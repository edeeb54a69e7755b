"""The paper's tri-threshold rule: keep a frame iff MS >= MT and SS >= ST and ES >= ET."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from memlog.selection._checks import finite_number
from memlog.selection.table import CRITERIA, ScoreTable, Selection

__all__ = ["PaperConfig", "select_paper", "first_failing"]


@dataclass(frozen=True)
class PaperConfig:
    """Thresholds of the paper's rule (defaults MT 0.5, ST 0.6, ET 0.4; SPEC.md)."""

    mt: float = 0.5
    st: float = 0.6
    et: float = 0.4

    def __post_init__(self) -> None:
        for name in ("mt", "st", "et"):
            finite_number(f"paper threshold {name}", getattr(self, name))

    def to_dict(self) -> dict[str, Any]:
        """Settings as a plain dict."""
        return asdict(self)


def first_failing(table: ScoreTable, mt: float, st: float, et: float) -> NDArray[np.int8]:
    """Per row, the first criterion failed in the staged order, as a code.

    0 = passes all three, 1 = staticity (SS < st), 2 = entropy (ES < et),
    3 = memorability (MS < mt); a NaN score fails its criterion. Code ``c > 0`` names
    ``CRITERIA[c - 1]``.
    """
    with np.errstate(invalid="ignore"):
        fail_s = ~(table.ss >= st)
        fail_e = ~(table.es >= et)
        fail_m = ~(table.ms >= mt)
    code = np.where(fail_s, 1, np.where(fail_e, 2, np.where(fail_m, 3, 0)))
    return code.astype(np.int8)


def codes_to_reasons(code: NDArray[np.int8]) -> list[str | None]:
    """Map codes from :func:`first_failing` to reason strings (None for 0)."""
    names: tuple[str | None, ...] = (None,) + CRITERIA
    return [names[c] for c in code.tolist()]


def select_paper(table: ScoreTable, config: PaperConfig | None = None) -> Selection:
    """Apply the paper's rule; each dropped frame's reason is its first failing criterion
    in the order staticity -> entropy -> memorability."""
    cfg = config if config is not None else PaperConfig()
    code = first_failing(table, cfg.mt, cfg.st, cfg.et)
    keep = code == 0
    info: dict[str, Any] = {
        "rule": "keep iff ms >= mt and ss >= st and es >= et (NaN fails)",
        "n_nan": {
            "memorability": int(np.count_nonzero(np.isnan(table.ms))),
            "staticity": int(np.count_nonzero(np.isnan(table.ss))),
            "entropy": int(np.count_nonzero(np.isnan(table.es))),
        },
    }
    if table.n and not np.any(keep):
        info["note"] = "empty map: no frame passes all three thresholds"
    return Selection(
        mode="paper",
        index=table.index,
        keep=keep,
        reason=codes_to_reasons(code),
        thresholds={"mt": float(cfg.mt), "st": float(cfg.st), "et": float(cfg.et)},
        info=info,
    )

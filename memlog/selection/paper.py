"""The paper's tri-threshold rule: keep a frame iff MS >= MT and SS >= ST and ES >= ET.

With ``dt`` set, a fourth criterion beyond the paper: the frame's distinctiveness DS
(:mod:`memlog.selection.distinctiveness`, the table's ``ds`` column) must be >= DT too.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from memlog.errors import ConfigError
from memlog.selection._checks import finite_number
from memlog.selection.table import CRITERIA, DISTINCT, ScoreTable, Selection

__all__ = ["PaperConfig", "select_paper", "first_failing"]


@dataclass(frozen=True)
class PaperConfig:
    """Thresholds of the paper's rule (defaults MT 0.5, ST 0.6, ET 0.4; SPEC.md); ``dt``: the
    distinctiveness threshold (None: not used)."""

    mt: float = 0.5
    st: float = 0.6
    et: float = 0.4
    dt: float | None = None

    def __post_init__(self) -> None:
        for name in ("mt", "st", "et"):
            finite_number(f"paper threshold {name}", getattr(self, name))
        if self.dt is not None:
            finite_number("paper threshold dt", self.dt)

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
    """Map codes from :func:`first_failing` to reason strings (None for 0; 4 = distinctiveness)."""
    names: tuple[str | None, ...] = (None,) + CRITERIA + (DISTINCT,)
    return [names[c] for c in code.tolist()]


def select_paper(table: ScoreTable, config: PaperConfig | None = None) -> Selection:
    """Apply the paper's rule; each dropped frame's reason is its first failing criterion
    in the order staticity -> entropy -> memorability."""
    cfg = config if config is not None else PaperConfig()
    code = first_failing(table, cfg.mt, cfg.st, cfg.et)
    rule = "keep iff ms >= mt and ss >= st and es >= et (NaN fails)"
    if cfg.dt is not None:
        if table.ds is None:
            raise ConfigError("the distinctiveness threshold dt needs the table's distinctiveness (ds) column")
        with np.errstate(invalid="ignore"):
            code = np.where((code == 0) & ~(table.ds >= cfg.dt), 4, code).astype(np.int8)
        rule = "keep iff ms >= mt and ss >= st and es >= et and ds >= dt (NaN fails)"
    keep = code == 0
    info: dict[str, Any] = {
        "rule": rule,
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
        thresholds={"mt": float(cfg.mt), "st": float(cfg.st), "et": float(cfg.et),
                    **({} if cfg.dt is None else {"dt": float(cfg.dt)})},
        info=info,
    )

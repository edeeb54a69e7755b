"""Small self-contained SVG charts for the HTML report (:mod:`memlog.outputs.report`): line charts,
histograms, the drive's score timeline and the spread of maps of one size."""

from __future__ import annotations

import html
from collections.abc import Callable, Sequence

import numpy as np

from memlog.selection import ScoreTable, Selection

__all__ = ["svg_lines", "svg_histogram", "svg_timeline", "svg_spread"]

_COLORS = ["#1f77b4", "#d62728", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b"]


def _scale(a0: float, a1: float, b0: float, b1: float) -> Callable[[float], float]:
    """The linear map taking a0..a1 to b0..b1 (data to pixels)."""
    def f(v: float) -> float:
        return b0 + (float(v) - a0) / (a1 - a0) * (b1 - b0)

    return f


def svg_lines(series: Sequence[tuple[str, Sequence[float], Sequence[float]]], *, title: str, xlabel: str,
              ylabel: str, w: int = 420, h: int = 280, xlim: tuple[float, float] | None = None,
              ylim: tuple[float, float] | None = None, marks: Sequence[float] = ()) -> str:
    """A small line chart; ``series`` = (label, xs, ys)."""
    pad_l, pad_b, pad_t, pad_r = 48, 36, 24, 10
    xs_all = [x for _, xs, _ in series for x in xs] or [0.0, 1.0]
    ys_all = [y for _, _, ys in series for y in ys if np.isfinite(y)] or [0.0, 1.0]
    x0, x1 = xlim or (min(xs_all), max(xs_all))
    y0, y1 = ylim or (min(ys_all), max(ys_all))
    x1 = x1 if x1 > x0 else x0 + 1
    y1 = y1 if y1 > y0 else y0 + 1
    sx = _scale(x0, x1, pad_l, w - pad_r)
    sy = _scale(y0, y1, h - pad_b, pad_t)
    parts = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{w}" height="{h}" font-size="11" font-family="sans-serif">',
             f'<text x="{w / 2}" y="14" text-anchor="middle" font-weight="bold">{html.escape(title)}</text>',
             f'<line x1="{pad_l}" y1="{h - pad_b}" x2="{w - pad_r}" y2="{h - pad_b}" stroke="#333"/>',
             f'<line x1="{pad_l}" y1="{pad_t}" x2="{pad_l}" y2="{h - pad_b}" stroke="#333"/>',
             f'<text x="{w / 2}" y="{h - 4}" text-anchor="middle">{html.escape(xlabel)}</text>',
             f'<text x="12" y="{h / 2}" text-anchor="middle" transform="rotate(-90 12 {h / 2})">{html.escape(ylabel)}</text>']
    for t in np.linspace(x0, x1, 5):
        parts.append(f'<text x="{sx(t):.1f}" y="{h - pad_b + 13}" text-anchor="middle">{t:.3g}</text>')
    for t in np.linspace(y0, y1, 5):
        parts.append(f'<text x="{pad_l - 4}" y="{sy(t) + 4:.1f}" text-anchor="end">{t:.3g}</text>')
    for m in marks:
        parts.append(f'<line x1="{sx(m):.1f}" y1="{pad_t}" x2="{sx(m):.1f}" y2="{h - pad_b}" stroke="#bbb" stroke-dasharray="3,3"/>')
    for i, (label, xs, ys) in enumerate(series):
        pts = " ".join(f"{sx(x):.1f},{sy(y):.1f}" for x, y in zip(xs, ys) if np.isfinite(y))
        c = _COLORS[i % len(_COLORS)]
        parts.append(f'<polyline fill="none" stroke="{c}" stroke-width="1.5" points="{pts}"/>')
        parts.append(f'<text x="{w - pad_r - 4}" y="{pad_t + 12 + 13 * i}" text-anchor="end" fill="{c}">{html.escape(label)}</text>')
    parts.append("</svg>")
    return "".join(parts)


def svg_histogram(values: np.ndarray, *, title: str, bins: int = 20, w: int = 280, h: int = 180,
                  threshold: float | None = None, rng: tuple[float, float] = (0.0, 1.0)) -> str:
    v = values[np.isfinite(values)]
    counts, edges = np.histogram(v, bins=bins, range=rng)
    top = max(int(counts.max()) if counts.size else 1, 1)
    pad_b, pad_t = 24, 20
    bw = (w - 20) / bins
    parts = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{w}" height="{h}" font-size="11" font-family="sans-serif">',
             f'<text x="{w / 2}" y="13" text-anchor="middle" font-weight="bold">{html.escape(title)} (n={len(v)})</text>']
    for i, c in enumerate(counts):
        bh = c / top * (h - pad_b - pad_t)
        parts.append(f'<rect x="{10 + i * bw:.1f}" y="{h - pad_b - bh:.1f}" width="{bw - 1:.1f}" height="{bh:.1f}" fill="#1f77b4"/>')
    if threshold is not None:
        x = 10 + (threshold - rng[0]) / (rng[1] - rng[0]) * (w - 20)
        parts.append(f'<line x1="{x:.1f}" y1="{pad_t}" x2="{x:.1f}" y2="{h - pad_b}" stroke="#d62728" stroke-width="2"/>')
    parts.append(f'<text x="10" y="{h - 6}">{rng[0]:g}</text><text x="{w - 10}" y="{h - 6}" text-anchor="end">{rng[1]:g}</text>')
    parts.append("</svg>")
    return "".join(parts)


def svg_timeline(table: ScoreTable, sel: Selection, w: int = 900, h: int = 240) -> str:
    """Scores over frame index; kept frames as ticks; gaps shaded."""
    x = [float(v) for v in table.index]
    series = [("MS", x, list(table.ms)), ("SS", x, list(table.ss)), ("ES", x, list(table.es))]
    svg = svg_lines(series, title="drive timeline: scores per frame (ticks: kept frames, shaded: gaps)",
                    xlabel="frame index", ylabel="score", w=w, h=h, ylim=(0.0, 1.0))
    pad_l, pad_r, pad_b, pad_t = 48, 10, 36, 24
    x0, x1 = (min(x), max(x)) if x else (0.0, 1.0)
    x1 = x1 if x1 > x0 else x0 + 1
    sx = _scale(x0, x1, pad_l, w - pad_r)
    extra = []
    for g in sel.gaps:
        extra.append(f'<rect x="{sx(g.start_index):.1f}" y="{pad_t}" width="{max(1.0, sx(g.end_index) - sx(g.start_index)):.1f}" '
                     f'height="{h - pad_b - pad_t}" fill="#d62728" opacity="0.15"/>')
    for i in table.index[sel.keep]:
        extra.append(f'<line x1="{sx(i):.1f}" y1="{h - pad_b}" x2="{sx(i):.1f}" y2="{h - pad_b - 8}" stroke="#000"/>')
    return svg.replace("</svg>", "".join(extra) + "</svg>")


def svg_spread(rows: Sequence[tuple[str, Sequence[float]]], marks: Sequence[tuple[str, float, str]], *,
               title: str, w: int = 700) -> str:
    """Where maps of one size fall: each row a label and its maps' values (dots), each mark a
    labelled value drawn across every row (the memorable map, the full map) in its colour."""
    vals = [v for _, vs in rows for v in vs if np.isfinite(v)] + [v for _, v, _ in marks if np.isfinite(v)]
    lo, hi = (min(vals), max(vals)) if vals else (0.0, 1.0)
    lo, hi = max(0.0, lo - 0.02), min(1.0, hi + 0.02)
    if hi <= lo:
        lo, hi = max(0.0, lo - 0.05), min(1.0, hi + 0.05)
    left, right, row_h, top = 170, 20, 26, 28
    h = top + row_h * len(rows) + 34 + 12 * len(marks)
    x = _scale(lo, hi, left, w - right)
    parts = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{w}" height="{h}" font-size="12">',
             f'<text x="{left}" y="16" font-weight="bold">{html.escape(title)}</text>']
    for j, (label, vs) in enumerate(rows):
        y = top + row_h * j + row_h / 2
        parts.append(f'<text x="{left - 8}" y="{y + 4:.1f}" text-anchor="end">{html.escape(label)}</text>'
                     f'<line x1="{left}" x2="{w - right}" y1="{y:.1f}" y2="{y:.1f}" stroke="#eee"/>')
        parts += [f'<circle cx="{x(v):.1f}" cy="{y:.1f}" r="4" fill="#1f77b4" fill-opacity="0.6"/>'
                  for v in vs if np.isfinite(v)]
    bottom = top + row_h * len(rows)
    for k, (label, v, colour) in enumerate(marks):
        if np.isfinite(v):
            parts.append(f'<line x1="{x(v):.1f}" x2="{x(v):.1f}" y1="{top}" y2="{bottom}" stroke="{colour}" '
                         f'stroke-width="2"/><text x="{x(v) + 3:.1f}" y="{bottom + 14 + 12 * k}" fill="{colour}">'
                         f'{html.escape(label)} {v:.3f}</text>')
    for t in np.linspace(lo, hi, 5):
        parts.append(f'<text x="{x(t):.1f}" y="{h - 2}" text-anchor="middle" fill="#666">{t:.2f}</text>')
    parts.append("</svg>")
    return "".join(parts)

"""The HTML report of ``memlog evaluate``: one self-contained file, plots as inline SVG.

PR curves of every map variant, the threshold sweeps, score histograms, a timeline of the
drive (scores over frame index, kept frames and gaps marked), and galleries of selected and
discarded frames with their scores.
"""

from __future__ import annotations

import base64
import html
import json
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from memlog.descriptors.table import DescriptorTable
from memlog.errors import ImageDecodeError
from memlog.evaluation.metrics import ProtocolResult
from memlog.io.atomic import write_bytes_atomic
from memlog.io.open import open_log
from memlog.selection import ScoreTable, Selection

__all__ = ["write_report", "svg_lines", "svg_histogram"]

_COLORS = ["#1f77b4", "#d62728", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b"]


def _scale(a0: float, a1: float, b0: float, b1: float) -> Callable[[float], float]:
    """The linear map taking a0..a1 to b0..b1 (data to pixels)."""
    def f(v: float) -> float:
        return b0 + (float(v) - a0) / (a1 - a0) * (b1 - b0)

    return f


def _fmt(v: float) -> str:
    return "-" if not np.isfinite(v) else f"{v:.3f}"


def _spread(rows: list[int], n: int = 24) -> list[int]:
    """Up to n rows spread evenly over ``rows``."""
    if not rows:
        return []
    return [rows[i] for i in np.linspace(0, len(rows) - 1, min(n, len(rows))).astype(int)]


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


def _thumbs(log: str, topic: str, indices: set[int], width: int = 160) -> dict[int, str]:
    out: dict[int, str] = {}
    if not indices:
        return out
    with open_log(log) as reader:
        reader.quiet_warnings()  # the evaluation already reported damage
        for f in reader.frames([topic], indices={topic: indices}):
            if f.index in indices:
                try:
                    img = f.decode_bgr()
                except ImageDecodeError:
                    continue
                h = max(1, int(img.shape[0] * width / img.shape[1]))
                interp = cv2.INTER_AREA if img.shape[1] > width else cv2.INTER_NEAREST
                small = cv2.resize(img, (width, h), interpolation=interp)
                jpg = bytes(cv2.imencode(".jpg", small, [cv2.IMWRITE_JPEG_QUALITY, 80])[1])
                out[f.index] = base64.b64encode(jpg).decode()
            if len(out) == len(indices):
                break
    return out


def _gallery(title: str, rows: list[int], table: ScoreTable, sel: Selection, thumbs: dict[int, str]) -> str:
    cells = []
    for r in rows:
        i = int(table.index[r])
        if i not in thumbs:
            continue
        why = "kept" if sel.keep[r] else f"dropped: {sel.reason[r]}"
        f = _fmt
        cells.append(f'<figure><img src="data:image/jpeg;base64,{thumbs[i]}"/><figcaption>#{i} {why}<br>'
                     f"MS {f(table.ms[r])} SS {f(table.ss[r])} ES {f(table.es[r])}</figcaption></figure>")
    return f"<h3>{html.escape(title)}</h3><div class='gallery'>{''.join(cells)}</div>"


def _table_html(results: dict[str, Any]) -> str:
    head = ("<tr><th>map</th><th>frames</th><th>coverage</th><th>AUC</th><th>R@1</th><th>R@5</th><th>R@10</th>"
            "<th>P@100%R</th><th>ms/query</th><th>paper AUC</th><th>paper R@1</th>"
            "<th>single-frame AUC</th><th>single-frame R@1</th><th>single-frame paper R@1</th></tr>")
    rows = []
    labels = {"memorable_exact": "memorable (exact selection)", "uniform": "every k-th frame",
              "uniform_distance": "uniform by distance"}
    for name in ("full", "memorable", "memorable_exact", "uniform", "uniform_distance", "random"):
        if name not in results:
            continue
        r = results[name]
        std = r.get("std", {})
        def f(key: str, d: dict[str, Any] = r, s: dict[str, Any] = std) -> str:
            v = d.get(key)
            if v is None:
                return "-"
            return f"{v:.3f}" + (f" ± {s[key]:.3f}" if key in s else "")
        pp = r["paper_protocol"]
        sf = r.get("single_frame") or {}
        sfp = sf.get("paper_protocol") or {}
        rows.append(f"<tr><td>{labels.get(name, name)}</td><td>{r['frames']}</td><td>{f('coverage')}</td>"
                    f"<td>{f('auc')}</td><td>{f('recall@1')}</td><td>{f('recall@5')}</td><td>{f('recall@10')}</td>"
                    f"<td>{f('precision@100%recall')}</td><td>{1e3 * r['match_seconds_per_query']:.3f}</td>"
                    f"<td>{f('auc', pp, pp.get('std', {}))}</td><td>{f('recall@1', pp, pp.get('std', {}))}</td>"
                    f"<td>{f('auc', sf, sf.get('std', {}))}</td><td>{f('recall@1', sf, sf.get('std', {}))}</td>"
                    f"<td>{f('recall@1', sfp, sfp.get('std', {}))}</td></tr>")
    return f"<table>{head}{''.join(rows)}</table>"


def write_report(path: Path, results: dict[str, Any], table: ScoreTable, sel: Selection,
                 per_variant: dict[str, tuple[ProtocolResult, ProtocolResult]], ref_t: DescriptorTable,
                 reference: str, topic: str) -> Path:
    """Write the self-contained HTML report (atomically)."""
    th = sel.thresholds or {}
    pr = [svg_lines([(name, list(mo.curve.recall), list(mo.curve.precision)) for name, (mo, _) in per_variant.items()],
                    title="PR curves (map-only)", xlabel="recall", ylabel="precision", xlim=(0, 1), ylim=(0, 1)),
          svg_lines([(name, list(po.curve.recall), list(po.curve.precision)) for name, (_, po) in per_variant.items()],
                    title="PR curves (paper protocol)", xlabel="recall", ylabel="precision", xlim=(0, 1), ylim=(0, 1))]
    sw = results["sweeps"]
    sweeps = [svg_lines([(n.upper(), [r["threshold"] for r in sw[n]], [r["frames"] for r in sw[n]]) for n in sw],
                        title="sweep: selected frames", xlabel="threshold (others 0)", ylabel="frames"),
              svg_lines([(n.upper(), [r["threshold"] for r in sw[n]], [r["auc"] for r in sw[n]]) for n in sw]
                        + [(n.upper() + " paper", [r["threshold"] for r in sw[n]], [r["paper_auc"] for r in sw[n]]) for n in sw],
                        title="sweep: AUC", xlabel="threshold (others 0)", ylabel="AUC", ylim=(0, 1))]
    hists = [svg_histogram(table.ms, title="MS", threshold=th.get("mt")),
             svg_histogram(table.ss, title="SS", threshold=th.get("st")),
             svg_histogram(table.es, title="ES", threshold=th.get("et"))]
    kept_rows = [int(r) for r in np.nonzero(sel.keep)[0]]
    drop_rows = [int(r) for r in np.nonzero(~sel.keep)[0]]
    kr, dr = _spread(kept_rows), _spread(drop_rows)
    thumbs = _thumbs(reference, topic, {int(table.index[r]) for r in kr + dr})
    contrib = results["criterion_contribution"]
    doc = f"""<!doctype html><html><head><meta charset="utf-8"><title>memlog evaluation</title>
<style>body{{font-family:sans-serif;margin:2em;max-width:1300px}} table{{border-collapse:collapse}}
td,th{{border:1px solid #ccc;padding:3px 8px;text-align:right}} .gallery{{display:flex;flex-wrap:wrap;gap:6px}}
figure{{margin:0;font-size:11px;width:160px}} svg{{margin:4px;border:1px solid #eee}}</style></head><body>
<h1>memlog evaluation</h1>
<p>reference <code>{html.escape(reference)}</code> ({html.escape(topic)}), query
<code>{html.escape(str(results['settings']['query']))}</code>, truth: {html.escape(str(results['truth']))},
descriptor <code>{html.escape(results['settings']['descriptor']['kind'])}</code>,
selection <code>{html.escape(results['memorable']['select'])}</code>, thresholds
<code>{html.escape(json.dumps(th))}</code>.</p>
<h2>Results</h2>{_table_html(results)}
<p>Matched as {html.escape(str(results.get('matching', {}).get('matching', 'single frame')))}
{html.escape(json.dumps(results.get('matching', {}).get('sequence') or {}))}; the single-frame columns match the
same maps frame by frame. Map-only: only map frames are searched. Paper protocol: the full reference database is
searched and a query whose best match was discarded reports no match. Random: mean ± std over
{results['random']['seeds']} seeds.</p>
<h2>Precision-recall</h2>{''.join(pr)}
<h2>Threshold sweeps</h2>{''.join(sweeps)}
<h2>Scores</h2>{''.join(hists)}
{svg_timeline(table, sel)}
<h2>Criterion contribution</h2><p>{contrib['mismatched_queries']} queries were mismatched with the full map; their
wrong best match would have been discarded by: {html.escape(json.dumps(contrib['wrong_match_discarded_by']))}.</p>
<h2>Frames</h2>{_gallery('selected', kr, table, sel, thumbs)}{_gallery('discarded', dr, table, sel, thumbs)}
</body></html>"""
    return write_bytes_atomic(path, doc.encode())

"""The HTML report of ``memlog evaluate``: one self-contained file, plots as inline SVG.

PR curves of every map variant, the threshold sweeps, score histograms, a timeline of the
drive (scores over frame index, kept frames and gaps marked), and galleries of selected and
discarded frames with their scores. Where localization fails: a strip along the query drive
(one cell per query frame in drive order, coloured right / wrong / true place not in the map /
no true place, with each query's confidence below it) and a gallery of query frames, worst first
(the wrong ones with the highest confidence first), each beside the map frame the matcher chose
and its nearest true map frame. The settings and the criterion contribution are tables, and
input paths are shown as the user gave them or relative to the report's directory, never as
absolute paths of the machine that ran it.
"""

from __future__ import annotations

import base64
import html
import os
from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from memlog.descriptors.table import DescriptorTable
from memlog.errors import ImageDecodeError
from memlog.evaluation.analysis import MAP_ROWS
from memlog.evaluation.metrics import ProtocolResult
from memlog.io.atomic import write_bytes_atomic
from memlog.io.open import open_log
from memlog.io.positions import geo_origin, geo_to_local
from memlog.outputs.svg_charts import svg_histogram, svg_lines, svg_spread
from memlog.outputs.svg_charts import svg_timeline as svg_timeline
from memlog.progress import warning
from memlog.selection import ScoreTable, Selection

__all__ = ["write_report", "svg_lines", "svg_histogram", "svg_strip", "query_outcomes", "QueryOutcome",
           "settings_rows", "shown_path", "GALLERY_QUERIES"]


def _fmt(v: float) -> str:
    return "-" if not np.isfinite(v) else f"{v:.3f}"


def _spread(rows: list[int], n: int = 24) -> list[int]:
    """Up to n rows spread evenly over ``rows``."""
    if not rows:
        return []
    return [rows[i] for i in np.linspace(0, len(rows) - 1, min(n, len(rows))).astype(int)]


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


def _spread_html(results: dict[str, Any]) -> str:
    """The maps of the memorable map's size, every k-th from each start offset and random, as dots,
    the memorable and the full map as lines, and where the memorable one lies among them."""
    rows = [(f"{label} ({len(results[name]['maps'])})", [m["recall@1"] for m in results[name]["maps"]])
            for name, label in (("uniform_phases", "every k-th, each offset"), ("random", "random"))
            if results.get(name, {}).get("maps")]
    if not rows:
        return ""
    mem = results["memorable"]
    marks = [("memorable", float(mem["recall@1"]), "#d62728")]
    if "full" in results:
        marks.append(("full", float(results["full"]["recall@1"]), "#222"))
    among = mem.get("among", {})
    text = "; ".join(f"{label}: {100 * a['below']:.0f} % below it, {100 * a['above']:.0f} % above"
                     for name, label in (("uniform_phases", "every k-th maps"), ("random", "random maps"))
                     for a in [among.get(name)] if a)
    spread = "; ".join(f"{label} R@1 {r['recall@1']:.3f} ± {r['std']['recall@1']:.3f} "
                       f"[{r['min']['recall@1']:.3f}, {r['max']['recall@1']:.3f}]"
                       for name, label in (("uniform_phases", "every k-th"), ("random", "random"))
                       for r in [results.get(name)] if r and "min" in r)
    return (svg_spread(rows, marks, title=f"R@1 of maps of {mem['frames']} frames") +
            f"<p class='note'>{html.escape(spread)}. The memorable map among them: {html.escape(text)}.</p>")


def _table_html(results: dict[str, Any]) -> str:
    head = ("<tr><th>map</th><th>frames</th><th>coverage</th><th>AUC</th><th>R@1</th><th>R@5</th><th>R@10</th>"
            "<th>P@100%R</th><th>ms/query</th><th>paper AUC</th><th>paper R@1</th>"
            "<th>single-frame AUC</th><th>single-frame R@1</th><th>single-frame paper R@1</th></tr>")
    rows = []
    for name, label in MAP_ROWS.items():
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
        rows.append(f"<tr><td>{label}</td><td>{r['frames']}</td><td>{f('coverage')}</td>"
                    f"<td>{f('auc')}</td><td>{f('recall@1')}</td><td>{f('recall@5')}</td><td>{f('recall@10')}</td>"
                    f"<td>{f('precision@100%recall')}</td><td>{1e3 * r['match_seconds_per_query']:.3f}</td>"
                    f"<td>{f('auc', pp, pp.get('std', {}))}</td><td>{f('recall@1', pp, pp.get('std', {}))}</td>"
                    f"<td>{f('auc', sf, sf.get('std', {}))}</td><td>{f('recall@1', sf, sf.get('std', {}))}</td>"
                    f"<td>{f('recall@1', sfp, sfp.get('std', {}))}</td></tr>")
    return f"<table>{head}{''.join(rows)}</table>"


#: How many query frames the gallery of queries shows at most (worst first).
GALLERY_QUERIES = 24

#: What became of a query frame, in the strip's and the gallery's words and colours (index = kind).
_KINDS: tuple[tuple[str, str, str], ...] = (
    ("right", "right", "#2e9e44"),
    ("wrong", "wrong place", "#d62728"),
    ("uncovered", "true place not in the map", "#f0a202"),
    ("no-truth", "no true place in the reference", "#b8b8b8"),
)
RIGHT, WRONG, UNCOVERED, NO_TRUTH = range(4)


def shown_path(p: str, base: Path) -> str:
    """A path as the report shows it: as the user gave it when relative, else relative to the
    report's directory ``base`` (never an absolute path of the machine that ran it)."""
    if not os.path.isabs(p):
        return p
    try:
        return os.path.relpath(p, os.path.abspath(base))
    except ValueError:  # another drive (Windows): the name alone
        return Path(p).name


@dataclass(frozen=True)
class QueryOutcome:
    """What became of one query frame under one protocol: ``kind`` (RIGHT, WRONG, UNCOVERED: its
    true places are all missing from the map, NO_TRUTH: it has none in the reference), the
    reported ``confidence`` (-inf: no match), the reference frame the matcher ``chosen`` (-1: none)
    and the ``true`` reference frame nearest the query (-1: none; a map frame when one is true,
    ``true_in_map``)."""

    row: int
    frame: int
    kind: int
    confidence: float
    chosen: int
    true: int
    true_in_map: bool


def _planar(query: DescriptorTable, ref: DescriptorTable) -> tuple[np.ndarray, np.ndarray] | None:
    """Both tables' positions in one local metric frame ([N, 2] each), or None when they do not share one."""
    qp, rp = query.positions, ref.positions
    if "x" in qp and "x" in rp:
        return np.stack([qp["x"], qp["y"]], axis=1), np.stack([rp["x"], rp["y"]], axis=1)
    if "lat" in qp and "lat" in rp:
        q = np.stack([qp["lat"], qp["lon"]], axis=1)
        r = np.stack([rp["lat"], rp["lon"]], axis=1)
        origin = geo_origin(np.concatenate([q, r]))
        return geo_to_local(q, origin), geo_to_local(r, origin)
    return None


def query_outcomes(result: ProtocolResult, truth: Sequence[Collection[int]], query: DescriptorTable,
                   ref: DescriptorTable, map_mask: np.ndarray) -> list[QueryOutcome]:
    """Each query row's outcome under ``result`` (rows of ``query``; ``truth`` and the result's
    best indices are rows of ``ref``; ``map_mask`` marks the map's rows), in drive order (by frame
    index). The true frame shown is the chosen one when it is right, else the true map frame
    nearest the query (by position when both drives have positions, else the middle of the true
    stretch), else, when the map holds none, the nearest true reference frame."""
    n = len(query.frame_index)
    if result.n_queries != n or len(truth) != n or len(map_mask) != len(ref.frame_index):
        raise ValueError(f"{result.n_queries} results, {len(truth)} truth sets and {n} query frames; "
                         f"map mask of {len(map_mask)} for {len(ref.frame_index)} reference frames")
    pos = _planar(query, ref)
    out = []
    for q in np.argsort(query.frame_index, kind="stable"):
        q = int(q)
        best = int(result.best_index[q])
        conf = float(result.confidence[q])
        if not np.isfinite(conf):
            conf = -np.inf
        true = sorted(int(j) for j in truth[q])
        in_map = [j for j in true if map_mask[j]]
        if result.correct[q]:
            kind, pick = RIGHT, best
        else:
            kind = NO_TRUTH if not true else UNCOVERED if not in_map else WRONG
            pick = -1
            cands = in_map or true
            if cands:
                pick = cands[len(cands) // 2]
                if pos is not None and np.all(np.isfinite(pos[0][q])):
                    d = np.linalg.norm(pos[1][cands] - pos[0][q], axis=1)
                    if np.isfinite(d).any():
                        pick = cands[int(np.nanargmin(d))]
        out.append(QueryOutcome(row=q, frame=int(query.frame_index[q]), kind=kind, confidence=conf,
                                chosen=int(ref.frame_index[best]) if best >= 0 else -1,
                                true=int(ref.frame_index[pick]) if pick >= 0 else -1,
                                true_in_map=pick >= 0 and bool(map_mask[pick])))
    return out


def _worst_first(outcomes: Sequence[QueryOutcome], n: int) -> list[QueryOutcome]:
    """Up to ``n`` outcomes, worst first: the wrong ones (every kind but right) by confidence,
    highest first (no match last), then the right ones by confidence, lowest first."""
    wrong = sorted((o for o in outcomes if o.kind != RIGHT), key=lambda o: (-o.confidence, o.frame))
    right = sorted((o for o in outcomes if o.kind == RIGHT), key=lambda o: (o.confidence, o.frame))
    return (wrong + right)[:n]


def _conf_text(c: float) -> str:
    return "no match" if not np.isfinite(c) else f"confidence {c:.3g}"


def _confidence_bars(norm: np.ndarray, edges: np.ndarray, x0: float, cw: float, top: int, height: int,
                     lo: float, hi: float) -> list[str]:
    """The strip's confidence row: one bar per cell (``edges``: its rows; ``norm``: each row's
    confidence scaled to 0..1, 0 for no match) of width ``cw`` from ``x0``, as one SVG path (none
    when every bar is empty)."""
    bars = []
    for b in range(len(edges) - 1):
        v = float(norm[edges[b]:edges[b + 1]].mean())
        if v > 0:
            bh = max(1.0, v * height)
            bars.append(f"M{x0 + b * cw:.2f},{top + height}v{-bh:.2f}h{cw:.2f}v{bh:.2f}z")
    if not bars:
        return []
    return [(f'<path class="confidence" d="{"".join(bars)}" fill="#555"><title>confidence of the reported '
             f'match, {lo:.3g} (bottom) to {hi:.3g} (top)</title></path>')]


def svg_strip(outcomes: Sequence[QueryOutcome], *, marks: Collection[int] = (), w: int = 1000) -> str:
    """The correctness strip: one cell per query frame in drive order (``outcomes`` as
    :func:`query_outcomes` gives them), coloured by kind, with each query's confidence as a bar
    below (scaled from 0, or the lowest reported when below it, to the highest; no match: none).
    Longer drives than the strip has pixels share a cell per pixel, stacked by kind. ``marks``:
    frames with a tick above (the gallery's)."""
    pad_l, pad_r, band_t, band_h, conf_h = 84, 10, 26, 34, 30
    conf_t = band_t + band_h + 6
    h = conf_t + conf_h + 30
    n = len(outcomes)
    parts = [f'<svg xmlns="http://www.w3.org/2000/svg" class="strip" width="{w}" height="{h}" font-size="12" '
             f'font-family="sans-serif"><text x="{pad_l}" y="14" font-weight="bold">the query drive, frame by frame '
             f'({n} frames): where the memorable map localized it and where not</text>']
    if not n:
        parts.append(f'<text x="{pad_l}" y="{band_t + 20}">no query frame</text></svg>')
        return "".join(parts)
    kinds = np.array([o.kind for o in outcomes], dtype=np.int64)
    conf = np.array([o.confidence for o in outcomes], dtype=np.float64)
    fin = np.isfinite(conf)
    # bars from 0 (or the lowest, when below) to the highest: equal confidences look equal
    lo, hi = (min(0.0, float(conf[fin].min())), float(conf[fin].max())) if fin.any() else (0.0, 1.0)
    norm = np.where(fin, (np.where(fin, conf, lo) - lo) / (hi - lo) if hi > lo else 1.0, 0.0)
    cols = min(n, w - pad_l - pad_r)
    edges = np.linspace(0, n, cols + 1).round().astype(int)
    cw = (w - pad_l - pad_r) / cols
    frames = [o.frame for o in outcomes]

    def span(a: int, b: int) -> str:  # rows a..b-1
        return f"query frame #{frames[a]}" if b - a == 1 else f"query frames #{frames[a]}–#{frames[b - 1]}"

    b = 0
    while b < cols:  # runs of cells of one kind: one rect each; a mixed cell: stacked
        a0, a1 = edges[b], edges[b + 1]
        counts = np.bincount(kinds[a0:a1], minlength=len(_KINDS))
        x = pad_l + b * cw
        if np.count_nonzero(counts) == 1:
            k = int(np.argmax(counts))
            e = b + 1
            while e < cols and np.all(kinds[edges[e]:edges[e + 1]] == k):
                e += 1
            tip = span(a0, edges[e]) + f": {_KINDS[k][1]}"
            if edges[e] - a0 == 1:
                tip += f", {_conf_text(conf[a0])}"
            parts.append(f'<rect class="cell {_KINDS[k][0]}" x="{x:.2f}" y="{band_t}" width="{(e - b) * cw:.2f}" '
                         f'height="{band_h}" fill="{_KINDS[k][2]}"><title>{html.escape(tip)}</title></rect>')
            b = e
            continue
        y = float(band_t)
        for k in (WRONG, UNCOVERED, NO_TRUTH, RIGHT):
            if counts[k]:
                hk = band_h * counts[k] / (a1 - a0)
                tip = f"{span(a0, a1)}: {counts[k]} {_KINDS[k][1]}"
                parts.append(f'<rect class="cell {_KINDS[k][0]}" x="{x:.2f}" y="{y:.2f}" width="{cw:.2f}" '
                             f'height="{hk:.2f}" fill="{_KINDS[k][2]}"><title>{html.escape(tip)}</title></rect>')
                y += hk
        b += 1
    parts.append(f'<rect x="{pad_l}" y="{conf_t}" width="{w - pad_l - pad_r}" height="{conf_h}" fill="#f4f4f4"/>')
    parts += _confidence_bars(norm, edges, pad_l, cw, conf_t, conf_h, lo, hi)
    parts.append(f'<text x="{pad_l - 6}" y="{band_t + band_h / 2 + 4}" text-anchor="end">outcome</text>'
                 f'<text x="{pad_l - 6}" y="{conf_t + conf_h / 2 + 4}" text-anchor="end">confidence</text>'
                 f'<text x="{pad_l - 6}" y="{conf_t + conf_h + 18}" text-anchor="end">frame</text>')
    row_of = {f: i for i, f in enumerate(frames)}
    for f in marks:
        if f in row_of:
            i = row_of[f]
            xm = pad_l + (int(np.searchsorted(edges, i, side="right")) - 0.5) * cw
            parts.append(f'<path class="mark" d="M{xm - 4:.1f},{band_t - 7}h8l-4,6z" fill="#222">'
                         f'<title>query frame #{f}: in the gallery below</title></path>')
    for i in sorted({int(v) for v in np.linspace(0, n - 1, min(n, 10)).round()}):
        xt = pad_l + (int(np.searchsorted(edges, i, side="right")) - 0.5) * cw
        parts.append(f'<line x1="{xt:.1f}" y1="{conf_t + conf_h}" x2="{xt:.1f}" y2="{conf_t + conf_h + 5}" stroke="#333"/>'
                     f'<text x="{xt:.1f}" y="{conf_t + conf_h + 18}" text-anchor="middle">#{frames[i]}</text>')
    parts.append("</svg>")
    return "".join(parts)


def _legend() -> str:
    return "<p class='legend'>" + "".join(
        f"<span><i style='background:{c}'></i>{html.escape(label)}</span>" for _, label, c in _KINDS) + \
        "<span>▼ shown in the gallery</span></p>"


def _img(thumbs: dict[int, str], frame: int, caption: str) -> str:
    pic = (f'<img src="data:image/jpeg;base64,{thumbs[frame]}" alt="{html.escape(caption)}"/>' if frame in thumbs
           else "<div class='noimg'>no image</div>")
    return f"<div class='shot'>{pic}<span>{caption}</span></div>"


def _query_gallery(shown: Sequence[QueryOutcome], q_thumbs: dict[int, str], r_thumbs: dict[int, str]) -> str:
    cards = []
    for o in shown:
        key, label, colour = _KINDS[o.kind]
        chosen = (_img(r_thumbs, o.chosen, f"chosen: map frame #{o.chosen}") if o.chosen >= 0
                  else "<div class='shot'><div class='noimg'>no match</div><span>chosen: none</span></div>")
        if o.true < 0:
            true = "<div class='shot'><div class='noimg'>none</div><span>no true place</span></div>"
        elif o.true_in_map:
            true = _img(r_thumbs, o.true, f"true: map frame #{o.true}")
        else:
            true = _img(r_thumbs, o.true, f"true: frame #{o.true}, not in the map")
        verdict = (f"<b style='color:{colour}'>RIGHT</b>" if o.kind == RIGHT
                   else f"<b style='color:{colour}'>WRONG</b>: {html.escape(label)}")
        cards.append(f"<figure class='query {key}' style='border-color:{colour}'>"
                     f"<figcaption>{verdict} · {_conf_text(o.confidence)}</figcaption><div class='trio'>"
                     f"{_img(q_thumbs, o.frame, f'query frame #{o.frame}')}{chosen}{true}</div></figure>")
    return f"<div class='query-gallery' id='query-gallery'>{''.join(cards)}</div>"


def _value(v: Any) -> str:
    """A setting's value as text (lists joined by commas; None as a dash)."""
    if v is None:
        return "–"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, float):
        return f"{v:g}"
    if isinstance(v, Mapping):
        return "; ".join(f"{k}: {_value(x)}" for k, x in v.items()) or "–"
    if isinstance(v, (list, tuple)):
        return ", ".join(_value(x) for x in v) or "–"
    return str(v)


def _flatten(d: Mapping[str, Any], prefix: str = "") -> list[tuple[str, Any]]:
    rows: list[tuple[str, Any]] = []
    for k, v in d.items():
        key = f"{prefix}.{k}" if prefix else str(k)
        if isinstance(v, Mapping) and v:
            rows += _flatten(v, key)
        else:
            rows.append((key, v))
    return rows


def _identity(ident: Any, base: Path) -> Any:
    """A log's identity (path, size, modification time) for the report: the path by
    :func:`shown_path`, the time as UTC."""
    if not isinstance(ident, Mapping):
        return ident
    out = dict(ident)
    if isinstance(out.get("path"), str):
        out["path"] = shown_path(out["path"], base)
    if isinstance(out.get("mtime_ns"), int):
        stamp = datetime.fromtimestamp(out.pop("mtime_ns") / 1e9, timezone.utc)
        out["modified"] = stamp.strftime("%Y-%m-%d %H:%M:%S UTC")
    return out


def settings_rows(settings: Mapping[str, Any], base: Path) -> list[tuple[str, list[tuple[str, str]]]]:
    """The settings as sections of (key, value text) rows: nested dicts flattened to dotted keys,
    the top level's plain values first (as "logs"); input paths by :func:`shown_path`."""
    s = dict(settings)
    for key in ("reference", "query"):
        if isinstance(s.get(key), str):
            s[key] = shown_path(s[key], base)
    if isinstance(s.get("inputs"), Mapping):
        s["inputs"] = {name: _identity(ident, base) for name, ident in s["inputs"].items()}
    plain = [(k, _value(v)) for k, v in s.items() if not isinstance(v, Mapping)]
    sections = [("logs", plain)] if plain else []
    for k, v in s.items():
        if isinstance(v, Mapping):
            sections.append((k, [(key, _value(x)) for key, x in _flatten(v)]))
    return sections


def _kv_tables(sections: Sequence[tuple[str, Sequence[tuple[str, str]]]], ident: str) -> str:
    """Sections of (key, value) rows as small tables side by side (one per section)."""
    tables = []
    for name, items in sections:
        rows = "".join(f"<tr><td class='key'>{html.escape(k)}</td><td>{html.escape(v)}</td></tr>" for k, v in items)
        tables.append(f"<table class='settings'><tr><th colspan='2' class='section'>{html.escape(name)}</th></tr>"
                      f"{rows}</table>")
    return f"<div class='settings' id='{ident}'>{''.join(tables)}</div>"


def _contribution_html(contrib: Mapping[str, Any]) -> str:
    if "skipped" in contrib:
        return f"<p id='contribution'>{html.escape(str(contrib['skipped']))}.</p>"
    th = contrib.get("thresholds") or {}
    keys = {"staticity": "st", "entropy": "et", "memorability": "mt"}
    rows = []
    for name, count in (contrib.get("wrong_match_discarded_by") or {}).items():
        t = th.get(keys.get(name, ""))
        rule = f"{keys[name].upper()} {t:.2f}" if t is not None else "passes all three"
        rows.append(f"<tr><td class='key'>{html.escape(str(name))}</td><td>{html.escape(rule)}</td><td>{count}</td></tr>")
    return (f"<p>{contrib.get('mismatched_queries', 0)} queries were mismatched with the full map. The first criterion "
            "of the paper's rule that their wrong best match fails (it would have been discarded by it):</p>"
            "<table class='contribution' id='contribution'><tr><th>criterion</th><th>threshold</th>"
            f"<th>wrong best matches</th></tr>{''.join(rows)}</table>"
            f"<p class='note'>{html.escape(str(contrib.get('note', '')))}</p>")


def _thresholds_text(th: Mapping[str, Any]) -> str:
    return ", ".join(f"{k.upper()} {v:.2f}" if isinstance(v, (int, float)) else f"{k.upper()} {v}"
                     for k, v in th.items()) or "none"


def _failures(per_variant: dict[str, tuple[ProtocolResult, ProtocolResult]], ref_t: DescriptorTable,
              sel: Selection, query_table: DescriptorTable | None, truth: Sequence[Collection[int]] | None,
              max_queries: int) -> tuple[list[QueryOutcome], list[QueryOutcome]] | None:
    """(every query's outcome under the memorable map, map-only; the gallery's), or None when the
    report was not given what it takes."""
    if query_table is None or truth is None or "memorable" not in per_variant:
        return None
    mask = np.isin(ref_t.frame_index, sel.kept_indices)
    try:
        outcomes = query_outcomes(per_variant["memorable"][0], truth, query_table, ref_t, mask)
    except ValueError as exc:
        warning(f"report: no gallery of queries ({exc})")
        return None
    return outcomes, _worst_first(outcomes, max_queries)


def _plots(results: dict[str, Any], table: ScoreTable,
           per_variant: dict[str, tuple[ProtocolResult, ProtocolResult]],
           th: Mapping[str, Any]) -> tuple[list[str], list[str], list[str]]:
    """The report's charts as SVG: the PR curves (map-only, paper protocol), the threshold sweeps
    (or why there are none) and the score histograms with their thresholds."""
    pr = [svg_lines([(name, list(mo.curve.recall), list(mo.curve.precision)) for name, (mo, _) in per_variant.items()],
                    title="PR curves (map-only)", xlabel="recall", ylabel="precision", xlim=(0, 1), ylim=(0, 1)),
          svg_lines([(name, list(po.curve.recall), list(po.curve.precision)) for name, (_, po) in per_variant.items()],
                    title="PR curves (paper protocol)", xlabel="recall", ylabel="precision", xlim=(0, 1), ylim=(0, 1))]
    sw = results["sweeps"]
    if "skipped" in sw:  # (the staged scoring leaves scores out: evaluate --compare-exact has them)
        sweeps = [f"<p id='no-sweeps'>{html.escape(str(sw['skipped']))}.</p>"]
    else:
        sweeps = [svg_lines([(n.upper(), [r["threshold"] for r in sw[n]], [r["frames"] for r in sw[n]]) for n in sw],
                            title="sweep: selected frames", xlabel="threshold (others 0)", ylabel="frames"),
                  svg_lines([(n.upper(), [r["threshold"] for r in sw[n]], [r["auc"] for r in sw[n]]) for n in sw]
                            + [(n.upper() + " paper", [r["threshold"] for r in sw[n]], [r["paper_auc"] for r in sw[n]])
                               for n in sw],
                            title="sweep: AUC", xlabel="threshold (others 0)", ylabel="AUC", ylim=(0, 1))]
    hists = [svg_histogram(table.ms, title="MS", threshold=th.get("mt")),
             svg_histogram(table.ss, title="SS", threshold=th.get("st")),
             svg_histogram(table.es, title="ES", threshold=th.get("et"))]
    return pr, sweeps, hists


def _where_html(fails: tuple[list[QueryOutcome], list[QueryOutcome]] | None, sel: Selection,
                q_thumbs: dict[int, str], r_thumbs: dict[int, str]) -> str:
    """The section "where localization fails": the summary, the strip and the gallery of queries
    (``fails`` as :func:`_failures` gives it), or why it is not available."""
    if fails is None:
        return ("<p id='no-failures'>Not available: the report was written without the query drive's frames "
                "and truth.</p>")
    outcomes, shown = fails
    counts = np.bincount([o.kind for o in outcomes], minlength=len(_KINDS))
    summary = ", ".join(f"{int(c)} {label}" for (_, label, _), c in zip(_KINDS, counts))
    return (f"<p>The memorable map ({int(sel.n_kept)} frames), map-only protocol, as the main results. "
            f"Of {len(outcomes)} query frames: {html.escape(summary)}. Hover a cell for its frames.</p>"
            f"<div class='strip-box' id='strip'>{svg_strip(outcomes, marks={o.frame for o in shown})}"
            f"{_legend()}</div>"
            f"<h3>Gallery of queries: worst first</h3><p>{len(shown)} of {len(outcomes)} query frames: the wrong "
            "ones with the highest confidence first, then the right ones, least confident first. Each: the "
            "query frame, the map frame the matcher chose, and the true map frame nearest the query (a "
            "discarded reference frame when none of its true places is in the map).</p>"
            + _query_gallery(shown, q_thumbs, r_thumbs))


def write_report(path: Path, results: dict[str, Any], table: ScoreTable, sel: Selection,
                 per_variant: dict[str, tuple[ProtocolResult, ProtocolResult]], ref_t: DescriptorTable,
                 reference: str, topic: str, *, query: str | None = None, query_topic: str | None = None,
                 query_table: DescriptorTable | None = None, truth: Sequence[Collection[int]] | None = None,
                 max_queries: int = GALLERY_QUERIES) -> Path:
    """Write the self-contained HTML report (atomically).

    ``query``/``query_topic``/``query_table`` (the query drive's descriptor table: its frame
    indices and positions) and ``truth`` (each query row's true reference rows) give the strip
    and the gallery of queries (under the memorable map, map-only: ``per_variant["memorable"]``);
    without them the report says where they would be."""
    base = path.parent
    th = sel.thresholds or {}
    pr, sweeps, hists = _plots(results, table, per_variant, th)
    kept_rows = [int(r) for r in np.nonzero(sel.keep)[0]]
    drop_rows = [int(r) for r in np.nonzero(~sel.keep)[0]]
    kr, dr = _spread(kept_rows), _spread(drop_rows)

    # every thumbnail from one pass over each log: the frame galleries' and the query gallery's
    fails = _failures(per_variant, ref_t, sel, query_table, truth, max_queries)
    ref_key, q_key = (reference, topic), (query or reference, query_topic or topic)
    wanted: dict[tuple[str, str], set[int]] = {ref_key: {int(table.index[r]) for r in kr + dr}}
    if fails is not None:
        wanted[ref_key] |= {f for o in fails[1] for f in (o.chosen, o.true) if f >= 0}
        wanted.setdefault(q_key, set()).update(o.frame for o in fails[1])
    thumbs = {(log, tp): _thumbs(log, tp, idx) for (log, tp), idx in wanted.items()}
    where = _where_html(fails, sel, thumbs.get(q_key, {}), thumbs[ref_key])
    contrib = results["criterion_contribution"]
    settings = results.get("settings") or {}
    ref_shown = shown_path(str(settings.get("reference", reference)), base)
    query_shown = shown_path(str(settings.get("query", query or "")), base)
    q_topic = settings.get("query_topic", query_topic or "")
    matching = dict(results.get("matching") or {})
    how = str(matching.pop("matching", "single frame"))
    match_sections = [("matching", [(k, _value(v)) for k, v in _flatten(matching)])] if matching else []
    doc = f"""<!doctype html><html lang="en"><head><meta charset="utf-8"><title>memlog evaluation</title>
<style>body{{font-family:sans-serif;font-size:15px;line-height:1.4;margin:2em;max-width:1300px;color:#111}}
table{{border-collapse:collapse;margin:6px 0}} td,th{{border:1px solid #ccc;padding:3px 8px;text-align:right}}
th{{background:#f2f2f2}} table.settings td,table.contribution td.key{{text-align:left}} td.key{{font-family:monospace}}
th.section{{text-align:left;background:#e4ecf4}} table.settings td{{max-width:380px;overflow-wrap:anywhere}}
div.settings{{display:flex;flex-wrap:wrap;gap:14px;align-items:flex-start}}
.gallery{{display:flex;flex-wrap:wrap;gap:6px}} figure{{margin:0;font-size:12px;width:160px}}
svg{{margin:4px;border:1px solid #eee;max-width:100%;height:auto}} nav a{{margin-right:1em}}
.legend span{{margin-right:1.5em;white-space:nowrap}} .legend i{{display:inline-block;width:14px;height:14px;
margin-right:5px;vertical-align:-2px;border:1px solid #888}}
.query-gallery{{display:grid;grid-template-columns:repeat(auto-fill,minmax(510px,1fr));gap:10px}}
figure.query{{width:auto;border:3px solid;border-radius:4px;padding:6px;font-size:13px}}
.trio{{display:flex;gap:6px}} .shot{{width:160px;display:flex;flex-direction:column}} .shot img{{width:160px}}
.shot span{{font-size:12px}} .noimg{{width:160px;height:120px;background:#eee;display:flex;align-items:center;
justify-content:center;color:#666}} .note{{color:#555;font-size:13px}}</style></head><body>
<h1>memlog evaluation</h1>
<nav><a href="#results">results</a><a href="#where">where localization fails</a><a href="#pr">precision-recall</a>
<a href="#sweeps">sweeps</a><a href="#scores">scores</a><a href="#criteria">criterion contribution</a>
<a href="#frames">frames</a><a href="#settings-section">settings</a></nav>
<p>Reference <code>{html.escape(ref_shown)}</code> ({html.escape(topic)}), query
<code>{html.escape(query_shown)}</code> ({html.escape(str(q_topic))}), truth:
{html.escape(shown_path(str(results['truth']), base))}, descriptor
<code>{html.escape(str(settings.get('descriptor', {}).get('kind', '')))}</code>, selection
<code>{html.escape(str(results['memorable'].get('select', '')))}</code>, thresholds {html.escape(_thresholds_text(th))}.</p>
<h2 id="results">Results</h2>{_table_html(results)}
<p>Matched as {html.escape(how)} (details under <a href="#settings-section">settings</a>); the single-frame columns
match the same maps frame by frame. Map-only: only map frames are searched. Paper protocol: the full reference
database is searched and a query whose best match was discarded reports no match. Random: mean ± std over
{results['random']['seeds']} seeds; every k-th, its start offsets: mean ± std over the maps of every k-th frame
from each start offset.</p>{_spread_html(results)}
<h2 id="where">Where localization fails</h2>{where}
<h2 id="pr">Precision-recall</h2>{''.join(pr)}
<h2 id="sweeps">Threshold sweeps</h2>{''.join(sweeps)}
<h2 id="scores">Scores</h2>{''.join(hists)}
{svg_timeline(table, sel)}
<h2 id="criteria">Criterion contribution</h2>{_contribution_html(contrib)}
<h2 id="frames">Frames</h2>{_gallery('selected', kr, table, sel, thumbs[ref_key])}{_gallery('discarded', dr, table, sel, thumbs[ref_key])}
<h2 id="settings-section">Settings</h2>{_kv_tables(settings_rows(settings, base) + match_sections, 'settings')}
</body></html>"""
    return write_bytes_atomic(path, doc.encode())

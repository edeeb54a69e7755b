"""The HTML report of ``memlog evaluate``: where localization fails (the correctness strip along the
query drive, the gallery of queries worst first), the settings and the criterion contribution as
tables, input paths never absolute, and the whole page rendered in headless Chromium.

The report is built here from hand-made evaluation results over the fixture drive (demo.mcap: the
compressed topic as reference, the raw one as query), so every outcome is known in advance and no
model runs; ``tests/test_pipeline.py`` writes one through ``memlog evaluate`` itself.
"""

from __future__ import annotations

import json
import re
import subprocess
from pathlib import Path
from typing import Any

import numpy as np

from memlog.descriptors.base import DescriptorMeta
from memlog.descriptors.table import DescriptorTable
from memlog.evaluation.metrics import evaluate_map_only, evaluate_paper
from memlog.outputs.report import (
    GALLERY_QUERIES,
    NO_TRUTH,
    RIGHT,
    UNCOVERED,
    WRONG,
    QueryOutcome,
    query_outcomes,
    settings_rows,
    shown_path,
    svg_strip,
    write_report,
)
from memlog.selection import ScoreTable, Selection
from tests.conftest import FIXTURES, ROOT, chromium

DEMO = FIXTURES / "demo.mcap"
COMP = "/camera/image/compressed"
RAW = "/camera/image_raw"
T0 = 1_700_000_000_000_000_000

# the map keeps reference frames 2 and 6; per query frame: its true reference frames, the map frame
# the matcher chose and the confidence it reported
KEPT = (2, 6)
TRUTH = [{0, 1}, {2}, {2, 3}, {5}, {6}, {6, 7}, set(), {2}]
CHOSEN = [6, 2, 6, 2, 6, 2, 6, 2]
CONF = [0.30, 0.50, 0.90, 0.20, 0.70, 0.10, 0.40, 0.05]
# 0: true places 0, 1 not in the map; 1: right; 2: wrong (2 was in the map); 3: 5 not in the map;
# 4: right; 5: wrong; 6: no true place; 7: right
KINDS = [UNCOVERED, RIGHT, WRONG, UNCOVERED, RIGHT, WRONG, NO_TRUTH, RIGHT]


def _table(n: int, x: np.ndarray) -> DescriptorTable:
    rng = np.random.default_rng(n)
    d = rng.normal(size=(n, 4)).astype(np.float32)
    return DescriptorTable(topic=[COMP] * n, frame_index=np.arange(n, dtype=np.int64),
                           log_time_ns=T0 + np.arange(n, dtype=np.int64) * 100_000_000,
                           stamp_ns=T0 + np.arange(n, dtype=np.int64) * 100_000_000,
                           descriptors=d / np.linalg.norm(d, axis=1, keepdims=True),
                           meta=DescriptorMeta(kind="thumbnail", version="1", dim=4),
                           positions={"x": x.astype(np.float64), "y": np.zeros(n)})


def _inputs() -> dict[str, Any]:
    """What write_report takes, for the fixture drive and the outcomes above."""
    n = 8
    x = 5.0 * np.arange(n)
    ref_t, q_t = _table(n, x), _table(n, x)
    mask = np.isin(np.arange(n), KEPT)
    idx = np.array(CHOSEN, dtype=np.int64)[:, None]
    sims = np.array(CONF)[:, None]
    mo = evaluate_map_only((idx, sims), TRUTH, mask, ns=(1,))
    po = evaluate_paper((idx, sims), TRUTH, mask, ns=(1,))
    rng = np.random.default_rng(0)
    table = ScoreTable(index=np.arange(n), t_ns=T0 + np.arange(n) * 100_000_000, ms=rng.random(n),
                       ss=rng.random(n), es=rng.random(n), topic=COMP)
    sel = Selection(mode="segment", index=np.arange(n), keep=mask,
                    reason=[None if k else "segment" for k in mask], thresholds={"mt": 0.0, "st": 0.1, "et": 0.0})
    row = {"frames": 2, "coverage": 0.25, "auc": mo.auc, "recall@1": mo.recall_at[1], "recall@5": None,
           "recall@10": None, "precision@100%recall": 0.0, "match_seconds_per_query": 1e-4,
           "paper_protocol": {"auc": po.auc, "recall@1": po.recall_at[1]}}
    sweep = [{"threshold": t, "frames": 8 - int(8 * t), "auc": 0.5 * (1 - t), "paper_auc": 0.4 * (1 - t)}
             for t in (0.0, 0.5, 1.0)]
    results: dict[str, Any] = {
        "full": dict(row, frames=8), "memorable": dict(row, select="segment"),
        "random": dict(row, seeds=2, std={"auc": 0.01}),
        "matching": {"matching": "sequence", "sequence": {"length": 10, "causal": False}, "sequence_queries": 8},
        "sweeps": {"mt": sweep, "st": sweep, "et": sweep},
        "criterion_contribution": {"mismatched_queries": 3, "thresholds": {"mt": 0.5, "st": 0.6, "et": 0.4},
                                   "wrong_match_discarded_by": {"staticity": 1, "entropy": 0, "memorability": 2,
                                                                "kept": 0},
                                   "note": "for each query the full map mismatched, the first criterion"},
        "truth": str(ROOT / "truth.json"),  # an absolute path, as a user may give it
        "settings": {"score": {"mt": 0.5, "dynamic_classes": ["person", "car"], "threads": 0},
                     "select": {"mode": "segment", "weights": [1.0, 1.0, 1.0], "keep_fraction": None},
                     "descriptor": {"kind": "thumbnail", "params": {"width": 64, "height": 32}},
                     "options": {"sequence": {"length": 10, "causal": False}, "whiten": True},
                     "reference": str(DEMO), "query": "fixtures/demo.mcap",
                     "reference_topic": COMP, "query_topic": RAW,
                     "inputs": {"reference": {"path": str(DEMO), "size": 1, "mtime_ns": 1_700_000_000_000_000_000},
                                "query": {"path": str(DEMO), "size": 1, "mtime_ns": 1_700_000_000_000_000_000}}},
    }
    return {"results": results, "table": table, "sel": sel, "per_variant": {"memorable": (mo, po), "full": (mo, po)},
            "ref_t": ref_t, "reference": str(DEMO), "topic": COMP, "query": str(DEMO), "query_topic": RAW,
            "query_table": q_t, "truth": TRUTH}


def _write(path: Path, **over: Any) -> str:
    kw = {**_inputs(), **over}
    write_report(path, kw.pop("results"), kw.pop("table"), kw.pop("sel"), kw.pop("per_variant"), kw.pop("ref_t"),
                 kw.pop("reference"), kw.pop("topic"), **kw)
    return path.read_text()


def test_outcomes_say_right_wrong_uncovered_and_the_nearest_true_map_frame() -> None:
    kw = _inputs()
    mo = kw["per_variant"]["memorable"][0]
    got = query_outcomes(mo, TRUTH, kw["query_table"], kw["ref_t"], np.isin(np.arange(8), KEPT))
    assert [o.frame for o in got] == list(range(8))  # drive order
    assert [o.kind for o in got] == KINDS
    assert [o.chosen for o in got] == CHOSEN
    assert [o.confidence for o in got] == CONF
    by = {o.frame: o for o in got}
    assert (by[1].true, by[1].true_in_map) == (2, True)  # right: the chosen frame
    assert (by[2].true, by[2].true_in_map) == (2, True)  # wrong: the true frame the map holds, not 3
    assert (by[5].true, by[5].true_in_map) == (6, True)
    assert (by[0].true, by[0].true_in_map) == (0, False)  # none in the map: the nearest true frame (x = 0 m)
    assert (by[3].true, by[3].true_in_map) == (5, False)
    assert by[6].true == -1 and not by[6].true_in_map  # no true place


def test_the_gallery_is_worst_first_and_bounded(tmp_path: Path) -> None:
    text = _write(tmp_path / "report.html")
    shown = re.findall(r"<figure class='query ([\w-]+)'.*?query frame #(\d+)", text)
    # the wrong ones by confidence, highest first: 2 (0.9), 0 (0.3)... then the right ones, least confident first
    assert [int(f) for _, f in shown] == [2, 6, 0, 3, 5, 7, 1, 4]
    assert [k for k, _ in shown] == ["wrong", "no-truth", "uncovered", "uncovered", "wrong", "right", "right", "right"]
    card = text[text.index("query frame #2"):]
    assert card.index("chosen: map frame #6") < card.index("true: map frame #2") < card.index("</figure>")
    assert "true: frame #0, not in the map" in text
    assert text.count("<figure class='query") == 8 and GALLERY_QUERIES == 24
    few = _write(tmp_path / "few.html", max_queries=3)
    assert [int(f) for f in re.findall(r"<figure class='query [\w-]+'.*?query frame #(\d+)", few)] == [2, 6, 0]
    # every card's three frames are real thumbnails (base64 JPEG read from the logs), but a missing true place
    gallery = text[text.index("id='query-gallery'"):text.index('<h2 id="pr">')]
    assert gallery.count('src="data:image/jpeg;base64,/9j/') == 3 * 8 - 1


def test_the_strip_has_one_cell_per_query_in_drive_order(tmp_path: Path) -> None:
    text = _write(tmp_path / "report.html")
    strip = text[text.index("<svg xmlns=\"http://www.w3.org/2000/svg\" class=\"strip\""):]
    strip = strip[:strip.index("</svg>")]
    cells = re.findall(r'<rect class="cell ([\w-]+)".*?<title>(.*?)</title>', strip)
    assert [k for k, _ in cells] == ["uncovered", "right", "wrong", "uncovered", "right", "wrong", "no-truth", "right"]
    assert cells[2][1] == "query frame #2: wrong place, confidence 0.9"
    assert strip.count('class="mark"') == 8  # each gallery query ticked
    assert 'class="confidence"' in strip


def test_a_long_drive_shares_cells_but_keeps_every_failing_stretch() -> None:
    n = 20_000
    kinds = np.full(n, RIGHT)
    kinds[5000:5100] = WRONG  # a failing stretch
    kinds[12345] = UNCOVERED  # one frame, narrower than a pixel
    outs = [QueryOutcome(row=i, frame=i, kind=int(k), confidence=float(i % 7), chosen=0, true=0, true_in_map=True)
            for i, k in enumerate(kinds)]
    svg = svg_strip(outs, w=1000)
    assert len(svg) < 100_000  # bounded by the strip's width, not the drive's length
    tips = re.findall(r'<rect class="cell ([\w-]+)"[^>]*><title>query frames #(\d+)–#(\d+): (.*?)</title>', svg)
    wrong = [(int(a), int(b)) for k, a, b, _ in tips if k == "wrong"]
    covered = set().union(*(range(a, b + 1) for a, b in wrong))
    assert set(range(5000, 5100)) <= covered <= set(range(4950, 5150))  # the stretch, to a cell or so
    assert [(int(a) <= 12345 <= int(b), t) for k, a, b, t in tips if k == "uncovered"] == [
        (True, "1 true place not in the map")]
    assert svg.count('<rect class="cell') < 20


def test_settings_and_contribution_are_tables_and_no_path_is_absolute(tmp_path: Path) -> None:
    out = tmp_path / "out"
    out.mkdir()
    text = _write(out / "report.html")
    assert not re.search(r"(?<!\.\.)" + re.escape(str(ROOT)), text)  # only as the tail of a relative path
    rel = shown_path(str(DEMO), out)
    assert not Path(rel).is_absolute() and (out / rel).resolve() == DEMO.resolve()
    assert f"<code>{rel}</code>" in text  # the reference, given absolute: relative to the report
    assert "fixtures/demo.mcap" in text  # the query as the user gave it
    assert shown_path("positions within 25 m", out) == "positions within 25 m"
    settings = text[text.index("id='settings'"):]
    assert "{" not in settings and "[" not in settings  # no raw JSON
    sections = dict(settings_rows(_inputs()["results"]["settings"], out))
    assert sections["score"] == [("mt", "0.5"), ("dynamic_classes", "person, car"), ("threads", "0")]
    assert sections["descriptor"] == [("kind", "thumbnail"), ("params.width", "64"), ("params.height", "32")]
    assert ("sequence.causal", "no") in sections["options"]
    assert ("reference.modified", "2023-11-14 22:13:20 UTC") in sections["inputs"]
    assert ("reference", rel) in sections["logs"] and ("query", "fixtures/demo.mcap") in sections["logs"]
    contrib = text[text.index("id='contribution'"):]
    contrib = contrib[:contrib.index("</table>")]
    assert re.findall(r"<td class='key'>(\w+)</td><td>([^<]*)</td><td>(\d+)</td>", contrib) == [
        ("staticity", "ST 0.60", "1"), ("entropy", "ET 0.40", "0"), ("memorability", "MT 0.50", "2"),
        ("kept", "passes all three", "0")]


def test_without_the_query_the_report_says_so(tmp_path: Path) -> None:
    text = _write(tmp_path / "report.html", query=None, query_topic=None, query_table=None, truth=None)
    assert "id='no-failures'" in text and "id='query-gallery'" not in text and 'class="strip"' not in text
    assert text.count("<svg") >= 6


_PROBE = """<script>
window.addEventListener("load", () => {
  const out = {width: document.documentElement.scrollWidth, sections: {}, images: []};
  for (const sel of ["#where", "#strip svg.strip", "#strip .legend", "#query-gallery", "#settings",
                     "#settings table", "#contribution", "#results + table"]) {
    const el = document.querySelector(sel);
    if (!el) { out.sections[sel] = null; continue; }
    const r = el.getBoundingClientRect(), cs = getComputedStyle(el);
    out.sections[sel] = {w: r.width, h: r.height, left: r.left, right: r.right, display: cs.display,
                         visibility: cs.visibility, opacity: cs.opacity, font: parseFloat(cs.fontSize)};
  }
  for (const img of document.querySelectorAll("#query-gallery img")) {
    out.images.push({natural: img.naturalWidth, w: img.getBoundingClientRect().width});
  }
  const pre = document.createElement("pre");
  pre.id = "probe";
  pre.textContent = JSON.stringify(out);
  document.body.appendChild(pre);
});
</script>"""


def _chromium(browser: str, tmp_path: Path, *args: str) -> subprocess.CompletedProcess[str]:
    cmd = [browser, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars",
           f"--user-data-dir={tmp_path / 'chromium-profile'}", "--window-size=1400,1000", *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=180, check=False)


def test_the_report_renders_in_headless_chromium(tmp_path: Path) -> None:
    """Every section the failure analysis adds is there, visible and on the page in a real browser;
    the gallery's thumbnails decode; nothing is wider than the window."""
    browser = chromium()
    text = _write(tmp_path / "report.html")
    probe = tmp_path / "probe.html"
    probe.write_text(text.replace("</body>", _PROBE + "</body>"))
    run = _chromium(browser, tmp_path, "--virtual-time-budget=10000", "--dump-dom", probe.as_uri())
    m = re.search(r'<pre id="probe">(.*?)</pre>', run.stdout)
    assert m, f"chromium rendered no probe (exit {run.returncode}): {run.stderr[-2000:]}"
    seen = json.loads(m.group(1).replace("&quot;", '"').replace("&amp;", "&"))
    for sel, box in seen["sections"].items():
        assert box is not None, f"{sel}: not in the page"
        assert box["w"] > 50 and box["h"] > 10, (sel, box)
        assert box["display"] != "none" and box["visibility"] == "visible" and float(box["opacity"]) == 1, (sel, box)
        assert box["left"] >= 0 and box["right"] <= 1400, (sel, box)
        assert box["font"] >= 12, (sel, box)  # legible
    assert seen["width"] <= 1400  # no sideways scrolling
    assert len(seen["images"]) == 3 * 8 - 1 and all(i["natural"] > 0 and i["w"] >= 120 for i in seen["images"])

    shot = tmp_path / "report.png"
    run = _chromium(browser, tmp_path, f"--screenshot={shot}", (tmp_path / "report.html").as_uri())
    assert shot.is_file(), f"no screenshot (exit {run.returncode}): {run.stderr[-2000:]}"
    import cv2

    img = cv2.imread(str(shot))
    assert img is not None and img.shape[:2] == (1000, 1400)
    assert (img < 200).any(axis=2).mean() > 0.02  # text and pictures, not a blank page


def test_sweeps_and_contribution_not_computed_say_why(tmp_path: Path) -> None:
    """evaluate without --compare-exact scores the reference as memlog map does (scores left null where
    they change nothing): the sweeps and the contribution are not computed, and the report says why
    instead of drawing them; the score histograms leave the null scores out."""
    kw = _inputs()
    why = "not computed: the reference was scored as memlog map scores it; run evaluate with --compare-exact"
    kw["results"] = dict(kw["results"], sweeps={"skipped": why}, criterion_contribution={"skipped": why})
    kw["table"].ms[:] = np.nan  # (ResMem ran on none of the frames)
    kw["table"].ss[::2] = np.nan
    text = _write(tmp_path / "report.html", **kw)
    sweeps = text[text.index("<h2 id=\"sweeps\">"):text.index("<h2 id=\"scores\">")]
    assert "id='no-sweeps'" in sweeps and "--compare-exact" in sweeps and "<svg" not in sweeps
    contrib = text[text.index("<h2 id=\"criteria\">"):]
    assert "--compare-exact" in contrib[:600] and "<table class='contribution'" not in contrib

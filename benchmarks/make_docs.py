#!/usr/bin/env python3
"""Regenerate docs/benchmarks.md from the benchmark scripts: one command, no tables pasted by hand.

    python benchmarks/make_docs.py                     # run every benchmark (hours on 2 cores), rewrite the page
    python benchmarks/make_docs.py --only record_codecs resmem_flops   # run these, keep the other sections
    python benchmarks/make_docs.py --quick             # run the benchmarks of a few minutes, keep the others
    python benchmarks/make_docs.py --cached            # run nothing: rebuild the page from the sections it has
    python benchmarks/make_docs.py --list              # the benchmarks, their commands and rough times

Each benchmark is one command (a script in ``benchmarks/`` or a ``memlog`` command) whose standard
output is the section's content, verbatim: the scripts print Markdown tables; other output is put in
a text block; ``memlog evaluate`` runs are summarised from their ``results.json``. A section's
heading is the command that produced it, and under it what was measured on which data, when, on
which machine (cores, CPU, load average), with which memlog (version, git commit) and how long it
took. A benchmark that is not run keeps its section as it stands in the page, so ``--only`` and
``--quick`` update part of the page and ``--cached`` only renews the page's frame (header, list of
sections). A section that no run has produced yet says so and links to the figures recorded by hand
when the defaults were chosen (docs/defaults.md).

The page is written atomically (temporary file, then rename) after every benchmark, so an
interrupted run keeps the sections finished so far. Benchmarks that need the shared data
(``../shared/data`` or ``$MEMLOG_SHARED_DATA``) are skipped, with a message, without it. The ones that
need every score of the Nordland summer drive (``--scores``) get the file made once by ``memlog score
--all-scores`` (about an hour of CNN on two cores) in ``--work`` unless ``--scores`` names one.
Scratch files (caches, outputs of ``memlog evaluate``) go to ``--work`` (default
``/tmp/memlog-make-docs``), never into the repository.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import os
import re
import shlex
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))  # (the evaluate summaries name memlog's map rows)
PAGE = ROOT / "docs" / "benchmarks.md"
SHARED = Path(os.environ.get("MEMLOG_SHARED_DATA", ROOT.parent / "shared" / "data"))
WORK = Path(os.environ.get("MEMLOG_BENCH_WORK", "/tmp/memlog-make-docs"))

#: the benchmarks of at most this many minutes (on 2 cores) run with ``--quick``
QUICK_MINUTES = 5.0


@dataclass(frozen=True)
class Bench:
    """One section of the page: ``argv`` is the command as shown in its heading, with ``{shared}``,
    ``{work}`` and ``{scores}`` filled in when it runs (``python`` is this interpreter)."""

    name: str
    argv: tuple[str, ...]
    what: str
    minutes: float
    needs: tuple[str, ...] = ()  # "shared", "scores", "models"
    summarise: Callable[[Path], str] | None = None  # memlog commands: their output directory -> Markdown
    outdir: str | None = None  # memlog commands: the output directory under --work (made empty first)
    defaults_anchor: str | None = None  # where docs/defaults.md keeps the figures recorded by hand
    prepare: Callable[[Path, Path | None], None] | None = field(default=None, compare=False)

    def command(self, work: Path, scores: Path | None, shown: bool = False) -> list[str]:
        """The argv to run (``shown``: as the heading shows it, with placeholders for machine paths)."""
        subst = {"{shared}": "../shared/data" if shown else str(SHARED),
                 "{work}": "$WORK" if shown else str(work),
                 "{scores}": "$WORK/nordland_summer.scored.mcap" if shown or scores is None else str(scores)}
        out = []
        for a in self.argv:
            for k, v in subst.items():
                a = a.replace(k, v)
            out.append(a)
        if not shown and out[0] == "python":
            out[0] = sys.executable
        if not shown and out[0] == "memlog":
            out = [sys.executable, "-m", "memlog", *out[1:]]
        return out

    def heading(self) -> str:
        """The command as the section's heading shows it (``$WORK``: the scratch directory)."""
        return " ".join(a if a and not re.search(r"[\s'\"]", a) else shlex.quote(a)
                        for a in self.command(WORK, None, shown=True))


# -- memlog evaluate: results.json -> Markdown --------------------------------------------------
def _f(v: Any, nd: int = 3) -> str:
    if v is None:
        return "–"
    if isinstance(v, dict) and "mean" in v:
        return f"{v['mean']:.{nd}f} ± {v.get('std', 0.0):.{nd}f}"
    if isinstance(v, (int, float)):
        return f"{v:.{nd}f}"
    return str(v)


def _frames(row: dict[str, Any]) -> str:
    for key in ("frames", "n_frames", "map_frames"):
        if key in row:
            return str(row[key])
    if "kept_indices" in row:
        return str(len(row["kept_indices"]))
    return "–"


def summarise_evaluate(outdir: Path) -> str:
    """The table ``memlog evaluate`` prints, from ``OUTDIR/results.json``: every map variant under
    the map-only protocol (sequences and single frames) and the paper protocol."""
    res = json.loads((outdir / "results.json").read_text())
    from memlog.evaluation.analysis import MAP_ROWS

    names = {**MAP_ROWS, "memorable": "memorable (the map `memlog map` writes)"}.items()
    lines = ["| map | frames | coverage | R@1 | R@5 | AUC-PR | R@1 single frames | AUC single frames | paper R@1 "
             "| paper AUC |", "|---|---|---|---|---|---|---|---|---|---|"]
    for key, label in names:
        row = res.get(key)
        if not isinstance(row, dict):
            continue
        sf = row.get("single_frame") or {}
        pp = row.get("paper_protocol") or {}
        std = row.get("std") or {}

        def g(d: dict[str, Any], k: str, s: dict[str, Any] | None = None) -> str:
            v = d.get(k)
            if s and k in s and v is not None:
                return f"{v:.3f} ± {s[k]:.3f}"
            return _f(v)

        if key == "random":
            label += f" ({row.get('seeds', len(row.get('per_seed', [])) or '?')} seeds)"
        lines.append(f"| {label} | {_frames(row)} | {g(row, 'coverage', std)} | {g(row, 'recall@1', std)} | "
                     f"{g(row, 'recall@5', std)} | {g(row, 'auc', std)} | {g(sf, 'recall@1', sf.get('std'))} | "
                     f"{g(sf, 'auc', sf.get('std'))} | {g(pp, 'recall@1', pp.get('std'))} | "
                     f"{g(pp, 'auc', pp.get('std'))} |")
    desc = res.get("descriptor") or {}
    match = res.get("matching") or {}
    notes = []
    if desc:
        notes.append(f"descriptor {desc.get('chosen') or desc.get('kind') or desc}")
    if isinstance(match, dict) and match:
        seq: dict[str, Any] = match["sequence"] if isinstance(match.get("sequence"), dict) else {}
        how = [str(match.get("matching", ""))]
        how += [f"{k} {seq[k]}" for k in ("length", "speed_prior", "candidates", "rerank") if k in seq]
        if "coordinate" in match:
            how.append(f"along {match['coordinate']}")
        notes.append("matched by " + ", ".join(h for h in how if h))
        if match.get("fallback"):
            notes.append(f"note: {match['fallback']}")
    if "seconds" in res:
        notes.append(f"{res['seconds']:.0f} s")
    return "\n".join(lines) + ("\n\n(" + "; ".join(notes) + ")" if notes else "")


def reuse_scores(outdir: Path, scores: Path | None) -> None:
    """Give ``memlog evaluate`` the summer drive's scores (it reuses ``OUTDIR/reference.scored.mcap``
    when it was made from the same log with the same settings, and scores again otherwise)."""
    if scores is not None and scores.exists():
        target = outdir / "reference.scored.mcap"
        try:
            os.link(scores, target)
        except OSError:
            shutil.copyfile(scores, target)


# -- the benchmarks -------------------------------------------------------------------------------
BENCHES: list[Bench] = [
    Bench("evaluate_stromovka",
          ("memlog", "-q", "evaluate", "--reference", "{shared}/stromovka_autumn.mcap",
           "--query", "{shared}/stromovka_winter.mcap", "--truth", "{shared}/stromovka_truth.json",
           "-o", "{work}/evaluate-stromovka"),
          "`memlog evaluate` with the defaults on Stromovka (1024x384 colour, autumn map, winter query, 101 places, "
          "truth +-1 place): full, memorable and baseline maps of the same size, map-only and paper protocol",
          15, ("shared", "models"), summarise_evaluate, "evaluate-stromovka", "results-on-the-shared-data"),
    Bench("evaluate_nordland",
          ("memlog", "-q", "evaluate", "--reference", "{shared}/nordland_dev_summer.mcap",
           "--query", "{shared}/nordland_dev_winter.mcap", "--truth", "{shared}/nordland_dev_truth.json",
           "-o", "{work}/evaluate-nordland"),
          "`memlog evaluate` with the defaults on Nordland (64x32 grey, summer map, winter query, 800 places, truth "
          "+-1 place); the summer drive's scores are reused from --scores",
          15, ("shared", "models", "scores"), summarise_evaluate, "evaluate-nordland", "results-on-the-shared-data",
          prepare=lambda out, scores: reuse_scores(out, scores)),
    Bench("matcher_defaults",
          ("python", "benchmarks/matcher_defaults.py", "--variants", "--cache", "{work}/matcher-defaults"),
          "the drive matcher's defaults against single frames and other settings: Stromovka (DINOv2, whitened) and "
          "Nordland (whitened thumbnail), maps written by `memlog map`, and the Nordland drive variants",
          40, ("shared", "models"), defaults_anchor="the-drive-matcher-localize-evaluate"),
    Bench("rerank_table",
          ("python", "benchmarks/rerank_table.py", "--cache", "{work}/matcher-defaults"),
          "patch re-ranking, the drive HMM and its whitening ensemble on the drive matcher's best places: Stromovka, "
          "frame-aligned and as drives with stops (full, half and default maps), Nordland",
          15, ("shared", "models")),
    Bench("drive_pair",
          ("python", "benchmarks/drive_pair.py", "--cache", "{work}/drive-pair"),
          "maps of every size through `memlog evaluate` (every row a map `memlog map` writes, matched as `memlog "
          "localize` matches it), with and without the whitening ensemble: the Stromovka pair, the Stromovka drive pair "
          "with stops, crawls and fast stretches, Nordland, and the drive pair with odometry on its map drive; half "
          "maps and memlog's default size",
          20, ("shared", "models"), defaults_anchor="drives-as-cameras-record-them"),
    Bench("drive_pair_candidates",
          ("python", "benchmarks/drive_pair.py", "--cache", "{work}/drive-pair", "--table", "candidates", "--pairs",
           "drive", "aligned", "--keep", "0.5"),
          "does memorability (ResMem) choose better map frames than the cheap rule at camera resolution? The memorable "
          "map of the Stromovka drive pair and the frame-aligned pair at half size with `--candidates 1` (default: no ResMem), `2` and `all`, "
          "and exact without MS",
          70, ("shared", "models"), defaults_anchor="does-memorability-help-choose-within-a-segment"),
    Bench("whitening_spread",
          ("python", "benchmarks/whitening_spread.py", "--cache", "{work}/matcher-defaults"),
          "how far a map's R@1 moves with the frames its whitening is fitted on (8 refits on 85 % samples of the map's "
          "own frames), matched once and with the whitening ensemble (also over the query's moving frames, a stop "
          "once): the Stromovka pairs (the drive pair also with odometry on its map drive), full, default, half and "
          "quarter maps",
          10, ("shared", "models"), defaults_anchor="the-whitening-ensemble"),
    Bench("map_spread",
          ("python", "benchmarks/map_spread.py", "--cache", "{work}/map-spread"),
          "maps of every size over every shared pair (Stromovka frame-aligned and drive pair, Nordland dev and two "
          "drive variants), one whitening per drive: the full map, memlog's default and half maps, every k-th "
          "frame from every start offset and 10 random maps of each size, R@1 mean, std, min and max",
          25, ("shared", "models")),
    Bench("map_spread_kept",
          ("python", "benchmarks/map_spread.py", "--cache", "{work}/map-spread", "--whiten", "kept"),
          "the same maps, each whitened on its own kept frames (memlog before one whitening per drive)",
          25, ("shared", "models")),
    Bench("matcher_stages",
          ("python", "benchmarks/map_spread.py", "--cache", "{work}/map-spread", "--stages"),
          "every stage and option of the drive matcher on and off over every shared pair (the memorable and every "
          "k-th maps of every offset, default and half size): the mean gain over the pairs and its spread",
          60, ("shared", "models")),
    Bench("drive_maps",
          ("python", "benchmarks/drive_maps.py", "--scores", "{scores}", "--cache", "{work}/drive-maps"),
          "maps of Nordland drive variants that stop, crawl and speed up: memlog's map against every k-th frame and "
          "random maps, three query drives; the candidates table (does memorability help choose?)",
          40, ("shared", "models", "scores"), defaults_anchor="maps-of-drives-that-stop-crawl-and-speed-up"),
    Bench("selection_table",
          ("python", "benchmarks/selection_table.py", "--out", "{work}/selection"),
          "selection modes (paper rule, calibrated; segment) against uniform and random maps on Nordland",
          70, ("shared", "models"), defaults_anchor="selection-modes-against-baselines-of-the-same-size"),
    Bench("shortlist_table",
          ("python", "benchmarks/shortlist_table.py", "--scores", "{scores}"),
          "`--candidates K` shortlists against exact staged selection on Nordland (single frames)",
          10, ("shared", "models", "scores"), defaults_anchor="shortlists---candidates-k"),
    Bench("desc_table",
          ("python", "benchmarks/desc_table.py", "--scores", "{scores}", "--cache", "{work}/desc-table"),
          "descriptor kinds x whitening, selection with distinctiveness, the paper protocol's readings (Nordland)",
          40, ("shared", "models", "scores"), defaults_anchor="descriptors-and-whitening"),
    Bench("sequence_table",
          ("python", "benchmarks/sequence_table.py", "--cache", "{work}/sequence-table"),
          "sequence against single-frame matching on Nordland drive variants, and its cost at 10^4 and 10^5 frames",
          15, ("shared", "models")),
    Bench("descriptor_choices",
          ("python", "benchmarks/descriptor_choices.py", "--cache", "{work}/descriptor-choices"),
          "descriptor choices at camera resolution (input, pooling, layers, scales, whitening) on Stromovka, "
          "single frames, sequences and sequences with patch re-ranking; Nordland beside it",
          15, ("shared", "models")),
    Bench("speed_table",
          ("python", "benchmarks/speed_table.py", "--work", "{work}/speed"),
          "frames per second of `memlog map`, `score`, `score --fast` and `evaluate` at camera resolution "
          "(Stromovka and a 1010-frame drive made from it), peak memory and where the time goes",
          45, ("shared", "models")),
    Bench("matcher_cost",
          ("python", "benchmarks/matcher_cost.py"),
          "the drive matcher's time per query and peak memory on synthetic maps of 10^4 and 10^5 frames at "
          "several sparsities",
          8),
    Bench("map_end_to_end",
          ("python", "benchmarks/run.py", "map", "--map-stride", "8", "--map-variants", "all-scores", "K1",
           "K1-score-kept", "K2", "staged"),
          "`memlog map` end to end on every 8th Nordland summer frame: all scores, the default (`--candidates 1`), "
          "`--score-kept`, `--candidates 2`, exact staged selection",
          30, ("shared", "models")),
    Bench("scorer",
          ("python", "benchmarks/run.py", "score", "--frames", "12"),
          "the scorer per stage: paper-literal against exact and fast mode, at the paper's thresholds, at MT 0.5 "
          "alone and in a stress setting (EuRoC and Nordland, 12 frames each)",
          25, ("shared", "models")),
    Bench("threads",
          ("python", "benchmarks/run.py", "threads"),
          "fp32 ResMem per crop: 1 thread, 2 threads, two 1-thread processes",
          3, ("models",)),
    Bench("io",
          ("python", "benchmarks/run.py", "io"),
          "reading and decoding every frame, `memlog convert`, and memory against log size (shared logs)",
          6, ("shared",)),
    Bench("descriptors",
          ("python", "benchmarks/run.py", "descriptors"),
          "descriptor extraction and matching on Nordland: R@N, AUC, ms per image and per query",
          15, ("shared", "models")),
    Bench("search",
          ("python", "benchmarks/run.py", "search"),
          "localization against a synthetic 100,000-frame map from Nordland thumbnails: exact and IVF search "
          "(builds ~1.1 GB in /tmp once)",
          15, ("shared",)),
    Bench("batch",
          ("python", "benchmarks/batch_bench.py"),
          "`memlog batch` on the three EuRoC logs: one process, local workers, Ray",
          25, ("shared", "models")),
    Bench("ms_probe",
          ("python", "benchmarks/ms_probe.py", "--cache", "{work}/ms-probe.npz"),
          "can a linear probe on the DINOv2 descriptor stand in for ResMem? (scikit-image photos)",
          12, ("models",)),
    Bench("resmem_flops",
          ("python", "benchmarks/resmem_flops.py"),
          "ResMem's cost per crop counted from its ONNX graph, and frames/s per GPU at a few sustained throughputs",
          1, ("models",)),
    Bench("record_codecs",
          ("python", "benchmarks/record_codecs.py", "3000"),
          "score record size and encode/decode cost per encoding family",
          1),
    Bench("video_decode",
          ("python", "benchmarks/video_decode.py"),
          "what a video camera topic costs to read: H.264 against JPEG at 960x540, per frame read",
          2, ("shared",)),
    Bench("read_count",
          ("python", "benchmarks/read_count.py", "--work", "{work}/reads"),
          "how many times `map`, `map --workers 2` and `batch` read a damaged and an unfinished log (bytes read from "
          "it over its size, and opens, under strace; and the bytes the job's spool wrote and read back)",
          8, ("shared",)),
    Bench("gpu_check",
          ("python", "benchmarks/gpu_check.py", "--smoke", "--work", "{work}/gpu"),
          "the GPU path: `score`, `map` and `localize` on CUDA against the CPU (frames/s, the provider each model "
          "runs on, agreement); without a GPU, the CPU fallback",
          2, ("shared",)),
    Bench("mcap_conformance",
          ("python", "benchmarks/mcap_conformance.py"),
          "the official MCAP conformance corpus (416 valid files) through the reader, `inspect` and `convert`, per "
          "feature combination",
          1, ("shared",)),
    Bench("damage_sweep",
          ("python", "benchmarks/damage_sweep.py"),
          "hundreds of damaged or wrong copies of the fixtures and shared logs through the readers, `inspect` and "
          "`convert`",
          20, ("shared",)),
]
BY_NAME = {b.name: b for b in BENCHES}
#: the short line of each benchmark in the page's list of sections
TITLES = {
    "evaluate_stromovka": "`memlog evaluate`, Stromovka (camera resolution)",
    "evaluate_nordland": "`memlog evaluate`, Nordland 64x32",
    "matcher_defaults": "the drive matcher's defaults",
    "rerank_table": "patch re-ranking",
    "drive_pair": "maps of every size on drives as cameras record them",
    "drive_pair_candidates": "does memorability choose better frames at camera resolution?",
    "whitening_spread": "a map's R@1 over refitted whitenings; the whitening ensemble",
    "map_spread": "maps of every size over every shared pair, one whitening per drive",
    "map_spread_kept": "the same maps, each whitened on its own kept frames (before)",
    "matcher_stages": "does every matcher stage earn its keep?",
    "drive_maps": "maps of drives that stop, crawl and speed up",
    "selection_table": "selection modes against baselines",
    "shortlist_table": "`--candidates K` shortlists",
    "desc_table": "descriptors x whitening; the paper's readings",
    "sequence_table": "sequences against single frames",
    "descriptor_choices": "descriptor choices at camera resolution",
    "speed_table": "frames per second at camera resolution",
    "matcher_cost": "the drive matcher's time and memory",
    "map_end_to_end": "`memlog map` end to end",
    "scorer": "the scorer per stage and mode",
    "threads": "ResMem: threads against processes",
    "io": "reading, decoding, converting",
    "descriptors": "descriptor extraction and matching",
    "search": "search in a 100,000-frame map",
    "batch": "`memlog batch`: processes and Ray",
    "ms_probe": "a memorability probe on DINOv2",
    "resmem_flops": "ResMem's FLOPs and GPU throughput",
    "record_codecs": "score record codecs",
    "video_decode": "video camera topics: decoding H.264 against JPEG",
    "read_count": "reads of a damaged or unfinished log per job",
    "gpu_check": "the GPU path and its CPU fallback",
    "mcap_conformance": "the MCAP conformance corpus",
    "damage_sweep": "the damage sweep",
}

#: scripts in benchmarks/ that are not a section of their own: a library of drive variants, this
#: script, and the scripts ``run.py search`` and ``run.py descriptors`` run
NOT_SECTIONS = ("drives.py", "make_docs.py", "search_bench.py", "descriptor_recall.py")

SCORES_ARGV = ("memlog", "score", "{shared}/nordland_dev_summer.mcap", "--all-scores", "-o", "{scores}")


# -- the page ------------------------------------------------------------------------------------
BEGIN = "<!-- begin section: {} -->"
END = "<!-- end section: {} -->"
_SECTION = re.compile(r"<!-- begin section: ([\w-]+) -->\n(.*?)<!-- end section: \1 -->", re.S)
_STATUS = re.compile(r"<!-- status: (.*?) -->")


def read_sections(page: Path) -> dict[str, str]:
    """The sections of an existing page, by benchmark name (each as it stands between its markers)."""
    if not page.exists():
        return {}
    return {m.group(1): m.group(2) for m in _SECTION.finditer(page.read_text())}


def status_of(body: str) -> str:
    m = _STATUS.search(body)
    return m.group(1) if m else "not run yet"


def placeholder(b: Bench) -> str:
    lines = [f'<a id="{b.name}"></a>', f"## `{b.heading()}`", "", f"*Measures:* {b.what}.", "",
             "<!-- status: not run yet -->",
             f"*Not run by this script yet* (`python benchmarks/make_docs.py --only {b.name}`, about "
             f"{b.minutes:g} min on two cores)."]
    if b.defaults_anchor:
        lines.append(f"The figures recorded when the defaults were chosen are in "
                     f"[defaults.md](defaults.md#{b.defaults_anchor}).")
    return "\n".join(lines) + "\n"


def _git() -> str:
    try:
        sha = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                             check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=ROOT,
                               capture_output=True, text=True, check=False).stdout.strip()
        return sha + (" with local changes" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def _cpu() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return "unknown CPU"


def machine() -> str:
    from memlog import __version__

    return f"memlog {__version__} (git {_git()}), {os.cpu_count()} cores ({_cpu()}), Python {sys.version.split()[0]}"


def as_markdown(text: str) -> str:
    """A script's output as the section's content: Markdown as it is when it holds a Markdown table,
    else in a text block."""
    text = text.rstrip() + "\n"
    if re.search(r"^\|[-:| ]+\|\s*$", text, re.M):
        return text
    return "```text\n" + text + "```\n"


def section(b: Bench, output: str, seconds: float, load: tuple[float, float], when: str, host: str) -> str:
    status = f"run {when}"
    return "\n".join([
        f'<a id="{b.name}"></a>', f"## `{b.heading()}`", "", f"*Measures:* {b.what}.", "",
        f"<!-- status: {status} -->",
        f"*Run* {when} in {seconds / 60:.1f} min; {host}; load average {load[0]:.1f} before, {load[1]:.1f} after "
        "(the machine may be shared: times are upper bounds, ratios within a table mean more).", "",
        as_markdown(output)])


HEADER = """# Benchmarks

<!-- Generated by `python benchmarks/make_docs.py`: do not edit by hand; re-run it (see --help). -->

This page is written by one command, `python benchmarks/make_docs.py`: each section below is the output of
the command in its heading, run by that script on the machine and at the time the section names
(`--only NAME` re-runs one section, `--quick` the ones of a few minutes, `--cached` rebuilds the page
without running anything; `--list` shows every benchmark and its rough time). `$WORK` is the script's
scratch directory (`--work`, default `/tmp/memlog-make-docs`); `../shared/data` is the shared data
(`$MEMLOG_SHARED_DATA`). The figures the defaults were chosen on, recorded when each default was chosen,
are in [defaults.md](defaults.md); the headline results are in the [README](../README.md#headline-results).

| section | measures | status |
|---|---|---|
"""


def render(sections: dict[str, str]) -> str:
    rows = []
    body = []
    for b in BENCHES:
        text = sections.get(b.name) or placeholder(b)
        rows.append(f"| [{b.name}](#{b.name}) | {TITLES.get(b.name, b.name)} | {status_of(text)} |")
        body.append(BEGIN.format(b.name) + "\n" + text.rstrip("\n") + "\n" + END.format(b.name))
    extra = [f"{BEGIN.format(n)}\n{t.rstrip()}\n{END.format(n)}" for n, t in sections.items() if n not in BY_NAME]
    if extra:  # a section of a benchmark no longer listed: kept at the end, for a human to remove
        body += extra
    return HEADER + "\n".join(rows) + "\n\n" + "\n\n".join(body) + "\n"


def write_atomic(path: Path, text: str) -> None:
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, path.stat().st_mode & 0o777 if path.exists() else 0o666 & ~umask)  # mkstemp makes 0600
        with os.fdopen(fd, "w") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


# -- running ---------------------------------------------------------------------------------------
def missing(b: Bench) -> str | None:
    """Why ``b`` cannot run here, or None."""
    if "shared" in b.needs and not SHARED.exists():
        return f"the shared data is not at {SHARED} (set $MEMLOG_SHARED_DATA)"
    return None


def run_bench(b: Bench, work: Path, scores: Path | None) -> tuple[str, float, tuple[float, float]]:
    """Run ``b``; its output (Markdown), wall time and load averages before and after."""
    argv = b.command(work, scores)
    out_dir = work / b.outdir if b.outdir else None
    if out_dir is not None:
        shutil.rmtree(out_dir, ignore_errors=True)
        out_dir.mkdir(parents=True)
        if b.prepare is not None:
            b.prepare(out_dir, scores)
    load0 = os.getloadavg()[0]
    t0 = time.perf_counter()
    print(f"make_docs: {b.name}: {shlex.join(argv)}", file=sys.stderr, flush=True)
    proc = subprocess.run(argv, cwd=ROOT, stdout=subprocess.PIPE, text=True, check=False)
    seconds = time.perf_counter() - t0
    if proc.returncode not in (0, 3):
        raise RuntimeError(f"{b.name}: exit status {proc.returncode}")
    output = b.summarise(out_dir) if b.summarise is not None and out_dir is not None else proc.stdout
    return output, seconds, (load0, os.getloadavg()[0])


def ensure_scores(work: Path, scores: Path | None, dry_run: bool) -> Path:
    path = scores or work / "nordland_summer.scored.mcap"
    if path.exists():
        return path
    argv = [sys.executable, "-m", "memlog", *[a.replace("{shared}", str(SHARED)).replace("{scores}", str(path))
                                               for a in SCORES_ARGV[1:]]]
    print(f"make_docs: every score of the Nordland summer drive (about an hour on two cores): {shlex.join(argv)}",
          file=sys.stderr, flush=True)
    if not dry_run:
        subprocess.run(argv, cwd=ROOT, check=True)
    return path


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(prog="python benchmarks/make_docs.py", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    pick = ap.add_mutually_exclusive_group()
    pick.add_argument("--only", nargs="+", metavar="NAME", choices=list(BY_NAME),
                      help="run only these benchmarks (names: --list); the other sections are kept as they are")
    pick.add_argument("--quick", action="store_true",
                      help=f"run only the benchmarks of at most {QUICK_MINUTES:g} minutes; keep the other sections")
    pick.add_argument("--cached", action="store_true",
                      help="run nothing: rebuild the page from the sections it already has")
    pick.add_argument("--list", action="store_true", help="list the benchmarks, their commands and rough times")
    ap.add_argument("--work", type=Path, default=WORK,
                    help="scratch directory for caches and outputs (default %(default)s or $MEMLOG_BENCH_WORK)")
    ap.add_argument("--scores", type=Path,
                    help="the Nordland summer drive scored with `memlog score --all-scores` (default: made once in "
                         "--work when a benchmark needs it)")
    ap.add_argument("--page", type=Path, default=PAGE, help="the page to write (default docs/benchmarks.md)")
    ap.add_argument("--dry-run", action="store_true", help="print what would run; write nothing")
    return ap.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_args(argv)
    if args.list:
        for b in BENCHES:
            print(f"{b.name:<20} ~{b.minutes:>4g} min  {b.heading()}")
        return 0
    if args.only:
        chosen = [BY_NAME[n] for n in args.only]
    elif args.quick:
        chosen = [b for b in BENCHES if b.minutes <= QUICK_MINUTES]
    elif args.cached:
        chosen = []
    else:
        chosen = list(BENCHES)
    sections = read_sections(args.page)
    runnable = []
    for b in chosen:
        why = missing(b)
        if why:
            print(f"make_docs: skipping {b.name}: {why}; its section is kept", file=sys.stderr)
        else:
            runnable.append(b)
    scores = args.scores
    if any("scores" in b.needs for b in runnable):
        scores = ensure_scores(args.work, args.scores, args.dry_run)
    if args.dry_run:
        for b in runnable:
            print(shlex.join(b.command(args.work, scores)))
        return 0
    args.work.mkdir(parents=True, exist_ok=True)
    host = machine()
    failed = []
    write_atomic(args.page, render(sections))
    for b in runnable:
        try:
            output, seconds, load = run_bench(b, args.work, scores)
        except (RuntimeError, OSError, ValueError, KeyError) as exc:
            print(f"make_docs: {b.name} failed ({exc}); its section is kept", file=sys.stderr)
            failed.append(b.name)
            continue
        when = _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
        sections[b.name] = section(b, output, seconds, load, when, host)
        write_atomic(args.page, render(sections))
        print(f"make_docs: {b.name} done in {seconds:.0f} s; wrote {args.page}", file=sys.stderr)
    if failed:
        print(f"make_docs: failed: {', '.join(failed)}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())

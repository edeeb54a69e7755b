"""Pipeline step ``evaluate``: does the memorable map help localization?

Given a reference log, a query log and ground truth (a JSON ``matches`` file, or positions in
both logs with a distance tolerance), it scores the reference as ``memlog map`` does (staged: the
detector and ResMem only where they can change the map, kept in OUT for a rerun:
:mod:`memlog.steps.score_cache`; with ``compare_exact``, every score of every frame,
``OUT/reference.scored.mcap``), describes both drives once (``OUT/{reference,query}.<kind>.parquet``)
and writes the memorable map with the map step's writer (:func:`~memlog.steps.map.make_map`, from the
scores, looks, descriptors and patch features it already has: ``OUT/map.mcap`` + ``OUT/map.parquet``,
exactly the map ``memlog map`` writes with the same settings). A map's whitening and patch PCA are
the reference drive's (fitted on its moving frames), so a map of some of the drive's frames is those
rows of the drive's one described table: the full map (every frame) and the baselines of the
memorable map's size (every k-th frame ``uniform``, and from each of its start offsets
``uniform_phases``: :func:`~memlog.selection.phase_masks`; random frames, ``seeds`` of them; each
with mean, std, min and max, and where the memorable map lies among them) are masks over that
table, matched as ``memlog localize`` matches a map of those frames (:mod:`memlog.evaluation.matching`),
under the map-only and the paper
protocol. It adds map size and matching time and, when every reference frame has every score
(``compare_exact``), the paper's threshold sweeps and the criterion contribution
(:mod:`memlog.evaluation.analysis`; otherwise each says why it is missing), and writes
``OUT/results.json`` and ``OUT/report.html``.

Outputs already in OUT are reused only when they were made from the same input (path, size,
modification time) with the same settings; the run says which it reused and which it refused.

Quick trials: ``window`` (start/end/stride, resolved per log) and ``max_frames`` restrict both
drives to part of them (every map is made of the window's frames); ``descriptors`` evaluates several
descriptors in one run (each drive is described once per descriptor and cached as
``OUT/{reference,query}.<kind>.parquet``; the memorable map of each is ``OUT/map.<kind>.mcap`` when
there are several). With ``whiten`` (the default) every map is whitened by the drive's transform and
the query with it, as ``localize`` whitens it; the unwhitened full map is reported beside it
(``full_unwhitened``).
"""

from __future__ import annotations

import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from memlog._version import __version__
from memlog.configfile import check_ints
from memlog.descriptors.auto import AUTO, resolve_descriptor
from memlog.descriptors.base import Describer
from memlog.descriptors.extract import describe_log
from memlog.descriptors.registry import DESCRIBERS, make_describer
from memlog.matching import SequenceConfig, standing_rows
from memlog.descriptors.table import DescriptorTable
from memlog.errors import ConfigError, EvaluationError, MemlogError
from memlog.evaluation.analysis import (
    MAP_ROWS, SWEEP_STEPS, among, contribution, local_positions, mean_std, position_truth, sweeps,
)
from memlog.evaluation.matching import Matching, rows_for, whitened
from memlog.evaluation.matching import truth_rows as truth_as_rows
from memlog.evaluation.metrics import PAPER_READINGS, ProtocolResult, parse_truth
from memlog.io.atomic import check_output
from memlog.io.base import FrameWindow
from memlog.io.identity import log_identity, same_identity
from memlog.io.open import open_log
from memlog.io import spool
from memlog.io.records import ReadReport
from memlog.outputs.annotated import read_scores, run_config, run_input_identity
from memlog.outputs.descriptor_table import read_cached, read_descriptors, write_descriptors
from memlog.outputs.results import write_results
from memlog.progress import info
from memlog.scoring.config import ScoreConfig
from memlog.selection import distance_uniform_mask, phase_masks, random_masks
from memlog.selection.config import DEFAULT_CANDIDATES, SelectionConfig
from memlog.settings import Flag, count_or_all, nonneg_float, positive_int, setting
from memlog.steps.map import MapConfig, MapResult, make_map, score_table, staged_stageable
from memlog.steps.score import score
from memlog.steps.score_cache import cached_staged_scores

__all__ = ["evaluate", "EvaluateConfig", "EvaluateResult", "SWEEP_STEPS"]



@dataclass(frozen=True)
class EvaluateConfig:
    """Settings of an evaluation (scoring and selection have their own typed configs).

    ``descriptor``: the VPR descriptor (``auto``: by frame size; several comma-separated names
    are evaluated one after the other, the first being the main result); ``whiten``: whiten
    with the drive's transform (fitted on its moving frames, as ``memlog map`` fits it); ``window``/``max_frames``: evaluate on part of both drives (quick
    trials; ``query_window``: the query's own time window when it differs, e.g. ``+S`` times
    resolved against each log); ``tol_m``: position truth tolerance (metres); ``k``:
    candidates per query; ``seeds``: random baselines; ``paper_discarded``: how the paper
    protocol counts a query whose best match was discarded; ``reference_topic`` /
    ``query_topic``: camera topics (default: the first); ``report``: write report.html.
    ``candidates``: the memorable map is the one ``memlog map --candidates`` writes with these
    settings; ``compare_exact``: its exact selection, ``candidates="all"``, is reported beside it
    as ``memorable_exact`` (opt-in: it scores every reference frame's memorability). ``sequence``: how query frames are matched (the localize step's
    default: sequences; ``length`` 0: single frames); every map is also evaluated frame by frame
    (``single_frame`` in each row) when sequences are on.
    """

    score: ScoreConfig = field(default_factory=ScoreConfig)
    select: SelectionConfig = field(default_factory=SelectionConfig)
    descriptor: str = setting(AUTO, Flag(
        ("--descriptor",), "auto (default: by frame size), a kind (thumbnail, dinov2-gem, ...), or several "
        "comma-separated (each described once and cached; one table)", "comparisons", metavar="KIND[,KIND...]"))
    whiten: bool = setting(True, Flag(("--no-whiten",), "evaluate unwhitened maps (default: whitened)",
                                      "comparisons", action="store_true", value=lambda v: False))
    window: FrameWindow = FrameWindow()
    query_window: FrameWindow | None = None
    max_frames: int | None = setting(None, Flag(("--max-frames",), "at most this many frames of each drive",
                                                "inputs", positive_int, metavar="N"))
    tol_m: float = setting(25.0, Flag(("--tolerance",), "position truth: metres (default 25)", check=nonneg_float,
                                      metavar="M"))
    k: int = 10
    seeds: int = setting(20, Flag(("--seeds",), "random baseline seeds (default 20)", "comparisons", positive_int,
                                  metavar="N"))
    paper_discarded: Literal["false_negative", "true_negative", "uncovered_negative"] = setting(
        "false_negative", Flag(
            ("--paper-discarded",), "(experimental) paper protocol: how a query whose best match was discarded "
            "counts (default false_negative; true_negative drops it from the positives; uncovered_negative drops the "
            "queries with no true place in the map instead)", "experimental",
            choices=("false_negative", "true_negative", "uncovered_negative")))
    reference_topic: str | None = setting(None, Flag(
        ("--reference-topic",), "reference camera topic (default: the first)", "inputs", metavar="TOPIC"))
    query_topic: str | None = setting(None, Flag(("--query-topic",), "query camera topic (default: the first)",
                                                 "inputs", metavar="TOPIC"))
    report: bool = setting(True, Flag(("--no-report",), "skip the HTML report (an older one in OUTDIR is removed)",
                                      "outputs", action="store_true", value=lambda v: False))
    candidates: int | Literal["all"] = setting(DEFAULT_CANDIDATES, Flag(
        ("--candidates",), "the memorable map is the one `memlog map --candidates K` writes (default "
        f"{DEFAULT_CANDIDATES})", "selection", count_or_all, metavar="K|all"))
    sequence: SequenceConfig = SequenceConfig()
    compare_exact: bool = setting(False, Flag(
        ("--compare-exact",), "also evaluate the exact selection (every reference frame's memorability scored; "
        "slower)", "comparisons", action="store_true"))

    def __post_init__(self) -> None:
        if not isinstance(self.sequence, SequenceConfig):
            raise ConfigError(f"sequence must be a SequenceConfig, got {self.sequence!r}")
        MapConfig(candidates=self.candidates)  # checks the value
        names = self.descriptors
        bad = [n for n in names if n != AUTO and n not in DESCRIBERS]
        if bad or not names or len(set(names)) != len(names):
            raise ConfigError(f"descriptor must be auto or one of {', '.join(sorted(DESCRIBERS))} (several: comma-"
                              f"separated, each once), got {self.descriptor!r}")
        check_ints(self, {"max_frames": 1}, optional=True)
        if self.window.topics is not None or (self.query_window is not None and self.query_window.topics):
            raise ConfigError("window: give topics with reference_topic / query_topic")
        if not (isinstance(self.tol_m, (int, float)) and np.isfinite(self.tol_m) and self.tol_m >= 0):
            raise ConfigError(f"tolerance must be a number >= 0 (metres), got {self.tol_m!r}")
        check_ints(self, {"k": 1, "seeds": 1})
        if self.paper_discarded not in PAPER_READINGS:
            raise ConfigError(f"paper_discarded must be one of {', '.join(PAPER_READINGS)}, got "
                              f"{self.paper_discarded!r}")

    @property
    def descriptors(self) -> list[str]:
        """The descriptor names of ``descriptor`` (comma-separated), in order."""
        return [n.strip() for n in str(self.descriptor).split(",") if n.strip()]

    def options(self) -> dict[str, Any]:
        """The settings other than scoring and selection, JSON-ready."""
        out = {k: v for k, v in asdict(self).items()
               if k not in ("score", "select", "window", "query_window", "sequence")}
        out["sequence"] = self.sequence.to_dict()
        out["window"] = self.window.to_dict()
        out["query_window"] = self.query_window.to_dict() if self.query_window else None
        return out


@dataclass
class EvaluateResult:
    """What ``results.json`` holds (``results``; also indexable: ``res["memorable"]``) and the
    read reports of the logs read in this run (damage found)."""

    results: dict[str, Any]
    reports: list[ReadReport] = field(default_factory=list)

    def __getitem__(self, key: str) -> Any:
        return self.results[key]


def _matching(q_t: DescriptorTable, ref_t: DescriptorTable, cfg: EvaluateConfig) -> Matching:
    """How the query is matched and scored against a map in the space of ``q_t`` / ``ref_t``."""
    return Matching(q_t, ref_t, cfg.sequence, cfg.k, cfg.paper_discarded)


def _reuse_scores(path: Path, reference: str, cfg: ScoreConfig, topic: str | None,
                  window: FrameWindow | None = None) -> bool:
    """Whether OUT/reference.scored.mcap was made from this reference log with this config
    (and, when ``window`` is given, holds a score for every frame of it)."""
    if not path.is_file():
        return False
    try:
        used = run_config(path)
        ident = run_input_identity(path)
    except MemlogError as exc:  # an unreadable cache is simply not reused
        info(f"not reusing {path}: it does not read ({exc})")
        return False
    if not same_identity(ident, reference):
        info(f"not reusing {path}: it was scored from another reference log (or {reference} changed)")
        return False
    if used is None or used.replace(threads=0, device="auto") != cfg.replace(threads=0, device="auto"):
        info(f"not reusing {path}: it was scored with other settings")
        return False
    if topic is not None and topic not in read_scores(path):
        info(f"not reusing {path}: it has no scores for {topic}")
        return False
    if window is not None and topic is not None:
        have = {r["frame_index"] for r in read_scores(path)[topic]}
        with open_log(reference) as reader:
            need = {f.index for f in reader.frames([topic], window.start_ns, window.end_ns, window.stride)}
        if not need <= have:
            info(f"not reusing {path}: it lacks scores of {len(need - have)} frame(s) of the window")
            return False
    info(f"reusing {path} (same reference log and scoring settings)")
    return True


def _described(log: str, path: Path, describer: Describer, window: FrameWindow, reports: list[ReadReport],
               still_distance: float, scores: dict[str, dict[int, dict[str, Any]]] | None = None) -> DescriptorTable:
    """Descriptors of ``log``, stops found with ``still_distance`` (cached at ``path`` when made
    from the same log, window, describer and stop rule)."""
    cached = read_cached(path, log, describer.meta(), window, still_distance, patches=describer.gives_patches)
    if cached is not None:
        return cached
    t, report = describe_log(log, describer, window, scores=scores, still_distance=still_distance)
    reports.append(report)
    write_descriptors(path, t)
    return t


def _frame_counts(log: str, topic: str | None) -> tuple[str, int | None]:
    """The camera topic evaluated in ``log`` and its number of frames (from the index)."""
    with open_log(log) as reader:
        t = reader.check_camera_topics([topic] if topic else None)[0]
        return t, reader.count_frames(FrameWindow((t,)))


def _trial_window(log: str, topic: str, window: FrameWindow, max_frames: int | None) -> FrameWindow:
    """``window`` on ``topic``, ending after its first ``max_frames`` frames when given."""
    w = FrameWindow((topic,), window.start_ns, window.end_ns, window.stride)
    if max_frames is None:
        return w
    with open_log(log) as reader:
        last = None
        for n, frame in enumerate(reader.frames([topic], w.start_ns, w.end_ns, w.stride)):
            last = frame.log_time_ns
            if n + 1 >= max_frames:
                break
    if last is None:
        raise EvaluationError(f"{log}: no frame of {topic} in the window --start/--end")
    return FrameWindow((topic,), w.start_ns, last + 1, w.stride)


def _check_truth_fits(truth: list[set[int]], source: str, n_query: int | None, n_ref: int | None) -> None:
    """Refuse a truth file whose length or indices do not fit the logs (before any scoring)."""
    if n_query is not None and len(truth) != n_query:
        raise EvaluationError(f"--truth {source}: \"matches\" has {len(truth)} entries but the query topic has "
                              f"{n_query} frames (one entry per query frame)")
    if n_ref is not None:
        for q, s in enumerate(truth):
            bad = [i for i in s if i >= n_ref]
            if bad:
                raise EvaluationError(f"--truth {source}: matches[{q}] names reference frame {min(bad)}, but the "
                                      f"reference topic has {n_ref} frames (0..{n_ref - 1})")
    if not any(truth):
        raise EvaluationError(f"--truth {source}: no query has a true match; every metric would be 0")


@dataclass
class _Run:
    """One evaluation's inputs, checked, and what its steps share: the settings, both drives'
    camera topics and windows, the output directory, the truth (frames, and where it came from),
    the reference's score records and looks, and every read report."""

    cfg: EvaluateConfig
    score_cfg: ScoreConfig
    reference: str
    query: str
    out: Path
    ref_topic: str
    q_topic: str
    ref_window: FrameWindow
    q_window: FrameWindow
    truth: str | None
    truth_frames: list[set[int]] | None
    reports: list[ReadReport] = field(default_factory=list)
    looks: Any = None
    score_by_frame: dict[str, dict[int, dict[str, Any]]] = field(default_factory=dict)


def evaluate(
    reference: str | os.PathLike[str],
    query: str | os.PathLike[str],
    out_dir: str | os.PathLike[str],
    config: EvaluateConfig | None = None,
    *,
    truth: str | os.PathLike[str] | None = None,
) -> EvaluateResult:
    """Run the evaluation (see module doc); returns what is written to ``results.json``."""
    t_start = time.perf_counter()
    run = _checked(str(reference), str(query), out_dir, config or EvaluateConfig(), truth)
    with spool.job(run.reference), spool.job(run.query):  # (each chunk read from a log once: memlog.io.spool)
        return _evaluated(run, t_start)


def _evaluated(run: _Run, t_start: float) -> EvaluateResult:
    """:func:`evaluate` after its checks."""
    cfg = run.cfg
    with open_log(run.reference) as reader:
        choices = [resolve_descriptor(name, reader, run.ref_topic) for name in cfg.descriptors]
    kinds = list(dict.fromkeys(c.chosen for c in choices))
    describers = {kind: make_describer(kind) for kind in kinds}
    run.out.mkdir(exist_ok=True)  # (an earlier run's results.json stays until this run's replaces it)
    _score_reference(run)
    results: dict[str, Any] = {"memlog_version": __version__}
    by_kind: dict[str, dict[str, Any]] = {}
    main: tuple[Any, ...] | None = None
    for choice in choices:
        kind = choice.chosen
        if kind in by_kind:
            by_kind[kind].setdefault("requested_as", []).append(choice.requested)
            continue
        by_kind[kind], first = _evaluate_kind(run, choice, describers[kind], len(kinds) > 1)
        main = main or first
    assert main is not None
    (choice, describer, ref_t, matching, truth_rows, table, sel, per_variant, map_res, truth_src) = main
    first_kind = by_kind[choice.chosen]
    for name in MAP_ROWS:
        if name in first_kind:
            results[name] = first_kind[name]
    results["matching"] = first_kind["matching"]
    results["descriptor"] = choice.to_dict()
    results["whitening"] = first_kind["whitening"]
    results["descriptors"] = by_kind
    _analyses(results, cfg, table, matching, truth_rows, sel, per_variant)
    results["map_size"] = map_res.to_dict()
    results["map_size"].pop("topics", None)
    results["truth"] = truth_src
    results["settings"] = _settings(run, describer)
    results["seconds"] = round(time.perf_counter() - t_start, 1)
    if cfg.report:
        from memlog.outputs.report import write_report

        write_report(run.out / "report.html", results, table, sel, per_variant, ref_t, run.reference, run.ref_topic,
                     query=run.query, query_topic=run.q_topic, query_table=matching.q_t, truth=truth_rows)
    else:
        (run.out / "report.html").unlink(missing_ok=True)  # never leave an older report beside new results
    write_results(run.out / "results.json", results)  # last: results.json is there only for a finished run
    if map_res.report is not None:
        run.reports.append(map_res.report)
    return EvaluateResult(results, run.reports)


def _checked(reference: str, query: str, out_dir: str | os.PathLike[str], cfg: EvaluateConfig,
             truth: str | os.PathLike[str] | None) -> _Run:
    """Everything a user can get wrong, checked before the reference is scored: the output
    directory, the camera topics, the truth file and that it fits both drives, the windows."""
    out = check_output(out_dir, [reference, query] + ([truth] if truth else []), directory=True)
    ref_topic, n_ref = _frame_counts(reference, cfg.reference_topic)
    q_topic, n_q = _frame_counts(query, cfg.query_topic)
    truth_frames: list[set[int]] | None = None
    if truth is not None and not Path(truth).is_file():
        raise ConfigError(f"--truth {truth}: no such file")
    if truth is not None:
        truth_frames = parse_truth(truth)
        _check_truth_fits(truth_frames, str(truth), n_q, n_ref)
    ref_window = _trial_window(reference, ref_topic, cfg.window, cfg.max_frames)
    q_window = _trial_window(query, q_topic, cfg.query_window or cfg.window, cfg.max_frames)
    return _Run(cfg, cfg.score.replace(all_scores=True), reference, query, out, ref_topic, q_topic, ref_window,
                q_window, None if truth is None else str(truth), truth_frames)


def _score_reference(run: _Run) -> None:
    """Score the reference drive. By default as `memlog map` scores it (staged: the detector and
    ResMem only where they can change the map; the scores not computed are null in the records), so
    the memorable map costs what the map step costs. With --compare-exact (the exact selection needs
    every MS), or settings the staged selection does not serve, every score of every frame
    (OUT/reference.scored.mcap, reused when it matches)."""
    cfg = run.cfg
    staged_cfg = MapConfig(score=cfg.score, select=cfg.select, topics=(run.ref_topic,), descriptor=None,
                           candidates=cfg.candidates)
    if not cfg.compare_exact and staged_stageable(staged_cfg):
        staged_recs, run.looks, staged_report = cached_staged_scores(run.out, "reference", run.reference, staged_cfg,
                                                                     run.ref_window)
        if staged_report is not None:
            run.reports.append(staged_report)
        recs = staged_recs.get(run.ref_topic, [])
    else:
        scored = run.out / "reference.scored.mcap"
        if not _reuse_scores(scored, run.reference, run.score_cfg, run.ref_topic, run.ref_window):
            run.reports.append(score(run.reference, scored, run.score_cfg, run.ref_window).report)
        recs = read_scores(scored)[run.ref_topic]
    run.score_by_frame = {run.ref_topic: {r["frame_index"]: r for r in recs}}


def _truth_rows(run: _Run, ref_t: DescriptorTable, q_t: DescriptorTable) -> tuple[list[set[int]], str]:
    """The ground truth as descriptor rows, and where it came from (the file, or both drives'
    positions within the tolerance)."""
    if run.truth_frames is not None:
        truth_src = str(run.truth)
        tf = run.truth_frames
    else:
        tf = position_truth(ref_t, q_t, run.cfg.tol_m)
        truth_src = f"positions within {run.cfg.tol_m} m"
    n_ref_rows = int(ref_t.frame_index.max()) + 1
    ref_rows = rows_for(ref_t, max(n_ref_rows, max((max(x) + 1 for x in tf if x), default=0)))
    truth_rows = truth_as_rows(tf, q_t, ref_rows)
    if not any(truth_rows):
        raise EvaluationError("no query frame in the window has a true match among the reference frames in it")
    return truth_rows, truth_src


def _evaluate_kind(run: _Run, choice: Any, describer: Describer, several: bool) -> tuple[dict[str, Any], tuple[Any, ...]]:
    """Every map of the comparison with one descriptor kind, and what the analyses of the main kind
    need. The memorable map is written by the map step's writer (`make_map`: exactly the map `memlog
    map` writes) from the scores and descriptors evaluate already has; its whitening and patch PCA
    are the reference drive's (fitted on its moving frames), so every other map of the drive (the
    full map, every k-th frame from each start offset, random frames) is a mask over the drive's
    one described table, matched as `memlog localize` matches a map of those frames."""
    cfg, kind, ref_topic = run.cfg, choice.chosen, run.ref_topic
    still = cfg.select.still_distance  # both drives' stops found as `memlog map` finds the map's
    # descriptors of every reference and query frame (unwhitened; cached per kind)
    ref_t = _described(run.reference, run.out / f"reference.{kind}.parquet", describer, run.ref_window, run.reports,
                       still, run.score_by_frame)
    q_t = _described(run.query, run.out / f"query.{kind}.parquet", describer, run.q_window, run.reports, still)
    if not len(ref_t) or not len(q_t):
        raise EvaluationError("no frame of the reference or the query was described (window too small?)")
    truth_rows, truth_src = _truth_rows(run, ref_t, q_t)
    in_window = {ref_topic: [run.score_by_frame[ref_topic][int(i)] for i in ref_t.frame_index
                             if int(i) in run.score_by_frame[ref_topic]]}
    map_cfg = MapConfig(score=run.score_cfg, select=cfg.select, topics=(ref_topic,), descriptor=kind,
                        whiten=cfg.whiten, candidates=cfg.candidates)
    map_path = run.out / (f"map.{kind}.mcap" if several else "map.mcap")
    map_res = make_map(run.reference, map_path, map_cfg, scores=in_window,
                       known_descriptors={(ref_topic, int(i)): ref_t.descriptors[r] for r, i in enumerate(ref_t.frame_index)},
                       known_patches=None if ref_t.patches is None else {
                           (ref_topic, int(i)): ref_t.patches[r] for r, i in enumerate(ref_t.frame_index)},
                       known_looks=run.looks, window=run.ref_window)
    run.looks = run.looks or map_res.looks
    sel = map_res.selections[ref_topic]
    assert map_res.descriptors is not None
    map_table = read_descriptors(map_res.descriptors)
    whitening = map_table.whitening if cfg.whiten else None
    # every map in the drive's one descriptor space (the query whitened and its patches projected by
    # the drive's transforms, as localize does), under both protocols; frame by frame too
    matching = _matching(whitened(q_t, whitening, map_table.patch_pca),
                         whitened(ref_t, whitening, map_table.patch_pca, reference=True), cfg)
    res: dict[str, Any] = {"descriptor": choice.to_dict(), "describer": describer.meta().to_dict(),
                           "whitening": map_res.whitening, "matching": matching.info}
    per_variant = _compare_maps(run, map_res, map_table, matching, ref_t, q_t, truth_rows, res)
    table = score_table(in_window[ref_topic], ref_topic)
    return res, (choice, describer, ref_t, matching, truth_rows, table, sel, per_variant, map_res, truth_src)


def _compare_maps(run: _Run, map_res: MapResult, map_table: DescriptorTable, matching: Matching,
                  ref_t: DescriptorTable, q_t: DescriptorTable, truth_rows: list[set[int]], res: dict[str, Any]
                  ) -> dict[str, tuple[ProtocolResult, ProtocolResult]]:
    """The memorable map (as written), the full map and the baselines of its size (masks of the
    drive's table) into ``res``; the map-only and paper results of each by name."""
    cfg, ref_topic = run.cfg, run.ref_topic
    sel = map_res.selections[ref_topic]
    mask = np.isin(ref_t.frame_index, sel.kept_indices)
    per_variant: dict[str, tuple[ProtocolResult, ProtocolResult]] = {}
    kk = int(mask.sum())
    phases = phase_masks(len(ref_t), kk)  # every k-th frame from every start offset
    # the full map: every frame but a stop's later ones, the frames `memlog map --keep-fraction 1` keeps
    given: dict[str, np.ndarray] = {"full": ~standing_rows(ref_t), "uniform": phases[0]}
    exact = None
    if (cfg.compare_exact and cfg.select.mode == "segment" and cfg.candidates != "all"
            and map_res.tables.get(ref_topic) is not None):
        exact = cfg.select.run(map_res.tables[ref_topic], ms_bound="one" if run.score_cfg.normalize == "static" else "ss")
        given["memorable_exact"] = np.isin(ref_t.frame_index, exact.kept_indices)
    if "x" in ref_t.positions or "lat" in ref_t.positions:
        pos = local_positions(ref_t)
        by_distance = distance_uniform_mask(pos, kk) if pos is not None else None
        if by_distance is not None:
            given["uniform_distance"] = by_distance
    r, mo, po = matching.evaluate(truth_rows, mask, map_table=map_table)
    res["memorable"], per_variant["memorable"] = r, (mo, po)
    for name, m in given.items():
        res[name], mo, po = matching.evaluate(truth_rows, m)
        per_variant[name] = (mo, po)
    if map_table.whitening is not None and cfg.whiten:  # the full map unwhitened, the same patch PCA
        raw = _matching(q_t.projected(map_table.patch_pca), ref_t.projected(map_table.patch_pca), cfg)
        res["full_unwhitened"] = raw.evaluate(truth_rows, given["full"])[0]
    res["memorable"].update({"kept_indices": sel.kept_indices.tolist(), "thresholds": sel.thresholds,
                             "select": cfg.select.mode, "candidates": cfg.candidates,
                             "keep_fraction": cfg.select.keep_fraction, "gaps": len(sel.gaps),
                             "segments": sel.info.get("by"), "still_frames": sel.info.get("still_frames")})
    if exact is not None:
        res["memorable_exact"]["kept_indices"] = exact.kept_indices.tolist()
    res["uniform"]["note"] = "every k-th frame: evenly spaced frame indices, as many as the memorable map"
    each = [res["uniform"]] + [matching.evaluate(truth_rows, m)[0] for m in phases[1:]]
    res["uniform_phases"] = {**mean_std(each), "maps": [
        {"kept_indices": ref_t.frame_index[m].tolist(), "recall@1": r["recall@1"], "auc": r["auc"]}
        for m, r in zip(phases, each)], "note": (
        f"every k-th frame from each of its {len(phases)} start offsets (the first: every k-th above): one "
        "every-k-th map is one draw of where its frames fall")}
    rand = [matching.evaluate(truth_rows, m)[0] for m in random_masks(len(ref_t), kk, range(cfg.seeds))]
    res["random"] = {**mean_std(rand), "maps": [{"recall@1": r["recall@1"], "auc": r["auc"]} for r in rand]}
    res["memorable"]["among"] = {name: among(res["memorable"], res[name]["maps"]) for name in ("uniform_phases", "random")}
    return per_variant


def _analyses(results: dict[str, Any], cfg: EvaluateConfig, table: Any, matching: Matching,
              truth_rows: list[set[int]], sel: Any, per_variant: dict[str, tuple[ProtocolResult, ProtocolResult]]
              ) -> None:
    """The sweeps and each criterion's contribution (main descriptor). They apply the paper's rule
    to every reference frame, so they need every score of every frame: without them (the staged
    scoring, --compare-exact not given) they say so instead of counting the frames not scored as
    failing."""
    missing = [c for c in ("ms", "ss", "es") if not np.isfinite(getattr(table, c)).all()]
    if missing:
        why = (f"not computed: the reference was scored as memlog map scores it (staged), so {', '.join(missing)} "
               "is null for frames that could not change the map; run evaluate with --compare-exact for every "
               "score of every frame")
        results["sweeps"] = {"skipped": why}
        results["criterion_contribution"] = {"skipped": why}
        return
    results["sweeps"] = sweeps(table, matching, truth_rows, cfg.k, cfg.paper_discarded)
    th = sel.thresholds if cfg.select.mode == "paper" and sel.thresholds else cfg.select.thresholds
    results["criterion_contribution"] = contribution(table, per_variant["full"][0], th)


def _settings(run: _Run, describer: Describer) -> dict[str, Any]:
    """``results.json``'s record of the run's settings, inputs, windows and protocols."""
    cfg = run.cfg
    return {"score": run.score_cfg.to_dict(), "select": cfg.select.to_dict(),
            "descriptor": describer.meta().to_dict(), "options": cfg.options(),
            "reference": run.reference, "query": run.query, "reference_topic": run.ref_topic,
            "query_topic": run.q_topic,
            "windows": {"reference": run.ref_window.to_dict(), "query": run.q_window.to_dict()},
            "inputs": {"reference": log_identity(run.reference), "query": log_identity(run.query)},
            "protocols": {
                "map-only": "only map frames are searched; a query is correct iff its best map frame "
                            "is in its truth set; queries whose true places are all missing from "
                            "the map stay positives and can only be wrong",
                "paper": "the full reference database is searched; a query whose best match is a "
                         "discarded frame reports no match (never accepted at any threshold); with "
                         "discarded=false_negative it still counts in the recall denominator",
            }}

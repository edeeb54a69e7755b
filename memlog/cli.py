"""The ``memlog`` command line.

Exit codes (stable, for scripts):
  0  success
  1  error: nothing (or nothing valid) was written; the message says why
  2  usage error (bad flags)
  3  finished, but input was damaged: frames or chunks were skipped or the log was
     truncated (the output holds everything that could be read; warnings list what not)
"""

from __future__ import annotations

import argparse
import signal
import sys
import time
from collections.abc import Callable, Sequence
from typing import Any

from memlog import __version__
from memlog.errors import MemlogError
from memlog.progress import info, set_quiet

__all__ = ["main", "build_parser", "EXIT_OK", "EXIT_ERROR", "EXIT_USAGE", "EXIT_DAMAGED"]

EXIT_OK, EXIT_ERROR, EXIT_USAGE, EXIT_DAMAGED = 0, 1, 2, 3

Command = Callable[[argparse.Namespace], int]
_COMMANDS: dict[str, Command] = {}


def _fmt_ns(ns: int | None) -> str:
    if ns is None:
        return "-"
    return time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime(ns / 1e9)) + f".{ns % 1_000_000_000 // 1_000_000:03d}"


def _fmt_size(n: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if n < 1024 or unit == "TiB":
            return f"{n:.1f} {unit}" if unit != "B" else f"{int(n)} B"
        n /= 1024
    return f"{n} B"


def _table(rows: Sequence[Sequence[str]], header: Sequence[str]) -> str:
    widths = [max(len(str(r[i])) for r in [header, *rows]) for i in range(len(header))]
    def line(r: Sequence[str]) -> str:
        return "  ".join(str(c).ljust(w) for c, w in zip(r, widths)).rstrip()

    return "\n".join([line(header), line(["-" * w for w in widths]), *(line(r) for r in rows)])


def fmt3(v: float | None) -> str:
    """A score with three decimals, or '-' when missing."""
    return "-" if v is None else f"{v:.3f}"


def _damaged(report: Any) -> bool:
    return bool(report.truncated or report.skipped_chunks or report.bad_messages or report.undecodable_frames)


def _report_damage(report: Any) -> int:
    if not _damaged(report):
        return EXIT_OK
    parts = []
    if report.truncated:
        parts.append(f"log truncated (read up to byte {report.bytes_read})" if report.bytes_read else "log truncated")
    if report.skipped_chunks:
        parts.append(f"{report.skipped_chunks} damaged chunk(s) skipped")
    if report.bad_messages:
        parts.append(f"{report.bad_messages} message(s) did not deserialize")
    if report.undecodable_frames:
        parts.append(f"{report.undecodable_frames} frame(s) did not decode")
    print(f"memlog: {report.path}: finished with damaged input: {'; '.join(parts)}", file=sys.stderr)
    return EXIT_DAMAGED


# -- inspect -------------------------------------------------------------------------
def cmd_inspect(args: argparse.Namespace) -> int:
    from memlog.io import open_log

    with open_log(args.log) as log:
        inf = log.info()
        if args.json:
            import json
            from dataclasses import asdict

            d = asdict(inf)
            d["duration_s"] = inf.duration_s
            d["camera_topics"] = inf.camera_topics
            print(json.dumps(d, indent=2))
            return _report_damage(log.report)
        prof = f" (profile {inf.profile})" if inf.profile else ""
        print(f"path:      {inf.path}")
        print(f"format:    {inf.format}{prof}")
        print(f"size:      {_fmt_size(inf.size_bytes)}")
        print(f"start:     {_fmt_ns(inf.start_ns)}")
        print(f"end:       {_fmt_ns(inf.end_ns)}")
        print(f"duration:  {inf.duration_s:.3f} s")
        print(f"messages:  {sum(t.count for t in inf.topics)}")
        print()
        rows = [
            [t.topic, t.msgtype, t.encoding, str(t.count), "camera" if t.is_camera else ""]
            for t in sorted(inf.topics, key=lambda t: t.topic)
        ]
        print(_table(rows, ["topic", "type", "encoding", "messages", ""]))
        print()
        cams = inf.camera_topics
        print(f"camera topics: {', '.join(cams) if cams else 'none'}")
        return _report_damage(log.report)


# -- convert -------------------------------------------------------------------------
def cmd_convert(args: argparse.Namespace) -> int:
    from memlog.convert import convert

    t0 = time.perf_counter()
    res = convert(args.log, args.output, compression=args.compression)
    dt = time.perf_counter() - t0
    info(
        f"memlog: wrote {res.output}: {res.messages} messages, {res.metadata} metadata, "
        f"{res.attachments} attachments, {_fmt_size(res.bytes_in)} -> {_fmt_size(res.bytes_out)} in {dt:.2f} s"
    )
    return _report_damage(res.report)


def _add_inspect(sub: Any) -> None:
    p = sub.add_parser("inspect", help="list topics, camera topics, duration and size of a log",
                       description="Show what a log holds: format, size, time range, and per topic the message "
                                   "type, encoding and count; camera topics are marked.")
    p.add_argument("log", help="MCAP file, ROS 1 .bag, or ROS 2 bag directory")
    p.add_argument("--json", action="store_true", help="print machine-readable JSON")
    p.set_defaults(func=cmd_inspect)


def _add_convert(sub: Any) -> None:
    p = sub.add_parser("convert", help="write any log as an indexed, compressed MCAP",
                       description="Copy every record of LOG into an indexed MCAP (zstd chunks, CRCs, summary). "
                                   "MCAP input keeps schemas, channels, messages, metadata and attachments "
                                   "byte for byte; bags become ros1/ros2-profile MCAP without re-serialising.")
    p.add_argument("log", help="MCAP file, ROS 1 .bag, or ROS 2 bag directory")
    p.add_argument("-o", "--output", required=True, help="output .mcap (written atomically)")
    p.add_argument("--compression", choices=["zstd", "lz4", "none"], default="zstd", help="chunk compression")
    p.set_defaults(func=cmd_convert)


_BUILDERS: list[Callable[[Any], None]] = [_add_inspect, _add_convert]


def register(builder: Callable[[Any], None]) -> Callable[[Any], None]:
    """Add a subcommand builder (used by the pipeline modules' CLI parts)."""
    _BUILDERS.append(builder)
    return builder


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="memlog",
        description="Turn recorded robot drives (MCAP, ROS 1 / ROS 2 bags) into small memorable maps for visual "
                    "place recognition: score every camera frame by memorability, staticity and entropy, keep the "
                    "good ones, localize new drives against them.",
        epilog="Exit codes: 0 ok, 1 error, 2 usage, 3 finished with damaged input (frames skipped / log truncated). "
               "The ResMem memorability weights are licensed for non-commercial use only (see `memlog models`).",
    )
    parser.add_argument("--version", action="version", version=f"memlog {__version__}")
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress bars or status lines")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    _load_commands()
    for b in _BUILDERS:
        b(sub)
    for p in sub.choices.values():  # -q works after the subcommand too
        p.add_argument("-q", "--quiet", action="store_true", default=argparse.SUPPRESS,
                       help="no progress bars or status lines")
    return parser


def _load_commands() -> None:
    """Import the modules that register further subcommands."""
    import importlib

    for mod in ("memlog.cli_pipeline",):
        try:
            importlib.import_module(mod)
        except ModuleNotFoundError as exc:
            if exc.name != mod:
                raise


def _on_sigterm(signum: int, frame: Any) -> None:
    """SIGTERM unwinds like Ctrl-C, so writers drop their temporary files."""
    raise KeyboardInterrupt


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return EXIT_USAGE
    set_quiet(bool(args.quiet))
    signal.signal(signal.SIGTERM, _on_sigterm)
    try:
        return int(args.func(args))
    except MemlogError as exc:
        print(f"memlog: error: {exc}", file=sys.stderr)
        return EXIT_ERROR
    except KeyboardInterrupt:
        print("memlog: interrupted; no output was written under its final name", file=sys.stderr)
        return 130
    except BrokenPipeError:
        return EXIT_OK
    except Exception as exc:  # a bug, not bad input: say so without a traceback unless asked
        import os
        import traceback

        if os.environ.get("MEMLOG_DEBUG"):
            traceback.print_exc()
        print(f"memlog: internal error: {type(exc).__name__}: {exc} (set MEMLOG_DEBUG=1 for a traceback; "
              "please report it)", file=sys.stderr)
        return EXIT_ERROR


if __name__ == "__main__":  # run the importable module, so subcommands register in one place
    from memlog.cli import main as _main

    sys.exit(_main())

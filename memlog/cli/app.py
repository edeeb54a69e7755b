"""The ``memlog`` command: the parser built from one static command table, and error handling.

Exit codes (stable, for scripts; :mod:`memlog.cli.common`):
  0  success
  1  error: nothing (or nothing valid) was written; the message says why
  2  usage error: a flag, a setting or an output path is wrong; reported before any work
  3  finished, but the input was damaged: frames or chunks were skipped or the log was
     truncated (the output holds everything that could be read; warnings list what not)
  130  interrupted (Ctrl-C, SIGTERM): nothing was written under an output's name
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
from collections.abc import Sequence
from typing import Any

from memlog._version import __version__
from memlog.cli.commands import COMMANDS
from memlog.cli.common import EXIT_ERROR, EXIT_INTERRUPTED, EXIT_OK, EXIT_USAGE, HelpFormatter
from memlog.cli.flags import GROUPS
from memlog.errors import MemlogError, UsageError
from memlog.progress import LOGGER, set_quiet
from memlog.runtime import Runtime, current, use

__all__ = ["main", "build_parser"]


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of every subcommand (:data:`memlog.cli.commands.COMMANDS`)."""
    parser = argparse.ArgumentParser(
        prog="memlog",
        description="Turn recorded robot drives (MCAP, ROS 1 / ROS 2 bags) into small memorable maps for visual "
                    "place recognition: score every camera frame by memorability, staticity and entropy, keep the "
                    "good ones, localize new drives against them.",
        epilog="`memlog COMMAND --help` shows the flags most runs need first, then the others by group ("
               + ", ".join(GROUPS) + ").\n\n"
               "Exit codes: 0 ok, 1 error, 2 usage (bad flag, setting or path; nothing done), 3 finished with "
               "damaged input (frames skipped / log truncated), 130 interrupted. Outputs are written atomically "
               "into existing directories and never over an input. The ResMem memorability weights are licensed "
               "for non-commercial use only (see `memlog models`).",
        formatter_class=HelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"memlog {__version__}")
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress bars or status lines")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for add in COMMANDS.values():
        add(sub)
    for p in sub.choices.values():  # -q works after the subcommand too (last of the flags shown first)
        p.add_argument("-q", "--quiet", action="store_true", default=argparse.SUPPRESS,
                       help="no progress bars or status lines")
    return parser


class _Format(logging.Formatter):
    """``memlog: TEXT`` for status lines, ``memlog: warning: TEXT`` for warnings."""

    def format(self, record: logging.LogRecord) -> str:
        text = record.getMessage()
        if record.levelno >= logging.ERROR:
            return f"memlog: error: {text}"
        if record.levelno >= logging.WARNING:
            return f"memlog: warning: {text}"
        return f"memlog: {text}"


class _Stderr(logging.StreamHandler):  # type: ignore[type-arg]
    """Writes to the ``sys.stderr`` of the moment (tests and callers may redirect it)."""

    def emit(self, record: logging.LogRecord) -> None:
        self.stream = sys.stderr
        super().emit(record)


def show_messages(quiet: bool) -> None:
    """What the command shows of the library's messages: status lines and warnings on stderr
    (``quiet``: warnings only), no progress bars when ``quiet``."""
    set_quiet(quiet)
    for h in [h for h in LOGGER.handlers if isinstance(h, _Stderr)]:
        LOGGER.removeHandler(h)
    handler = _Stderr()
    handler.setFormatter(_Format())
    LOGGER.addHandler(handler)
    LOGGER.setLevel(logging.WARNING if quiet else logging.INFO)
    LOGGER.propagate = False


def _on_sigterm(signum: int, frame: Any) -> None:
    """SIGTERM unwinds like Ctrl-C, so writers drop their temporary files."""
    raise KeyboardInterrupt


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``memlog`` command line; returns the exit code. The environment is read here, once:
    the runtime context it asks for (:meth:`memlog.runtime.Runtime.from_environment`, with this
    process's caches) is in force while the command runs (``--max-pixels`` replaces it)."""
    try:
        asked, problem = Runtime.from_environment(os.environ), None
    except MemlogError as exc:  # said once the command line is read (--help, --version still work)
        asked, problem = current(), exc
    with use(current().with_settings_of(asked)):
        return _run(argv, problem)


def _run(argv: Sequence[str] | None, problem: MemlogError | None) -> int:
    """:func:`main` within its runtime context; ``problem``: what was wrong in the environment."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return EXIT_USAGE
    show_messages(bool(args.quiet))
    if problem is not None:
        print(f"memlog: error: {problem}", file=sys.stderr)
        return EXIT_USAGE if isinstance(problem, UsageError) else EXIT_ERROR
    signal.signal(signal.SIGTERM, _on_sigterm)
    try:
        return int(args.func(args))
    except UsageError as exc:
        print(f"memlog {args.command}: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except MemlogError as exc:
        print(f"memlog: error: {exc}", file=sys.stderr)
        return EXIT_ERROR
    except KeyboardInterrupt:
        print("memlog: interrupted; no output was written under its final name", file=sys.stderr)
        return EXIT_INTERRUPTED
    except MemoryError:
        print("memlog: error: out of memory (try fewer --workers or --threads); no output was written under its "
              "final name", file=sys.stderr)
        return EXIT_ERROR
    except BrokenPipeError:
        return EXIT_OK
    except Exception as exc:  # a bug, not bad input: say so without a traceback unless asked
        import traceback

        if current().debug:
            traceback.print_exc()
        print(f"memlog: internal error: {type(exc).__name__}: {exc} (set MEMLOG_DEBUG=1 for a traceback; "
              "please report it)", file=sys.stderr)
        return EXIT_ERROR

"""What every subcommand shares: exit codes, damage reporting, and plain-text formatting (tables,
and the ``--help`` text's)."""

from __future__ import annotations

import argparse
import sys
import textwrap
import time
from collections.abc import Sequence

from memlog.io.records import ReadReport

__all__ = [
    "EXIT_OK", "EXIT_ERROR", "EXIT_USAGE", "EXIT_DAMAGED", "EXIT_INTERRUPTED",
    "report_damage", "fmt_ns", "fmt_size", "fmt3", "table", "HelpFormatter",
]

#: Exit codes (stable, for scripts).
EXIT_OK = 0  # success
EXIT_ERROR = 1  # the work could not be done; nothing was written under the output's name
EXIT_USAGE = 2  # memlog was called wrongly (a flag, a setting, an output path); nothing was done
EXIT_DAMAGED = 3  # finished, but the input was damaged: frames or chunks skipped, or the log truncated
EXIT_INTERRUPTED = 130  # Ctrl-C or SIGTERM; nothing was written under the output's name


def report_damage(*reports: ReadReport) -> int:
    """Print one line per damaged input and return :data:`EXIT_DAMAGED`, else :data:`EXIT_OK`."""
    code = EXIT_OK
    for report in reports:
        if report.ok:
            continue
        parts = report.damage()
        print(f"memlog: {report.path}: finished with damaged input: {'; '.join(parts)}", file=sys.stderr)
        code = EXIT_DAMAGED
    return code


def fmt_ns(ns: int | None) -> str:
    """A log time as UTC date and time with milliseconds ('-' when unknown or out of range)."""
    if ns is None:
        return "-"
    try:
        return time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime(ns / 1e9)) + f".{ns % 1_000_000_000 // 1_000_000:03d}"
    except (OverflowError, OSError, ValueError):
        return f"{ns} ns (out of range)"


def fmt_size(n: float) -> str:
    """Bytes as B/KiB/MiB/GiB/TiB."""
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if n < 1024 or unit == "TiB":
            return f"{n:.1f} {unit}" if unit != "B" else f"{int(n)} B"
        n /= 1024
    return f"{n} B"


def fmt3(v: float | None) -> str:
    """A score with three decimals, or '-' when missing."""
    return "-" if v is None else f"{v:.3f}"


def table(rows: Sequence[Sequence[str]], header: Sequence[str]) -> str:
    """A plain-text table with a header rule."""
    widths = [max(len(str(r[i])) for r in [header, *rows]) for i in range(len(header))]

    def line(r: Sequence[str]) -> str:
        return "  ".join(str(c).ljust(w) for c, w in zip(r, widths)).rstrip()

    return "\n".join([line(header), line(["-" * w for w in widths]), *(line(r) for r in rows)])


class HelpFormatter(argparse.HelpFormatter):
    """The ``--help`` text: paragraphs of the description and epilog wrapped to the terminal, a block
    with indented lines (examples) kept as written; lines never break inside a hyphenated word (a
    flag name, ``resmem-int8``)."""

    def _fill_text(self, text: str, width: int, indent: str) -> str:
        blocks = []
        for block in text.split("\n\n"):
            lines = block.splitlines()
            if any(line.startswith(" ") for line in lines):
                blocks.append("\n".join(indent + line for line in lines))
            else:
                blocks.append(textwrap.fill(" ".join(block.split()), width, initial_indent=indent,
                                            subsequent_indent=indent, break_on_hyphens=False))
        return "\n\n".join(blocks)

    def _split_lines(self, text: str, width: int) -> list[str]:
        return textwrap.wrap(" ".join(text.split()), width, break_on_hyphens=False)

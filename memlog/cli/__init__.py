"""The ``memlog`` command line (a thin layer over :mod:`memlog.steps`)."""

from memlog.cli.app import build_parser, main

__all__ = ["main", "build_parser"]

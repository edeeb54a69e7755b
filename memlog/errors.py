"""Error classes, one per module family (like rosbags), and which exit code each means.

* :class:`UsageError` (exit 2): the command was called wrongly (a flag value, a config key or
  value, an output path, a path that is a symlink loop). Raised before any expensive work.
* :class:`LogReadError` etc. (exit 1): the work could not be done; nothing was written under
  the output's name. Damaged input that could still be read is not an error: the run finishes
  and exits 3 (see :mod:`memlog.cli`).
"""

from __future__ import annotations

__all__ = [
    "MemlogError",
    "UsageError",
    "ConfigError",
    "OutputPathError",
    "SymlinkLoopError",
    "TopicError",
    "LogReadError",
    "ImageDecodeError",
    "LogWriteError",
    "ModelError",
    "ScoringError",
    "SelectionError",
    "DescriptorError",
    "EvaluationError",
]


class MemlogError(Exception):
    """Base class of every error memlog raises on purpose."""


class UsageError(MemlogError):
    """memlog was called wrongly (exit code 2): the message names the flag or setting."""


class ConfigError(UsageError):
    """A configuration file, setting or option value is invalid."""


class OutputPathError(UsageError):
    """An output path cannot be used (missing directory, a directory, or one of the inputs)."""


class SymlinkLoopError(UsageError):
    """A path given to memlog (an input or an output) is, or passes through, a symbolic link
    loop, so it names no file."""


class TopicError(UsageError):
    """A topic named on the command line (or in a config) is not in the log, or is not a camera topic."""


class LogReadError(MemlogError):
    """A log (MCAP file, ROS 1 bag, ROS 2 bag) could not be opened or read."""


class ImageDecodeError(MemlogError):
    """An image message could not be decoded to pixels."""


class LogWriteError(MemlogError):
    """An output log could not be written."""


class ModelError(MemlogError):
    """A model file is missing, corrupt or could not be converted or run."""


class ScoringError(MemlogError):
    """A frame could not be scored (wrong shape, model failure)."""


class SelectionError(MemlogError):
    """Frames could not be selected (for example: no frame passes, so the map would be empty)."""


class DescriptorError(MemlogError):
    """Descriptors could not be computed, read or matched."""


class EvaluationError(MemlogError):
    """Ground truth or evaluation inputs are invalid."""

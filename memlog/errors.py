"""Error classes, one per module family (like rosbags)."""

from __future__ import annotations

__all__ = [
    "MemlogError",
    "LogReadError",
    "ImageDecodeError",
    "LogWriteError",
    "ModelError",
    "ScoringError",
    "DescriptorError",
    "EvaluationError",
    "ConfigError",
]


class MemlogError(Exception):
    """Base class of every error memlog raises on purpose."""


class LogReadError(MemlogError):
    """A log (MCAP file, ROS 1 bag, ROS 2 bag) could not be opened or read."""


class ImageDecodeError(MemlogError):
    """An image message could not be decoded to pixels."""


class LogWriteError(MemlogError):
    """An output log could not be written."""


class ModelError(MemlogError):
    """A model file is missing, corrupt or could not be converted."""


class ScoringError(MemlogError):
    """A frame could not be scored (wrong shape, model failure)."""


class DescriptorError(MemlogError):
    """Descriptors could not be computed, read or matched."""


class EvaluationError(MemlogError):
    """Ground truth or evaluation inputs are invalid."""


class ConfigError(MemlogError):
    """A configuration file or option is invalid."""

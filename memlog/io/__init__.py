"""Log I/O: open any log, stream frames, decode images, write MCAP.

>>> from memlog.io import open_log
>>> with open_log("drive.bag") as log:
...     for frame in log.frames(stride=5):
...         bgr = frame.decode_bgr()
"""

from __future__ import annotations

from memlog.io.base import FrameError, LogReader
from memlog.io.open import open_log
from memlog.io.records import ChannelInfo, RawMessage, ReadReport, SchemaInfo
from memlog.io.types import Frame, ImagePayload, LogInfo, TopicInfo
from memlog.io.writer import McapLogWriter, copy_log

__all__ = [
    "open_log",
    "LogReader",
    "Frame",
    "FrameError",
    "ImagePayload",
    "LogInfo",
    "TopicInfo",
    "ChannelInfo",
    "SchemaInfo",
    "RawMessage",
    "ReadReport",
    "McapLogWriter",
    "copy_log",
]

"""Log I/O: open any log, stream frames, decode images, write MCAP atomically.

>>> from memlog.io import open_log
>>> with open_log("drive.bag") as log:
...     for frame in log.frames(stride=5):
...         bgr = frame.decode_bgr()

One subpackage per format (:mod:`memlog.io.mcap`, :mod:`memlog.io.rosbag1`,
:mod:`memlog.io.rosbag2`); this package re-exports the small API every step uses. The names
load on first use, so ``import memlog.io.atomic`` does not pull in the MCAP or image libraries.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from memlog.errors import (
        ImageDecodeError as ImageDecodeError,
        LogReadError as LogReadError,
        LogWriteError as LogWriteError,
    )
    from memlog.io.atomic import (
        AtomicFile as AtomicFile,
        atomic_output as atomic_output,
        check_output as check_output,
        write_bytes_atomic as write_bytes_atomic,
    )
    from memlog.io.base import (
        FrameError as FrameError,
        FrameWindow as FrameWindow,
        LogReader as LogReader,
        StreamItem as StreamItem,
    )
    from memlog.io._opened import clear_cache as clear_cache
    from memlog.io.frame import Frame as Frame
    from memlog.io.mcap import McapLogWriter as McapLogWriter, copy_log as copy_log
    from memlog.io.open import open_log as open_log
    from memlog.io.records import (
        ChannelInfo as ChannelInfo,
        RawMessage as RawMessage,
        ReadReport as ReadReport,
        SchemaInfo as SchemaInfo,
    )
    from memlog.io.types import ImagePayload as ImagePayload, LogInfo as LogInfo, TopicInfo as TopicInfo


_WHERE = {
    "open_log": "memlog.io.open",
    "LogReader": "memlog.io.base",
    "StreamItem": "memlog.io.base",
    "FrameWindow": "memlog.io.base",
    "FrameError": "memlog.io.base",
    "Frame": "memlog.io.frame",
    "ImagePayload": "memlog.io.types",
    "LogInfo": "memlog.io.types",
    "TopicInfo": "memlog.io.types",
    "ChannelInfo": "memlog.io.records",
    "SchemaInfo": "memlog.io.records",
    "RawMessage": "memlog.io.records",
    "ReadReport": "memlog.io.records",
    "McapLogWriter": "memlog.io.mcap",
    "copy_log": "memlog.io.mcap",
    "AtomicFile": "memlog.io.atomic",
    "atomic_output": "memlog.io.atomic",
    "write_bytes_atomic": "memlog.io.atomic",
    "check_output": "memlog.io.atomic",
    "clear_cache": "memlog.io._opened",
    "LogReadError": "memlog.errors",
    "LogWriteError": "memlog.errors",
    "ImageDecodeError": "memlog.errors",
}

__all__ = sorted(_WHERE)


def __getattr__(name: str) -> Any:
    module = _WHERE.get(name)
    if module is None:
        raise AttributeError(f"module 'memlog.io' has no attribute {name!r}")
    return getattr(importlib.import_module(module), name)

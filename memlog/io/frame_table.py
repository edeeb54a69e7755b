"""Frame numbering: every message of a camera topic that the log lists, in log-time order.

The frame index of a camera message (the spec's "position of the message on its topic, from 0,
in log-time order") is its position in the topic's :class:`FrameTable`. A reader builds the
table once per log (and per process, :mod:`memlog.io._opened`), **before** any frame is read:

* from the log's index when the reader trusts it (MCAP message indexes, the ROS 1 bag's index
  data, the rows of a ROS 2 ``.db3``): every message the recording wrote is numbered, also one
  in a chunk that later turns out to be unreadable — its number is then missing from the
  stream, and the frames after it keep theirs;
* otherwise from the one scan of the data the reader makes when it opens an unindexed or
  damaged log: every message that scan could read, or that the message indexes an MCAP writer
  put after each chunk list (an unfinished MCAP: a chunk learned from its indexes is numbered
  as an indexed log's is, also when its data later turns out to be unreadable).

A message read later is numbered by looking up *where* it was read (``RawMessage.where``: the
chunk or row and the offset inside it), never by counting what a stream happened to read. So a
time window, a stride, a worker reading one chunk of frames, a second pass or another process
all give a frame the same index, and a damaged chunk never shifts the numbers of the frames
after it.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

__all__ = ["FrameTable"]

I64 = npt.NDArray[np.int64]


class FrameTable:
    """The messages of one topic by log time: position ``i`` is frame index ``i``.

    ``times``, ``containers``, ``offsets``: one entry per message (any order); entries are
    ordered by log time, ties by where they lie in the file.
    """

    def __init__(self, times: npt.ArrayLike, containers: npt.ArrayLike, offsets: npt.ArrayLike) -> None:
        t = np.asarray(times, dtype=np.int64)
        c = np.asarray(containers, dtype=np.int64)
        o = np.asarray(offsets, dtype=np.int64)
        order = np.lexsort((o, c, t))
        self.times: I64 = t[order]
        by_place = np.lexsort((o[order], c[order]))
        self._c: I64 = c[order][by_place]
        self._o: I64 = o[order][by_place]
        self._pos: I64 = by_place.astype(np.int64)

    @classmethod
    def concat(cls, parts: Sequence[tuple[I64, I64, I64]]) -> "FrameTable":
        """A table of several sources' (times, containers, offsets)."""
        if not parts:
            return cls(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64))
        return cls(*(np.concatenate([p[k] for p in parts]) for k in range(3)))

    def __len__(self) -> int:
        return int(self.times.shape[0])

    def index_of(self, where: tuple[int, int] | None) -> int:
        """The frame index of the message read at ``where``; -1 when the table does not list it."""
        if where is None:
            return -1
        c, o = where
        lo = int(np.searchsorted(self._c, c, side="left"))
        hi = int(np.searchsorted(self._c, c, side="right"))
        if lo == hi:
            return -1
        j = lo + int(np.searchsorted(self._o[lo:hi], o, side="left"))
        if j >= hi or int(self._o[j]) != o:
            return -1
        return int(self._pos[j])

    def entries(self) -> tuple[I64, I64, I64]:
        """(times, containers, offsets) of every entry, in frame-index order."""
        order = np.argsort(self._pos, kind="stable")
        return self.times, self._c[order], self._o[order]

    def window(self, start_ns: int | None, end_ns: int | None) -> tuple[int, int]:
        """The frame indices ``[first, last)`` whose log times lie in [``start_ns``, ``end_ns``)."""
        first = 0 if start_ns is None else int(np.searchsorted(self.times, start_ns, side="left"))
        last = len(self) if end_ns is None else int(np.searchsorted(self.times, end_ns, side="left"))
        return first, max(first, last)

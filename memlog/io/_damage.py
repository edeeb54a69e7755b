"""What the readers share about damaged input: where damage starts, bounded decompression,
and a merge that restores log-time order across chunks without holding the whole log."""

from __future__ import annotations

import heapq
import os
import stat
from collections.abc import Iterable, Iterator
from typing import IO, TypeVar

from memlog.errors import LogReadError

__all__ = ["MAX_CHUNK_BYTES", "check_regular_file", "damage_place", "decompress", "merge_groups"]

#: Largest uncompressed chunk a reader accepts (a larger declared size is damage, not a memory bill).
MAX_CHUNK_BYTES = 1 << 31

T = TypeVar("T")


def check_regular_file(path: str) -> os.stat_result:
    """``os.stat`` of ``path``; :class:`LogReadError` unless it is a regular file (a named pipe,
    a device or a socket would block or never end). Called before the file is opened."""
    try:
        st = os.stat(path)
    except FileNotFoundError:
        raise LogReadError(f"{path}: no such file or directory") from None
    except OSError as exc:
        raise LogReadError(f"{path}: cannot read: {exc.strerror}") from exc
    if not stat.S_ISREG(st.st_mode):
        kind = ("a directory" if stat.S_ISDIR(st.st_mode) else "a named pipe" if stat.S_ISFIFO(st.st_mode)
                else "a socket" if stat.S_ISSOCK(st.st_mode) else "a device" if stat.S_ISCHR(st.st_mode)
                or stat.S_ISBLK(st.st_mode) else "not a regular file")
        raise LogReadError(f"{path}: is {kind}, not a log file (memlog reads regular files and ROS 2 bag directories)")
    return st


def _zero_from(fh: IO[bytes], pos: int, size: int) -> int | None:
    """Where the run of zero bytes that reaches the end of the file starts, if the bytes from
    ``pos`` to the end are all zero; None otherwise. Reads the tail once, in blocks."""
    block = 1 << 20
    at = pos
    fh.seek(pos)
    while at < size:
        buf = fh.read(min(block, size - at))
        if not buf:
            break
        if buf.count(0) != len(buf):
            return None
        at += len(buf)
    return pos


def _zero_run_start(fh: IO[bytes], pos: int) -> int:
    """Where the run of zero bytes that ends at ``pos`` begins (reading backwards in blocks)."""
    block = 1 << 16
    at = pos
    while at > 0:
        lo = max(0, at - block)
        fh.seek(lo)
        buf = fh.read(at - lo)
        stripped = buf.rstrip(b"\0")
        if len(stripped) < len(buf) and stripped:
            return lo + len(stripped)
        if stripped:
            return at
        at = lo
    return 0


def damage_place(fh: IO[bytes], pos: int, size: int) -> str:
    """Where damage found at byte ``pos`` is, in words: a zero-filled tail is named from where the
    zeros start (an interrupted recording leaves one), anything else by its byte offset."""
    if pos < size and _zero_from(fh, pos, size) is not None:
        start = _zero_run_start(fh, pos)
        return (f"zero-filled from byte {start} to the end ({size - start} bytes of zeros, an interrupted "
                "recording?)")
    return f"near byte {pos} of {size}"


def decompress(kind: str, data: bytes, size: int) -> bytes:
    """Decompress ``data`` (``zstd``, ``lz4``, ``bz2`` or ``""``/``none``) to exactly the declared
    ``size`` bytes, never producing more: a chunk that claims or inflates to more is damage
    (ValueError), not a memory bill."""
    if size < 0 or size > MAX_CHUNK_BYTES:
        raise ValueError(f"chunk declares {size} bytes uncompressed (more than {MAX_CHUNK_BYTES})")
    try:
        out = _inflate(kind, data, size)
    except ValueError:
        raise
    except Exception as exc:  # noqa: BLE001 - zstd, lz4 (RuntimeError) and bz2 (OSError) fail differently
        raise ValueError(f"{kind} data does not decompress ({type(exc).__name__}: {exc})") from None
    if len(out) != size:
        raise ValueError(f"chunk inflates to {len(out)}{'+' if len(out) > size else ''} bytes, declares {size}")
    return out


def _inflate(kind: str, data: bytes, size: int) -> bytes:
    if kind in ("", "none"):
        return data
    elif kind == "zstd":
        import zstandard

        with zstandard.ZstdDecompressor().stream_reader(data, read_across_frames=True) as r:
            return r.read(size + 1)
    elif kind == "lz4":
        import lz4.frame

        d = lz4.frame.LZ4FrameDecompressor()
        return bytes(d.decompress(data, max_length=size + 1))
    elif kind == "bz2":
        import bz2

        return bz2.BZ2Decompressor().decompress(data, max_length=size + 1)
    raise ValueError(f"unknown chunk compression {kind!r}")


def merge_groups(groups: Iterable[list[tuple[int, T]]]) -> Iterator[T]:
    """Items of consecutive groups (chunks) in time order: each group is sorted, and an item is
    released once a later group starts after it. Exact when groups start in time order (as chunks
    of a recording do); memory holds the groups that overlap in time."""
    heap: list[tuple[int, int, T]] = []
    order = 0
    for group in groups:
        if not group:
            continue
        low = min(t for t, _ in group)
        while heap and heap[0][0] <= low:
            yield heapq.heappop(heap)[2]
        for t, item in group:
            heapq.heappush(heap, (t, order, item))
            order += 1
    while heap:
        yield heapq.heappop(heap)[2]

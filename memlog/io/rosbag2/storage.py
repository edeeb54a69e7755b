"""The storage files of a ROS 2 bag: a ``.db3`` read row by row with sqlite (robust to damaged
pages and cut files), and what tells the storage kinds apart (see :mod:`memlog.io.rosbag2.reader`)."""

from __future__ import annotations

import os
import shutil
import sqlite3
import struct
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any

import numpy as np

from memlog.io._damage import MAX_CHUNK_BYTES
from memlog.io.base import LogReader

__all__ = ["Db3Storage", "StorageFileBad", "inflate_message", "sniff_storage"]

_ZSTD = b"\x28\xb5\x2f\xfd"
_PROBE = 256  # rows looked up one by one after a damaged page before jumping ahead


class StorageFileBad(Exception):
    """A storage file that cannot be read at all (the bag goes on without it)."""


def inflate_message(data: bytes) -> bytes:
    """A zstd-compressed message (message-mode compression), bounded."""
    import zstandard

    with zstandard.ZstdDecompressor().stream_reader(data, read_across_frames=True) as r:
        out: bytes = r.read(MAX_CHUNK_BYTES + 1)
    if len(out) > MAX_CHUNK_BYTES:
        raise ValueError("message inflates to more than 2 GiB")
    return out


class Db3Storage:
    """One sqlite3 storage file, read row by row."""

    _con: sqlite3.Connection
    _pid: int  # the process that opened _con

    def __init__(self, path: Path, owner: LogReader) -> None:
        self.path, self.owner = path, owner
        self._tmp: IO[bytes] | None = None
        self.con = self._connect(path)
        try:
            self.topics = self._topics()
        except sqlite3.DatabaseError as exc:
            self.con.close()
            self.con = self._patched_copy(exc)
            try:
                self.topics = self._topics()
            except sqlite3.DatabaseError as exc2:
                self.close()
                raise StorageFileBad(f"sqlite cannot read it ({exc2})") from None
        self.msgdefs = self._msgdefs()
        self._rows: tuple[Any, Any, Any] | None = None

    @property
    def con(self) -> sqlite3.Connection:
        """This process's connection: a process forked after the file was opened (the entry of
        :mod:`memlog.io._opened` came with it) opens its own, never using its parent's."""
        if self._pid != os.getpid():
            where = Path(self._tmp.name) if self._tmp is not None else self.path
            self._con = sqlite3.connect(f"file:{where}?immutable=1", uri=True, check_same_thread=False)
            self._pid = os.getpid()
        return self._con

    @con.setter
    def con(self, con: sqlite3.Connection) -> None:
        self._con, self._pid = con, os.getpid()

    @staticmethod
    def _connect(path: Path) -> sqlite3.Connection:
        try:
            return sqlite3.connect(f"file:{path}?immutable=1", uri=True, check_same_thread=False)
        except sqlite3.Error as exc:
            raise StorageFileBad(f"sqlite cannot open it ({exc})") from None

    def _patched_copy(self, why: Exception) -> sqlite3.Connection:
        """A private copy whose header page count matches the file (a cut file's header claims
        pages it lost, and sqlite then refuses every page)."""
        with open(self.path, "rb") as fh:
            head = fh.read(100)
            if len(head) < 100 or not head.startswith(b"SQLite format 3\x00"):
                raise StorageFileBad(f"not an sqlite3 database ({why})")
            page = struct.unpack(">H", head[16:18])[0]
            page = 65536 if page == 1 else page
            size = os.fstat(fh.fileno()).st_size
            pages = -(-size // page) if page else 0
            if pages == struct.unpack(">I", head[28:32])[0]:
                raise StorageFileBad(f"sqlite cannot read it ({why})")
            fh.seek(0)
            self._tmp = tempfile.NamedTemporaryFile(prefix="memlog-", suffix=".db3")
            shutil.copyfileobj(fh, self._tmp)
        self._tmp.seek(28)
        self._tmp.write(struct.pack(">I", pages))
        self._tmp.flush()
        self.owner.warn(f"{self.path}: sqlite database is cut off ({size} bytes, its header claims more pages): "
                        "reading the rows that are left")
        self.owner.report.truncated = True
        return self._connect(Path(self._tmp.name))

    def _topics(self) -> dict[int, tuple[str, str, str, str]]:
        cols = {r[1] for r in self.con.execute("PRAGMA table_info(topics)")}
        qos = "offered_qos_profiles" if "offered_qos_profiles" in cols else "''"
        out = {}
        for tid, name, typ, ser, q in self.con.execute(f"SELECT id, name, type, serialization_format, {qos} FROM topics"):
            if isinstance(tid, int) and isinstance(name, str) and isinstance(typ, str):
                out[tid] = (name, typ, ser if isinstance(ser, str) and ser else "cdr", q if isinstance(q, str) else "")
        return out

    def _msgdefs(self) -> dict[str, tuple[str, str]]:
        try:
            rows = self.con.execute(
                "SELECT topic_type, encoding, encoded_message_definition FROM message_definitions").fetchall()
        except sqlite3.DatabaseError:
            return {}
        return {t: (e, d) for t, e, d in rows if isinstance(t, str) and isinstance(d, str) and d.strip()}

    def close(self) -> None:
        if self._pid == os.getpid():  # (a parent's connection is the parent's to close)
            self._con.close()
        if self._tmp is not None:
            self._tmp.close()
            self._tmp = None

    def _lookup(self, rid: int) -> tuple[Any, ...] | None:
        try:
            row: tuple[Any, ...] | None = self.con.execute(
                "SELECT id, topic_id, timestamp FROM messages WHERE id = ?", (rid,)).fetchone()
            return row
        except sqlite3.DatabaseError:
            return None

    def rows(self, header_stamp: Callable[[int, bytes], int | None] | None = None) -> tuple[Any, Any, Any]:
        """(row ids, topic ids, timestamps) of every readable, valid row, in (timestamp, id) order;
        found once (the bag reader's first call passes ``header_stamp``: (topic id, message bytes)
        -> the message's header stamp or None).

        A row whose timestamp is not a non-negative integer (SQLite columns take any type) keeps
        its message: its time is the message's header stamp, else the previous row's time (the
        next row's for the first rows), reported (``retimed_messages``) with file, topic and row."""
        if self._rows is not None:
            return self._rows
        found = _RowTimes(self, header_stamp)
        last = -(1 << 63)
        damaged_at: int | None = None
        while True:
            try:
                for rid, tid, t in self.con.execute(
                        "SELECT id, topic_id, timestamp FROM messages WHERE id > ? ORDER BY id", (last,)):
                    found.add(rid, tid, t)
                    last = rid
                break
            except sqlite3.DatabaseError as exc:
                if damaged_at is None:
                    damaged_at = last
                    self.owner.report.truncated = True
                    self.owner.warn(f"{self.path}: database damaged after message row {last} ({exc}); "
                                    "reading the rows that are left one by one")
                nxt = self._probe(last)
                if nxt is None:
                    break
                found.add(*nxt)
                last = nxt[0]
        self._rows = found.finish()
        return self._rows

    def _stamp(self, rid: int, tid: int, header_stamp: Callable[[int, bytes], int | None] | None) -> int | str | None:
        """The header stamp (ns, > 0) of row ``rid``'s message, None when it has none, or why its
        message cannot be had."""
        data = self.data(rid)
        if isinstance(data, str):
            return data
        stamp = None if header_stamp is None else header_stamp(tid, data)
        return stamp if stamp is not None and 0 < stamp < (1 << 63) else None

    def _probe(self, last: int) -> tuple[Any, ...] | None:
        """The next row after ``last`` that sqlite can read: ids one by one, then ever larger jumps."""
        for rid in range(last + 1, last + 1 + _PROBE):
            row = self._lookup(rid)
            if row is not None:
                return row
        step = _PROBE
        while last + step < (1 << 62):
            step *= 2
            row = self._lookup(last + step)
            if row is not None:
                return row
        return None

    def data(self, rid: int) -> bytes | str:
        """The row's message bytes, or why they cannot be had."""
        try:
            row = self.con.execute("SELECT data FROM messages WHERE id = ?", (rid,)).fetchone()
        except sqlite3.DatabaseError as exc:
            return f"sqlite cannot read it ({exc})"
        if row is None or not isinstance(row[0], bytes):
            return "its data is not a blob"
        data = row[0]
        if data.startswith(_ZSTD):
            try:
                return inflate_message(data)
            except Exception as exc:  # noqa: BLE001 - zstd errors have no common base
                return f"its zstd data does not decompress ({exc})"
        return data


class _RowTimes:
    """The rows of one ``.db3`` as :meth:`Db3Storage.rows` reads them (row id order): the valid
    ones kept, each with its log time, and what was wrong with the others counted and reported."""

    def __init__(self, db: Db3Storage, header_stamp: Callable[[int, bytes], int | None] | None) -> None:
        self.db, self.header_stamp = db, header_stamp
        self.rep = db.owner.report
        self.ids: list[int] = []
        self.tids: list[int] = []
        self.ts: list[int] = []
        self.bad = 0
        self.retimed = 0
        self.prev: int | None = None  # the time of the row before (row id order: the order of recording)
        self.waiting: list[tuple[int, int, Any, Any]] = []  # (place in ts, row id, topic id, timestamp): no time yet

    def warn(self, text: str) -> None:
        self.db.owner.warn(text)

    def retime(self, rid: int, tid: int, t: Any, how: str) -> None:
        """Report that row ``rid``'s timestamp ``t`` is no time and its message is kept at ``how``."""
        if self.rep.count("retimed_messages", (str(self.db.path), rid)):
            self.retimed += 1
            if self.retimed <= 5:
                self.warn(f"{self.db.path}: topic {self.db.topics[tid][0]}: message row {rid}: timestamp {t!r} "
                          f"is not a time; its message is kept at {how}")

    def add(self, rid: Any, tid: Any, t: Any) -> None:
        """Take the row ``rid`` (topic id ``tid``, timestamp ``t``), or count it as bad."""
        db = self.db
        if tid not in db.topics:
            self.bad += 1
            if self.bad <= 5:
                self.warn(f"{db.path}: message row {rid}: topic id {tid!r} is not in its topics table; skipped")
            return
        if type(t) is not int or t < 0:
            stamp = db._stamp(rid, tid, self.header_stamp)
            if isinstance(stamp, str):  # no message to keep
                self.bad += 1
                if self.bad <= 5:
                    self.warn(f"{db.path}: message row {rid}: timestamp {t!r} is not a time and {stamp}; skipped")
                return
            if stamp is not None:
                self.retime(rid, tid, t, f"its header stamp {stamp}")
            elif self.prev is not None:
                self.retime(rid, tid, t, f"the previous row's time {self.prev} (it has no header stamp)")
                stamp = self.prev
            else:
                self.waiting.append((len(self.ts), rid, tid, t))
            t = stamp
        if t is not None:
            for at, wid, wtid, wt in self.waiting:
                self.ts[at] = t
                self.retime(wid, wtid, wt, f"the next row's time {t} (it has no header stamp, no row before it a time)")
            self.waiting.clear()
            self.prev = t
        self.ids.append(rid)
        self.tids.append(tid)
        self.ts.append(0 if t is None else t)

    def finish(self) -> tuple[Any, Any, Any]:
        """Report what is left to say; (row ids, topic ids, timestamps) in (timestamp, id) order."""
        for _at, wid, wtid, wt in self.waiting:  # no row of the file has a time
            self.retime(wid, wtid, wt, "time 0 (it has no header stamp, no row of the file a time)")
        if self.bad:
            self.rep.bad_messages += self.bad
            if self.bad > 5:
                self.warn(f"{self.db.path}: {self.bad} message rows in all had no valid topic or no message; skipped")
        if self.retimed > 5:
            self.warn(f"{self.db.path}: {self.retimed} message rows in all had no valid timestamp; their messages "
                      "are kept at their header stamps (else a neighbouring row's time)")
        a_ids = np.asarray(self.ids, dtype=np.int64)
        a_ts = np.asarray(self.ts, dtype=np.int64)
        order = np.lexsort((a_ids, a_ts))
        return a_ids[order], np.asarray(self.tids, dtype=np.int64)[order], a_ts[order]


def sniff_storage(f: Path) -> str:
    """What the file ``f`` holds by its first bytes: "sqlite", "mcap" or "" (neither)."""
    with open(f, "rb") as fh:
        head = fh.read(16)
    if head.startswith(b"SQLite format 3\x00"):
        return "sqlite"
    if head.startswith(b"\x89MCAP0\r\n"):
        return "mcap"
    return ""

"""ROS 2 bags (sqlite3 or mcap storage), streaming raw CDR bytes.

What the storage files hold is the truth; ``metadata.yaml`` is only checked against it. Every
``.db3`` and ``.mcap`` file of the bag directory (and every file the metadata names) is opened on
its own, so a damaged or foreign file costs only its own messages:

* a ``.db3`` is read with sqlite (read-only, immutable): topics and message definitions from its
  own tables; rows located by id one at a time, so a damaged page loses only the rows on it; a
  cut file whose header claims more pages than it has is read from a private temporary copy with
  the page count corrected; rows with an unknown topic or data that is not a blob are reported
  and skipped; a row whose timestamp is not a non-negative integer keeps its message at the
  message's header stamp (else the previous row's time), reported; messages come in log-time
  order (timestamp, then row id);
* an ``.mcap`` file is read by :class:`memlog.io.mcap.McapLog` with all its damage handling;
* ``NAME.zstd`` (file-compressed storage) is decompressed to a temporary file first.

What opening learned (the row index of every ``.db3``, temporary copies, decompressed files,
the channels) is kept for the next reader of the same bag (:mod:`memlog.io._opened`): a bag is
decompressed, copied or indexed once per process, not once per reader. Frame indices come from
the rows and the MCAP files' frame tables (:mod:`memlog.io.frame_table`).

Files merge in log-time order. A metadata.yaml that is missing, does not parse or disagrees with
the storage (files, topics, types, counts, compression) is reported as a damaged index.
"""

from __future__ import annotations

import copy
import functools
import heapq
import os
import shutil
import sqlite3
import struct
import tempfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import numpy as np

from memlog.errors import LogReadError
from memlog.io._damage import MAX_CHUNK_BYTES, check_regular_file
from memlog.io._opened import file_key, learned, release
from memlog.io.base import LogReader
from memlog.io.frame_table import FrameTable
from memlog.io.records import ChannelInfo, RawMessage, ReadReport, SchemaInfo
from memlog.io.types import LogInfo

__all__ = ["Ros2BagLog"]

_ZSTD = b"\x28\xb5\x2f\xfd"
_PROBE = 256  # rows looked up one by one after a damaged page before jumping ahead


class _FileBad(Exception):
    """A storage file that cannot be read at all (the bag goes on without it)."""


def _inflate(data: bytes) -> bytes:
    """A zstd-compressed message (message-mode compression), bounded."""
    import zstandard

    with zstandard.ZstdDecompressor().stream_reader(data, read_across_frames=True) as r:
        out: bytes = r.read(MAX_CHUNK_BYTES + 1)
    if len(out) > MAX_CHUNK_BYTES:
        raise ValueError("message inflates to more than 2 GiB")
    return out


class _Db3:
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
                raise _FileBad(f"sqlite cannot read it ({exc2})") from None
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
            raise _FileBad(f"sqlite cannot open it ({exc})") from None

    def _patched_copy(self, why: Exception) -> sqlite3.Connection:
        """A private copy whose header page count matches the file (a cut file's header claims
        pages it lost, and sqlite then refuses every page)."""
        with open(self.path, "rb") as fh:
            head = fh.read(100)
            if len(head) < 100 or not head.startswith(b"SQLite format 3\x00"):
                raise _FileBad(f"not an sqlite3 database ({why})")
            page = struct.unpack(">H", head[16:18])[0]
            page = 65536 if page == 1 else page
            size = os.fstat(fh.fileno()).st_size
            pages = -(-size // page) if page else 0
            if pages == struct.unpack(">I", head[28:32])[0]:
                raise _FileBad(f"sqlite cannot read it ({why})")
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
        import numpy as np

        if self._rows is not None:
            return self._rows
        ids: list[int] = []
        tids: list[int] = []
        ts: list[int] = []
        rep = self.owner.report
        bad = 0
        retimed = 0
        prev: int | None = None  # the time of the row before (row id order: the order of recording)
        waiting: list[tuple[int, int, Any, Any]] = []  # (place in ts, row id, topic id, timestamp): no time yet
        last = -(1 << 63)
        damaged_at: int | None = None

        def retime(rid: int, tid: int, t: Any, how: str) -> None:
            nonlocal retimed
            if rep.count("retimed_messages", (str(self.path), rid)):
                retimed += 1
                if retimed <= 5:
                    self.owner.warn(f"{self.path}: topic {self.topics[tid][0]}: message row {rid}: timestamp {t!r} "
                                    f"is not a time; its message is kept at {how}")

        def add(rid: Any, tid: Any, t: Any) -> None:
            nonlocal bad, prev
            if tid not in self.topics:
                bad += 1
                if bad <= 5:
                    self.owner.warn(f"{self.path}: message row {rid}: topic id {tid!r} is not in its topics table; "
                                    "skipped")
                return
            if type(t) is not int or t < 0:
                stamp = self._stamp(rid, tid, header_stamp)
                if isinstance(stamp, str):  # no message to keep
                    bad += 1
                    if bad <= 5:
                        self.owner.warn(f"{self.path}: message row {rid}: timestamp {t!r} is not a time and {stamp}; "
                                        "skipped")
                    return
                if stamp is not None:
                    retime(rid, tid, t, f"its header stamp {stamp}")
                elif prev is not None:
                    retime(rid, tid, t, f"the previous row's time {prev} (it has no header stamp)")
                    stamp = prev
                else:
                    waiting.append((len(ts), rid, tid, t))
                t = stamp
            if t is not None:
                for at, wid, wtid, wt in waiting:
                    ts[at] = t
                    retime(wid, wtid, wt, f"the next row's time {t} (it has no header stamp, no row before it a time)")
                waiting.clear()
                prev = t
            ids.append(rid)
            tids.append(tid)
            ts.append(0 if t is None else t)

        while True:
            try:
                for rid, tid, t in self.con.execute(
                        "SELECT id, topic_id, timestamp FROM messages WHERE id > ? ORDER BY id", (last,)):
                    add(rid, tid, t)
                    last = rid
                break
            except sqlite3.DatabaseError as exc:
                if damaged_at is None:
                    damaged_at = last
                    rep.truncated = True
                    self.owner.warn(f"{self.path}: database damaged after message row {last} ({exc}); "
                                    "reading the rows that are left one by one")
                nxt = self._probe(last)
                if nxt is None:
                    break
                add(*nxt)
                last = nxt[0]
        for _at, wid, wtid, wt in waiting:  # no row of the file has a time
            retime(wid, wtid, wt, "time 0 (it has no header stamp, no row of the file a time)")
        if bad:
            rep.bad_messages += bad
            if bad > 5:
                self.owner.warn(f"{self.path}: {bad} message rows in all had no valid topic or no message; skipped")
        if retimed > 5:
            self.owner.warn(f"{self.path}: {retimed} message rows in all had no valid timestamp; their messages are "
                            "kept at their header stamps (else a neighbouring row's time)")
        a_ids = np.asarray(ids, dtype=np.int64)
        a_ts = np.asarray(ts, dtype=np.int64)
        order = np.lexsort((a_ids, a_ts))
        self._rows = (a_ids[order], np.asarray(tids, dtype=np.int64)[order], a_ts[order])
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
                return _inflate(data)
            except Exception as exc:  # noqa: BLE001 - zstd errors have no common base
                return f"its zstd data does not decompress ({exc})"
        return data


def _read_metadata(d: Path) -> tuple[dict[str, Any] | None, str]:
    p = d / "metadata.yaml"
    if not p.exists():
        return None, "metadata.yaml is missing"
    try:
        check_regular_file(str(p))
        from ruamel.yaml import YAML

        with open(p, encoding="utf-8") as fh:
            doc = YAML(typ="safe", pure=True).load(fh)
        info = doc["rosbag2_bagfile_information"]
        if not isinstance(info, dict):
            raise TypeError("rosbag2_bagfile_information is not a mapping")
        return info, ""
    except Exception as exc:  # noqa: BLE001 - yaml, unicode, key and type errors all mean: not usable
        return None, f"metadata.yaml does not parse ({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''})"


_SRC_BITS = 48  # a frame table container: (source << 48) | row id or chunk offset


@dataclass
class _Learned:
    """What opening one bag learned; shared by its readers in a process (it owns the sqlite
    connections and the temporary files)."""

    said: set[str] = field(default_factory=set)
    dbs: list[_Db3] = field(default_factory=list)
    mcap_files: list[Path] = field(default_factory=list)
    tmps: list[IO[bytes]] = field(default_factory=list)
    chans: dict[int, ChannelInfo] = field(default_factory=dict)
    gid: dict[tuple[int, int], int] = field(default_factory=dict)  # (source, local id) -> channel id here
    by_topic: dict[tuple[str, str], int] = field(default_factory=dict)
    tables: dict[str, FrameTable] = field(default_factory=dict)
    report: ReadReport | None = None

    def close(self) -> None:
        for db in self.dbs:
            db.close()
        for tmp in self.tmps:
            tmp.close()
        self.dbs, self.tmps = [], []


class Ros2BagLog(LogReader):
    """A ROS 2 bag directory (sqlite3 or mcap storage). Messages keep their CDR bytes."""

    format = "ros2bag"
    profile = "ros2"

    def __init__(self, path: str | os.PathLike[str]) -> None:
        super().__init__(path)
        self._mcaps: list[LogReader] = []
        self._key: Any = None
        self._decoders: dict[int, Any] = {}  # channel id -> deserializer (header stamps of rows without a time)
        key = file_key("ros2bag", self.path)
        try:
            self._l, new = learned(key, self._learn)
            self._key = key
            self._said = self._l.said
            if not new:
                if self._l.report is not None:
                    self._learned_before(self._l.report)
                for f in self._l.mcap_files:
                    self._attach_mcap(f)
        except BaseException:
            self.close()
            raise

    @property
    def _dbs(self) -> list[_Db3]:
        return self._l.dbs

    @property
    def _chans(self) -> dict[int, ChannelInfo]:
        return self._l.chans

    @property
    def _gid(self) -> dict[tuple[int, int], int]:
        return self._l.gid

    @property
    def _by_topic(self) -> dict[tuple[str, str], int]:
        return self._l.by_topic

    def _learn(self) -> _Learned:
        self._l = lrn = _Learned()
        self._said = lrn.said
        d = Path(self.path)
        meta, why = _read_metadata(d)
        files = self._storage_files(d, meta)
        failed = []
        try:
            for f in files:
                try:
                    self._open_file(f)
                except (_FileBad, LogReadError) as exc:
                    self.report.skipped_files += 1
                    msg = str(exc) if isinstance(exc, LogReadError) else f"{f}: {exc}"
                    failed.append(msg)
                    self.warn(f"{msg}; the bag goes on without this file")
            if not lrn.dbs and not self._mcaps:
                raise LogReadError(f"{d}: ROS 2 bag has no readable storage file"
                                   + (f" ({'; '.join(failed)})" if failed else " (no .db3 or .mcap file)"))
            for src, db in enumerate(lrn.dbs):  # every row's place, once (its warnings go into this report)
                db.rows(functools.partial(self._header_stamp, src))
            self._check_metadata(meta, why, files)
        except BaseException:
            lrn.close()
            raise
        lrn.report = copy.deepcopy(self.report)
        return lrn

    # -- opening -------------------------------------------------------------------
    @staticmethod
    def _storage_files(d: Path, meta: dict[str, Any] | None) -> list[Path]:
        names: list[str] = []
        if meta is not None:
            rel = meta.get("relative_file_paths")
            if isinstance(rel, list):
                names += [r for r in rel if isinstance(r, str) and r and "/" not in r and r not in (".", "..")]
        for p in sorted(d.iterdir()):
            if p.name.endswith((".db3", ".mcap", ".db3.zstd", ".mcap.zstd")) and p.name not in names:
                names.append(p.name)
        return [d / n for n in names]

    def _open_file(self, f: Path) -> None:
        if not f.exists():
            raise _FileBad("named in metadata.yaml but missing")
        check_regular_file(str(f))
        name = f.name
        if name.endswith(".zstd"):
            f = self._unzstd(f)
            name = name.removesuffix(".zstd")
        kind = _sniff(f)
        if kind == "sqlite":
            self._add_db(_Db3(f, self))
        elif kind == "mcap":
            self._l.mcap_files.append(f)
            self._attach_mcap(f)
        else:
            raise _FileBad(f"not {'an sqlite3 database' if name.endswith('.db3') else 'an MCAP file' if name.endswith('.mcap') else 'a storage file memlog reads (sqlite3 or MCAP)'}")

    def _unzstd(self, f: Path) -> Path:
        import zstandard

        tmp = tempfile.NamedTemporaryFile(prefix="memlog-", suffix=f.name.removesuffix(".zstd")[-5:])
        self._l.tmps.append(tmp)
        try:
            with open(f, "rb") as src:
                zstandard.ZstdDecompressor().copy_stream(src, tmp)
        except Exception as exc:  # noqa: BLE001 - zstd errors have no common base
            raise _FileBad(f"does not decompress ({exc})") from None
        tmp.flush()
        return Path(tmp.name)

    def _attach_mcap(self, f: Path) -> None:
        """Open the MCAP storage file ``f`` (its damage goes into this bag's report)."""
        from memlog.io.mcap import McapLog

        sub = McapLog(f)
        self.report.merge(sub.report)
        sub.report = self.report
        sub.on_warning = lambda text: self.on_warning(text)
        self._add_mcap(sub)

    def _channel_id(self, src: int, local: int, topic: str, msgtype: str, make: Any) -> None:
        key = (topic, msgtype)
        gid = self._by_topic.get(key)
        if gid is None:
            gid = self._by_topic[key] = len(self._by_topic) + 1
            self._chans[gid] = make(gid)
        self._gid[(src, local)] = gid

    def _add_db(self, db: _Db3) -> None:
        src = len(self._dbs)
        self._dbs.append(db)
        for tid, (name, typ, ser, qos) in db.topics.items():
            def make(gid: int, name: str = name, typ: str = typ, ser: str = ser, qos: str = qos) -> ChannelInfo:
                enc, text = db.msgdefs.get(typ, ("", ""))
                if not text.strip():
                    text = _typestore_msgdef(typ)
                    enc = "ros2msg"
                meta = {"offered_qos_profiles": qos} if qos else {}
                return ChannelInfo(gid, name, ser, SchemaInfo(typ, "ros2idl" if enc == "ros2idl" else "ros2msg",
                                                               text.encode()), meta)

            self._channel_id(src, tid, name, typ, make)

    def _header_stamp(self, src: int, tid: int, data: bytes) -> int | None:
        """The header stamp of a message of the ``src``-th ``.db3``'s topic ``tid``, decoded as the
        frame stream decodes it (:func:`memlog.io.camera.header_stamp`); None when it does not
        decode or has no stamp."""
        from memlog.io.camera import header_stamp
        from memlog.io.decoders import make_deserializer

        ch = self._chans[self._gid[(src, tid)]]
        if ch.id not in self._decoders:
            try:
                self._decoders[ch.id] = make_deserializer(ch)
            except Exception:  # noqa: BLE001 - no definition to decode by: no stamp
                self._decoders[ch.id] = None
        dec = self._decoders[ch.id]
        try:
            return None if dec is None else header_stamp(dec(data))
        except Exception:  # noqa: BLE001 - a message that does not decode has no stamp to offer
            return None

    def _add_mcap(self, sub: LogReader) -> None:
        src = -1 - len(self._mcaps)
        self._mcaps.append(sub)
        for ch in sub.channels():
            self._channel_id(src, ch.id, ch.topic, ch.msgtype,
                             lambda gid, ch=ch: ChannelInfo(gid, ch.topic, ch.message_encoding, ch.schema, ch.metadata))

    def _check_metadata(self, meta: dict[str, Any] | None, why: str, files: list[Path]) -> None:
        """Compare metadata.yaml with what the storage holds; a difference is a damaged index."""
        if meta is None:
            self.report.index_damaged = True
            self.warn(f"{self.path}: {why}: reading what the storage files hold")
            return
        problems = []
        rel = meta.get("relative_file_paths")
        named = {r for r in rel if isinstance(r, str)} if isinstance(rel, list) else set()
        found = {f.name for f in files}
        if named != found:
            problems.append(f"it names the files {sorted(named)}, the bag holds {sorted(found)}")
        claimed: dict[tuple[str, str], int] = {}
        for t in meta.get("topics_with_message_count") or []:
            try:
                tm = t["topic_metadata"]
                claimed[(str(tm["name"]), str(tm["type"]))] = int(t["message_count"])
            except (KeyError, TypeError, ValueError):
                problems.append("a topic entry is malformed")
        counts = self.message_counts()
        have = {k: (counts or {}).get(g, 0) for k, g in self._by_topic.items()}
        if set(claimed) != set(have):
            problems.append(f"it lists the topics {sorted(claimed)}, the storage holds {sorted(have)}")
        elif counts is not None and claimed != have:
            problems.append("its message counts differ from the storage's "
                            + ", ".join(f"{k[0]} {claimed[k]} vs {have[k]}" for k in claimed if claimed[k] != have[k]))
        kinds = {"sqlite3"} if self._dbs else set()
        kinds |= {"mcap"} if self._mcaps else set()
        storage = str(meta.get("storage_identifier") or "")
        if storage not in kinds or len(kinds) > 1:
            problems.append(f"its storage is {storage!r}, the files are {' and '.join(sorted(kinds))}")
        mode = str(meta.get("compression_mode") or "").lower()
        fmt = str(meta.get("compression_format") or "").lower()
        zipped = any(f.name.endswith(".zstd") for f in files)
        if (mode == "file") != zipped or (mode not in ("", "none", "file", "message")) or (
                mode in ("file", "message") and fmt != "zstd"):
            problems.append(f"its compression ({mode or 'none'} {fmt}) does not match the files")
        if problems:
            self.report.index_damaged = True
            self.warn(f"{self.path}: metadata.yaml does not match the storage files ({'; '.join(problems)}); "
                      "reading what the storage files hold")

    def close(self) -> None:
        for sub in self._mcaps:
            sub.close()
        self._mcaps = []
        if self._key is not None:
            release(self._key)
            self._key = None

    # -- listing -------------------------------------------------------------------
    def channels(self) -> list[ChannelInfo]:
        return list(self._chans.values())

    def message_counts(self) -> dict[int, int] | None:
        import numpy as np

        out: dict[int, int] = {}
        for src, db in enumerate(self._dbs):
            _, tids, _ = db.rows()
            for tid, n in zip(*np.unique(tids, return_counts=True)):
                gid = self._gid[(src, int(tid))]
                out[gid] = out.get(gid, 0) + int(n)
        for i, sub in enumerate(self._mcaps):
            counts = sub.message_counts()
            if counts is None:
                return None
            for cid, n in counts.items():
                g = self._gid.get((-1 - i, cid))
                if g is not None:
                    out[g] = out.get(g, 0) + n
        return out

    def checksums(self) -> str:
        kinds = {"none"} if self._dbs else set()
        kinds |= {sub.checksums() for sub in self._mcaps}
        if kinds == {"all"}:
            return "all"
        if "unknown" in kinds:
            return "unknown"
        return "some" if kinds & {"all", "some"} else "none"

    def frame_table(self, topic: str) -> FrameTable:
        table = self._l.tables.get(topic)
        if table is not None:
            return table
        parts = []
        for src, db in enumerate(self._dbs):
            ids, tids, ts = db.rows()
            wanted = np.isin(tids, [tid for tid, (name, _t, _s, _q) in db.topics.items() if name == topic])
            parts.append((ts[wanted], ((src + 1) << _SRC_BITS) | ids[wanted], np.zeros(int(wanted.sum()), np.int64)))
        for i, sub in enumerate(self._mcaps):
            if topic in sub.camera_topics():
                t, c, o = sub.frame_table(topic).entries()
                parts.append((t, ((1024 + i) << _SRC_BITS) | c, o))
        return self._l.tables.setdefault(topic, FrameTable.concat(parts))

    def _fill_time_range(self, info: LogInfo) -> None:
        lo, hi = [], []
        for db in self._dbs:
            _, _, ts = db.rows()
            if len(ts):
                lo.append(int(ts[0]))
                hi.append(int(ts[-1]))
        for sub in self._mcaps:
            part = LogInfo(sub.path, sub.format, 0)
            sub._fill_time_range(part)
            if part.start_ns is not None and part.end_ns is not None:
                lo.append(part.start_ns)
                hi.append(part.end_ns)
        if lo:
            info.start_ns, info.end_ns = min(lo), max(hi)
        info.storage = "+".join((["sqlite3"] if self._dbs else []) + (["mcap"] if self._mcaps else []))

    # -- messages ------------------------------------------------------------------
    def _iter_messages(
        self, topics: set[str] | None, start_ns: int | None, end_ns: int | None, log_time_order: bool
    ) -> Iterator[RawMessage]:
        its = [self._db_messages(i, topics, start_ns, end_ns) for i in range(len(self._dbs))]
        its += [self._mcap_messages(i, topics, start_ns, end_ns, log_time_order) for i in range(len(self._mcaps))]
        if len(its) == 1:
            yield from its[0]
        else:
            yield from heapq.merge(*its, key=lambda m: m.log_time)

    def _db_messages(self, src: int, topics: set[str] | None, start_ns: int | None,
                     end_ns: int | None) -> Iterator[RawMessage]:
        import numpy as np

        db = self._dbs[src]
        ids, tids, ts = db.rows()
        keep = np.ones(len(ids), dtype=bool)
        if topics is not None:
            keep &= np.isin(tids, [t for t, v in db.topics.items() if v[0] in topics])
        if start_ns is not None:
            keep &= ts >= start_ns
        if end_ns is not None:
            keep &= ts < end_ns
        for rid, tid, t in zip(ids[keep].tolist(), tids[keep].tolist(), ts[keep].tolist()):
            data = db.data(rid)
            if isinstance(data, str):
                if self.report.count("bad_messages", (str(db.path), rid)):
                    self.warn(f"{db.path}: message row {rid} (log time {t}): {data}; skipped")
                continue
            yield RawMessage(self._chans[self._gid[(src, tid)]], t, t, 0, data, (((src + 1) << _SRC_BITS) | rid, 0))

    def _mcap_messages(self, i: int, topics: set[str] | None, start_ns: int | None, end_ns: int | None,
                       log_time_order: bool) -> Iterator[RawMessage]:
        sub = self._mcaps[i]
        for m in sub._iter_messages(topics, start_ns, end_ns, log_time_order):
            gid = self._gid.get((-1 - i, m.channel.id))
            if gid is None:  # a channel the file defined only inside its data
                self._channel_id(-1 - i, m.channel.id, m.channel.topic, m.channel.msgtype,
                                 lambda g, ch=m.channel: ChannelInfo(g, ch.topic, ch.message_encoding, ch.schema,
                                                                     ch.metadata))
                gid = self._gid[(-1 - i, m.channel.id)]
            where = None if m.where is None else (((1024 + i) << _SRC_BITS) | m.where[0], m.where[1])
            yield RawMessage(self._chans[gid], m.log_time, m.publish_time, m.sequence, m.data, where)


def _sniff(f: Path) -> str:
    with open(f, "rb") as fh:
        head = fh.read(16)
    if head.startswith(b"SQLite format 3\x00"):
        return "sqlite"
    if head.startswith(b"\x89MCAP0\r\n"):
        return "mcap"
    return ""


def _typestore_msgdef(msgtype: str) -> str:
    from rosbags.typesys import Stores, get_typestore

    try:
        text, _ = get_typestore(Stores.ROS2_HUMBLE).generate_msgdef(msgtype, ros_version=2)
    except Exception:  # noqa: BLE001 - an unknown type simply has no definition to offer
        return ""
    return str(text)

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
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import numpy as np

from memlog.errors import LogReadError
from memlog.io._damage import check_regular_file
from memlog.io._opened import file_key, holder, learned, release
from memlog.io.base import LogReader
from memlog.io.frame_table import FrameTable
from memlog.io.records import ChannelInfo, RawMessage, ReadReport, SchemaInfo
from memlog.io.rosbag2.metadata import metadata_problems, read_metadata
from memlog.io.rosbag2.storage import Db3Storage, StorageFileBad, sniff_storage
from memlog.io.types import LogInfo

__all__ = ["Ros2BagLog"]

_SRC_BITS = 48  # a frame table container: (source << 48) | row id or chunk offset


@dataclass
class _Learned:
    """What opening one bag learned; shared by its readers in a process (it owns the sqlite
    connections and the temporary files)."""

    said: set[str] = field(default_factory=set)
    dbs: list[Db3Storage] = field(default_factory=list)
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
            self._holder = holder()
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
    def _dbs(self) -> list[Db3Storage]:
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
        meta, why = read_metadata(d)
        files = self._storage_files(d, meta)
        failed = []
        try:
            for f in files:
                try:
                    self._open_file(f)
                except (StorageFileBad, LogReadError) as exc:
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
            raise StorageFileBad("named in metadata.yaml but missing")
        check_regular_file(str(f))
        name = f.name
        if name.endswith(".zstd"):
            f = self._unzstd(f)
            name = name.removesuffix(".zstd")
        kind = sniff_storage(f)
        if kind == "sqlite":
            self._add_db(Db3Storage(f, self))
        elif kind == "mcap":
            self._l.mcap_files.append(f)
            self._attach_mcap(f)
        else:
            raise StorageFileBad(f"not {'an sqlite3 database' if name.endswith('.db3') else 'an MCAP file' if name.endswith('.mcap') else 'a storage file memlog reads (sqlite3 or MCAP)'}")

    def _unzstd(self, f: Path) -> Path:
        import zstandard

        tmp = tempfile.NamedTemporaryFile(prefix="memlog-", suffix=f.name.removesuffix(".zstd")[-5:])
        self._l.tmps.append(tmp)
        try:
            with open(f, "rb") as src:
                zstandard.ZstdDecompressor().copy_stream(src, tmp)
        except Exception as exc:  # noqa: BLE001 - zstd errors have no common base
            raise StorageFileBad(f"does not decompress ({exc})") from None
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

    def _add_db(self, db: Db3Storage) -> None:
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
        kinds = {"sqlite3"} if self._dbs else set()
        kinds |= {"mcap"} if self._mcaps else set()
        problems = metadata_problems(meta, files, self.message_counts(), self._by_topic, kinds)
        if problems:
            self.report.index_damaged = True
            self.warn(f"{self.path}: metadata.yaml does not match the storage files ({'; '.join(problems)}); "
                      "reading what the storage files hold")

    def close(self) -> None:
        for sub in self._mcaps:
            sub.close()
        self._mcaps = []
        if self._key is not None:
            release(self._key, self._holder)
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


def _typestore_msgdef(msgtype: str) -> str:
    from rosbags.typesys import Stores, get_typestore

    try:
        text, _ = get_typestore(Stores.ROS2_HUMBLE).generate_msgdef(msgtype, ros_version=2)
    except Exception:  # noqa: BLE001 - an unknown type simply has no definition to offer
        return ""
    return str(text)

"""Damaged copies of real logs and what an honest reader must get from them.

Used by ``tests/test_damage_sweep.py`` (a fast subset) and ``benchmarks/damage_sweep.py`` (the
whole sweep). Each :class:`Case` builds one damaged or wrong input from an intact log and knows,
computed independently of memlog's readers (mcap's own stream reader, rosbags, sqlite row
lookups), which messages survive the damage intact: a reader must return every one of them.
:func:`run_case` runs the frame stream, ``inspect`` and ``convert`` on it and records the outcome.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import os
import random
import shutil
import signal
import sqlite3
import struct
import tempfile
import time
import zlib
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

Key = tuple[str, int, bytes]  # (topic, log time, message bytes)

MCAP_MAGIC = b"\x89MCAP0\r\n"


# ----------------------------------------------------------------------------- independent truth


@dataclass
class Piece:
    """A byte range of the intact file and the messages that live in it (a chunk, a row...)."""

    start: int
    end: int
    keys: list[Key]


def mcap_pieces(path: Path) -> list[Piece]:
    """Chunks (and top-level messages) of an intact MCAP with their byte ranges, read with the
    mcap library's stream reader (not memlog's)."""
    from mcap.records import Channel, Chunk, Message
    from mcap.stream_reader import StreamReader, breakup_chunk

    data = path.read_bytes()
    out: list[Piece] = []
    topics: dict[int, str] = {}
    pos = len(MCAP_MAGIC)
    while pos < len(data):
        op = data[pos]
        (n,) = struct.unpack_from("<Q", data, pos + 1)
        body = data[pos + 9 : pos + 9 + n]
        if op == 0x06:
            rec = next(iter(StreamReader(io.BytesIO(data[pos : pos + 9 + n]), skip_magic=True,
                                         emit_chunks=True).records))
            assert isinstance(rec, Chunk)
            keys = []
            for r in breakup_chunk(rec):
                if isinstance(r, Channel):
                    topics[r.id] = r.topic
                elif isinstance(r, Message):
                    keys.append((topics[r.channel_id], r.log_time, bytes(r.data)))
            out.append(Piece(pos, pos + 9 + n, keys))
        elif op in (0x04, 0x05):
            rec = next(iter(StreamReader(io.BytesIO(data[pos : pos + 9 + n]), skip_magic=True).records))
            if isinstance(rec, Channel):
                topics[rec.id] = rec.topic
            elif isinstance(rec, Message):
                out.append(Piece(pos, pos + 9 + n, [(topics[rec.channel_id], rec.log_time, bytes(rec.data))]))
        elif op in (0x0F, 0x02):
            break
        pos += 9 + n
    del body
    return out


def has_chunk_crcs(path: Path) -> bool:
    """Whether every chunk of an intact MCAP carries a CRC (flipped bytes are then detectable)."""
    from mcap.records import Chunk
    from mcap.stream_reader import StreamReader

    with open(path, "rb") as fh:
        chunks = [r for r in StreamReader(fh, emit_chunks=True).records if isinstance(r, Chunk)]
    return bool(chunks) and all(c.uncompressed_crc != 0 for c in chunks)


def ros1_pieces(path: Path) -> list[Piece]:
    """Chunks of an intact ROS 1 bag with their byte ranges and messages, from rosbags."""
    import heapq

    from rosbags.rosbag1 import Reader

    out: dict[int, Piece] = {}
    with Reader(path) as r:
        entries = list(heapq.merge(*[r.indexes[c.id] for c in r.connections]))
        for e, (conn, t, raw) in zip(entries, r.messages()):
            ch = r.chunks[e.chunk_pos]
            p = out.setdefault(e.chunk_pos, Piece(e.chunk_pos, ch.datapos + ch.datasize, []))
            p.keys.append((_ros1_topic(conn.topic), t, bytes(raw)))
    return sorted(out.values(), key=lambda p: p.start)


def _ros1_topic(t: str) -> str:
    return t


def sqlite_rows(db: Path, topics_from: Path | None = None) -> list[Key]:
    """Every row of a (possibly damaged) .db3 that sqlite can read by id, looked up one by one
    from id 1 to the intact file's last id, in a private copy whose header page count matches
    the file (what a careful person would do by hand)."""
    ref = topics_from or db
    con = sqlite3.connect(f"file:{ref}?immutable=1", uri=True)
    max_id = con.execute("SELECT max(id) FROM messages").fetchone()[0] or 0
    names = dict(con.execute("SELECT id, name FROM topics"))
    con.close()
    with tempfile.TemporaryDirectory() as tmp:
        copy = Path(tmp) / "copy.db3"
        shutil.copy(db, copy)
        size = copy.stat().st_size
        with open(copy, "r+b") as fh:
            head = fh.read(100)
            if len(head) == 100 and head.startswith(b"SQLite format 3\x00"):
                page = struct.unpack(">H", head[16:18])[0] or 65536
                fh.seek(28)
                fh.write(struct.pack(">I", -(-size // page)))
        keys: list[Key] = []
        try:
            con = sqlite3.connect(f"file:{copy}?immutable=1", uri=True)
            for rid in range(1, max_id + 1):
                try:
                    row = con.execute("SELECT topic_id, timestamp, data FROM messages WHERE id = ?", (rid,)).fetchone()
                except sqlite3.DatabaseError:
                    continue
                if row and row[0] in names and type(row[1]) is int and row[1] >= 0 and isinstance(row[2], bytes):
                    keys.append((names[row[0]], row[1], bytes(row[2])))
            con.close()
        except sqlite3.DatabaseError:
            pass
    return keys


def keys_of(log: Any) -> list[Key]:
    return [(m.channel.topic, m.log_time, bytes(m.data)) for m in log.messages()]


# ------------------------------------------------------------------------------------- cases


@dataclass
class Case:
    """One damaged input: ``build(dir)`` writes it and returns its path; ``expect(path)`` gives the
    messages that must come back (None: no claim); ``checksummed`` when flipped bytes are
    detectable (every message returned must then be an original one)."""

    source: str
    kind: str
    name: str
    build: Callable[[Path], Path]
    expect: Callable[[Path], list[Key] | None]
    checksummed: bool = False
    original: Callable[[], list[Key]] | None = None
    bad_frames: int = 0  # frames that must be reported as not decodable


def _copy(src: Path, dst_dir: Path) -> Path:
    dst = dst_dir / src.name
    if src.is_dir():
        shutil.copytree(src, dst)
    else:
        shutil.copy(src, dst)
    os.chmod(dst, 0o644 if dst.is_file() else 0o755)
    return dst


def _patch(src: Path, fn: Callable[[bytearray], bytes | bytearray], name: str | None = None) -> Callable[[Path], Path]:
    def build(d: Path) -> Path:
        out = d / (name or src.name)
        out.write_bytes(bytes(fn(bytearray(src.read_bytes()))))
        return out

    return build


def _survivors(pieces: list[Piece], hit: Callable[[Piece], bool]) -> list[Key]:
    return [k for p in pieces if not hit(p) for k in p.keys]


def _mcap_layout(data: bytes) -> tuple[int, int, list[tuple[int, int, int]]]:
    """(summary_start, footer_pos, [(offset, opcode, length)] of summary records)."""
    footer = len(data) - 8 - 29
    start = struct.unpack_from("<Q", data, footer + 9)[0]
    recs = []
    pos = start
    while pos < footer:
        op = data[pos]
        (n,) = struct.unpack_from("<Q", data, pos + 1)
        recs.append((pos, op, n))
        pos += 9 + n
    return start, footer, recs


def _fix_summary_crc(b: bytearray) -> bytearray:
    start, footer, _ = _mcap_layout(bytes(b))
    crc = zlib.crc32(bytes(b[footer : footer + 25]), zlib.crc32(bytes(b[start:footer])))
    struct.pack_into("<I", b, footer + 25, crc)
    return b


def mcap_cases(src: Path, rng: random.Random, n_trunc: int, n_flip: int) -> list[Case]:
    data = src.read_bytes()
    pieces = mcap_pieces(src)
    allk = [k for p in pieces for k in p.keys]
    start, footer, srecs = _mcap_layout(data)
    cases: list[Case] = []
    name = src.name

    def add(kind: str, label: str, fn: Callable[[bytearray], bytes | bytearray], expect: list[Key] | None) -> None:
        cases.append(Case(name, kind, f"{name}:{label}", _patch(src, fn), lambda _p, e=expect: e, crcs,
                          lambda: allk))

    crcs = has_chunk_crcs(src)
    cuts = sorted({rng.randrange(9, len(data)) for _ in range(n_trunc)} | {p.end for p in pieces[:3]}
                  | {len(MCAP_MAGIC), start, len(data) - 1})
    for at in cuts:
        add("truncate", f"cut@{at}", lambda b, at=at: b[:at], _survivors(pieces, lambda p, at=at: p.end > at))
    for at in sorted({rng.randrange(len(MCAP_MAGIC), len(data) - 8) for _ in range(n_flip)}):
        add("flip byte", f"flip@{at}", lambda b, at=at: _flip(b, at),
            _survivors(pieces, lambda p, at=at: p.start <= at < p.end))
    for p in pieces[1:3]:  # the record length field of a chunk
        add("flip byte", f"chunk-length@{p.start}", lambda b, at=p.start + 3: _flip(b, at), None)
    zero_at = pieces[len(pieces) // 2].start if pieces else len(data) // 2
    add("zero tail", f"zeros@{zero_at}", lambda b, at=zero_at: b[:at] + bytes(len(b) - at),
        _survivors(pieces, lambda p, at=zero_at: p.end > at))
    add("zero tail", "zeros-appended-32MiB", lambda b: b + bytes(32 << 20), allk)
    add("zero tail", "cut+zeros-32MiB", lambda b, at=zero_at: b[:at] + bytes(32 << 20),
        _survivors(pieces, lambda p, at=zero_at: p.end > at))
    chunk_idx = [(o, n) for o, op, n in srecs if op == 0x08]
    chans = [(o, n) for o, op, n in srecs if op == 0x04]
    if chunk_idx:
        o = chunk_idx[0][0] + 9
        add("index damage", "chunk-index-offset+7 (CRC fixed)",
            lambda b, o=o: _fix_summary_crc(_add_u64(b, o + 16, 7)), allk)
        add("index damage", "chunk-index-offset+7 (CRC kept)", lambda b, o=o: _add_u64(b, o + 16, 7), allk)
        add("index damage", "chunk-length-huge (CRC fixed)",
            lambda b, o=o: _fix_summary_crc(_set_u64(b, o + 24, 1 << 50)), allk)
        add("index damage", "chunk-length-huge (CRC zeroed)",
            lambda b, o=o: _zero_crc(_set_u64(b, o + 24, 1 << 50)), allk)
        if len(chunk_idx) > 1:
            last = chunk_idx[-1]
            add("index damage", "chunk-index-entry-dropped (CRC fixed)",
                lambda b, last=last: _fix_summary_crc(_drop_chunk_index(b, last[0])), allk)
    if chans:
        o = chans[0][0] + 9 + 8  # first topic byte
        add("index damage", "summary-channel-topic-flip (CRC kept)", lambda b, o=o: _flip(b, o), allk)
        add("index damage", "summary-channel-topic-flip (CRC zeroed)", lambda b, o=o: _zero_crc(_flip(b, o)), allk)
    add("index damage", "summary-crc-garbage", lambda b: _set_u32(b, len(b) - 12, 0xDEADBEEF), allk)
    add("index damage", "footer-summary-start-huge", lambda b: _set_u64(b, len(b) - 8 - 20, 1 << 60), allk)
    if pieces and data[pieces[0].start] == 0x06:
        p0 = pieces[0]
        add("absurd size", "chunk-uncompressed-size-huge", lambda b, o=p0.start: _set_u64(b, o + 9 + 16, 1 << 62),
            _survivors(pieces, lambda p, o=p0.start: p.start == o))
        add("absurd size", "chunk-record-length-huge", lambda b, o=p0.start: _set_u64(b, o + 1, 1 << 60),
            _survivors(pieces, lambda p, o=p0.start: p.start == o))
    return cases


def _flip(b: bytearray, at: int) -> bytearray:
    b[at] ^= 0xFF
    return b


def _set_u64(b: bytearray, at: int, v: int) -> bytearray:
    struct.pack_into("<Q", b, at, v)
    return b


def _set_u32(b: bytearray, at: int, v: int) -> bytearray:
    struct.pack_into("<I", b, at, v)
    return b


def _add_u64(b: bytearray, at: int, d: int) -> bytearray:
    return _set_u64(b, at, struct.unpack_from("<Q", b, at)[0] + d)


def _zero_crc(b: bytearray) -> bytearray:
    return _set_u32(b, len(b) - 8 - 4, 0)


def _drop_chunk_index(b: bytearray, at: int) -> bytearray:
    """Turn one ChunkIndex record of the summary into an unknown private record (0x80)."""
    b[at] = 0x80
    return b


def ros1_cases(src: Path, rng: random.Random, n_trunc: int, n_flip: int) -> list[Case]:
    data = src.read_bytes()
    pieces = ros1_pieces(src)
    allk = [k for p in pieces for k in p.keys]
    name = src.name
    cases: list[Case] = []
    hdr = 13  # after the magic line

    def add(kind: str, label: str, fn: Callable[[bytearray], bytes | bytearray], expect: list[Key] | None) -> None:
        cases.append(Case(name, kind, f"{name}:{label}", _patch(src, fn), lambda _p, e=expect: e, False,
                          lambda: allk))

    for at in sorted({rng.randrange(13, len(data)) for _ in range(n_trunc)} | {p.end for p in pieces[:2]}
                     | {hdr, pieces[-1].end if pieces else hdr}):
        add("truncate", f"cut@{at}", lambda b, at=at: b[:at], _survivors(pieces, lambda p, at=at: p.end > at))
    for at in sorted({rng.randrange(13, len(data)) for _ in range(n_flip)}):
        add("flip byte", f"flip@{at}", lambda b, at=at: _flip(b, at),
            _survivors(pieces, lambda p, at=at: p.start <= at < p.end))
    zero_at = pieces[len(pieces) // 2].start
    add("zero tail", f"zeros@{zero_at}", lambda b, at=zero_at: b[:at] + bytes(len(b) - at),
        _survivors(pieces, lambda p, at=zero_at: p.end > at))
    add("zero tail", "cut+zeros-32MiB", lambda b, at=zero_at: b[:at] + bytes(32 << 20),
        _survivors(pieces, lambda p, at=zero_at: p.end > at))
    add("truncate", "magic-line-only", lambda b: b[:13], [])

    def field_at(b: bytes, key: bytes) -> int:
        return b.index(key + b"=", hdr) + len(key) + 1

    for key in (b"conn_count", b"chunk_count"):
        add("index damage", f"bag-header-{key.decode()}=0",
            lambda b, key=key: _set_u32(b, field_at(bytes(b), key), 0), allk)
    add("index damage", "bag-header-index_pos=0", lambda b: _set_u64(b, field_at(bytes(b), b"index_pos"), 0), allk)
    add("index damage", "bag-header-index_pos-huge",
        lambda b: _set_u64(b, field_at(bytes(b), b"index_pos"), 1 << 60), allk)
    # the index data record after the first chunk: garbage in its body
    p0 = pieces[0]
    add("index damage", "index-data-garbage", lambda b, at=p0.end: _garbage_index_data(b, at), allk)
    # the index section: garbage over the chunk info records
    add("index damage", "index-section-garbage", lambda b: _garbage_tail_records(b), allk)
    add("index damage", "index-conn-topic-flip", lambda b: _flip_index_topic(b), allk)
    # a chunk's op byte 5 -> 2 (KeyError 'conn' before)
    add("flip byte", "chunk-op-5-to-2", lambda b, at=p0.start: _chunk_op(b, at), _survivors(pieces, lambda p: p is p0))
    add("absurd size", "chunk-size-field-huge", lambda b, at=p0.start: _chunk_field(b, at, b"size", 0xFFFFFFF0),
        _survivors(pieces, lambda p: p is p0))
    return cases


def _garbage_index_data(b: bytearray, at: int) -> bytearray:
    (hlen,) = struct.unpack_from("<I", b, at)
    body = at + 4 + hlen + 4
    (dlen,) = struct.unpack_from("<I", b, at + 4 + hlen)
    b[body : body + dlen] = bytes((i * 37 + 11) & 0xFF for i in range(dlen))
    return b


def _garbage_tail_records(b: bytearray) -> bytearray:
    at = bytes(b).rindex(b"op=\x06")  # the last chunk info record's header
    for i in range(at + 4, min(len(b), at + 60)):
        b[i] = (i * 53 + 7) & 0xFF
    return b


def _flip_index_topic(b: bytearray) -> bytearray:
    idx = struct.unpack_from("<Q", b, bytes(b).index(b"index_pos=") + 10)[0]
    at = bytes(b).index(b"topic=/", idx) + 7
    b[at] ^= 0x20
    return b


def _chunk_op(b: bytearray, at: int) -> bytearray:
    i = bytes(b).index(b"op=\x05", at)
    b[i + 3] = 0x02
    return b


def _chunk_field(b: bytearray, at: int, key: bytes, v: int) -> bytearray:
    i = bytes(b).index(key + b"=", at) + len(key) + 1
    return _set_u32(b, i, v)


def ros2_cases(src: Path, rng: random.Random, n_trunc: int, n_flip: int) -> list[Case]:
    """Damaged copies of a ROS 2 bag directory (sqlite3 or mcap storage)."""
    name = src.name
    dbs = sorted(src.glob("*.db3"))
    mcaps = sorted(src.glob("*.mcap"))
    cases: list[Case] = []
    if dbs:
        allk = sqlite_rows(dbs[0])
        checksummed = False
    else:
        allk = [k for p in mcap_pieces(mcaps[0]) for k in p.keys]
        checksummed = has_chunk_crcs(mcaps[0])
    store = (dbs or mcaps)[0]

    def add(kind: str, label: str, fn: Callable[[Path], None], expect: Callable[[Path], list[Key] | None]) -> None:
        def build(d: Path, fn: Callable[[Path], None] = fn) -> Path:
            out = _copy(src, d)
            fn(out)
            return out

        cases.append(Case(name, kind, f"{name}:{label}", build, expect, checksummed, lambda: allk))

    def same(_p: Path) -> list[Key]:
        return allk

    def from_db(p: Path) -> list[Key]:
        return sqlite_rows(p / store.name, dbs[0] if dbs else None) if dbs else allk

    meta_edits: dict[str, Callable[[str], str | None]] = {
        "metadata-missing": lambda t: None,
        "metadata-empty": lambda t: "",
        "metadata-garbage": lambda t: "\x00\x01 this: [is not: yaml",
        "metadata-empty-file-list": lambda t: t.replace(f"  - {store.name}\n", "").replace(
            "relative_file_paths:\n", "relative_file_paths: []\n"),
        "metadata-empty-topics": lambda t: t.split("  topics_with_message_count:")[0]
        + "  topics_with_message_count: []\n  version: 9\n",
        "metadata-wrong-type": lambda t: t.replace("type: sensor_msgs/msg/", "type: nonexistent_msgs/msg/"),
        "metadata-wrong-compression": lambda t: t.replace("compression_format: ''", "compression_format: zstd")
        .replace("compression_mode: ''", "compression_mode: FILE"),
        "metadata-wrong-counts": lambda t: t.replace("message_count: ", "message_count: 1"),
        "metadata-wrong-storage": lambda t: t.replace(f"storage_identifier: {'sqlite3' if dbs else 'mcap'}",
                                                      f"storage_identifier: {'mcap' if dbs else 'sqlite3'}"),
    }
    for label, edit in meta_edits.items():
        def fn(p: Path, edit: Callable[[str], str | None] = edit) -> None:
            m = p / "metadata.yaml"
            new = edit(m.read_text())
            if new is None:
                m.unlink()
            else:
                m.write_text(new)

        add("bag metadata", label, fn, same)
    add("bag metadata", "second-garbage-storage-file",
        lambda p: (p / f"zz_garbage{store.suffix}").write_bytes(bytes(range(256)) * 64), same)
    add("bag metadata", "storage-file-is-a-directory", lambda p: (p / f"aa_dir{store.suffix}").mkdir(), same)
    add("bag metadata", "empty-storage-file-added", lambda p: (p / f"aa_empty{store.suffix}").write_bytes(b""), same)
    size = store.stat().st_size
    for at in sorted({rng.randrange(100, size) for _ in range(n_trunc)}):
        def cut(p: Path, at: int = at) -> None:
            f = p / store.name
            f.write_bytes(f.read_bytes()[:at])

        add("truncate", f"cut@{at}", cut, from_db if dbs else (lambda p: None))
    for at in sorted({rng.randrange(100, size) for _ in range(n_flip)}):
        def flip(p: Path, at: int = at) -> None:
            f = p / store.name
            f.write_bytes(bytes(_flip(bytearray(f.read_bytes()), at)))

        add("flip byte", f"flip@{at}", flip, from_db if dbs else (lambda p: None))
    if dbs:
        for label, sql, lost in (
            ("text-timestamp", "UPDATE messages SET timestamp = 'noon' WHERE id = 2", 1),
            ("negative-timestamp", "UPDATE messages SET timestamp = -5 WHERE id = 3", 1),
            ("unknown-topic-id", "UPDATE messages SET topic_id = 99 WHERE id = 1", 1),
            ("text-data", "UPDATE messages SET data = 'not bytes' WHERE id = 1", 1),
            ("reversed-timestamps", "UPDATE messages SET timestamp = 4000000000000000000 - timestamp", 0),
        ):
            def edit_db(p: Path, sql: str = sql) -> None:
                con = sqlite3.connect(p / store.name)
                con.execute(sql)
                con.commit()
                con.close()

            add("wrong values", label, edit_db, from_db)
    return cases


def image_cases(tmp_src: Path) -> list[Case]:
    """MCAPs whose image payloads are garbage or bombs (frames must be reported, not decoded)."""
    cases = []
    for label in ("png-bomb-32768x32768", "jpeg-header-65500x65500", "garbage-jpeg", "truncated-png",
                  "raw-huge-dims", "zero-size-raw"):
        def build(d: Path, label: str = label) -> Path:
            out = d / f"{label}.mcap"
            write_image_log(out, label)
            return out

        cases.append(Case("synthetic", "garbage image", f"images:{label}", build, lambda _p: None, True,
                          bad_frames=1))
    return cases


def png_bomb(w: int, h: int) -> bytes:
    """A small PNG that declares w x h grey pixels (all zero rows, deflated)."""
    def chunk(t: bytes, d: bytes) -> bytes:
        return struct.pack(">I", len(d)) + t + d + struct.pack(">I", zlib.crc32(t + d))

    comp = zlib.compressobj(9)
    row = b"\x00" * (w + 1)
    body = b"".join(comp.compress(row) for _ in range(min(h, 4096))) + comp.flush()
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0))
            + chunk(b"IDAT", body) + chunk(b"IEND", b""))


def write_image_log(out: Path, label: str) -> None:
    """A ros2-profile MCAP with 3 good JPEG frames and one bad frame of the given kind."""
    import cv2
    import numpy as np
    from rosbags.typesys import Stores, get_typestore

    from memlog.io import McapLogWriter

    ts = get_typestore(Stores.ROS2_HUMBLE)
    Header = ts.types["std_msgs/msg/Header"]
    Time = ts.types["builtin_interfaces/msg/Time"]
    Comp = ts.types["sensor_msgs/msg/CompressedImage"]
    Img = ts.types["sensor_msgs/msg/Image"]
    good = cv2.imencode(".jpg", (np.arange(64 * 48) % 251).astype(np.uint8).reshape(48, 64))[1].tobytes()
    bad = {
        "png-bomb-32768x32768": png_bomb(32768, 32768),
        "jpeg-header-65500x65500": good[:2] + bytes.fromhex("ffc0000b08ffdcffdc01011100") + good[2:],
        "garbage-jpeg": b"\xff\xd8\xff" + bytes(range(256)) * 4,
        "truncated-png": cv2.imencode(".png", np.zeros((48, 64), np.uint8))[1].tobytes()[:40],
    }
    comp_def, _ = ts.generate_msgdef("sensor_msgs/msg/CompressedImage", ros_version=2)
    img_def, _ = ts.generate_msgdef("sensor_msgs/msg/Image", ros_version=2)
    t0 = 1_700_000_000_000_000_000
    with McapLogWriter(out, profile="ros2") as w:
        sc = w.add_schema("sensor_msgs/msg/CompressedImage", "ros2msg", comp_def.encode())
        si = w.add_schema("sensor_msgs/msg/Image", "ros2msg", img_def.encode())
        cc = w.add_channel("/cam/compressed", "cdr", sc)
        ci = w.add_channel("/cam/raw", "cdr", si)
        for i in range(4):
            t = t0 + i * 100_000_000
            hdr = Header(Time(t // 10**9, t % 10**9), "cam")
            payload = bad.get(label, good) if i == 2 else good
            if label in ("raw-huge-dims", "zero-size-raw") and i == 2:
                wd, ht = (1 << 20, 1 << 20) if label == "raw-huge-dims" else (0, 0)
                msg = Img(hdr, ht, wd, "mono8", 0, wd, np.zeros(16, np.uint8))
                w.write(ci, t, ts.serialize_cdr(msg, "sensor_msgs/msg/Image"))
                continue
            msg = Comp(hdr, "jpeg" if payload[:2] == b"\xff\xd8" else "png", np.frombuffer(payload, np.uint8))
            w.write(cc, t, ts.serialize_cdr(msg, "sensor_msgs/msg/CompressedImage"))


# ------------------------------------------------------------------------------------ running


class Timeout(BaseException):
    """A case ran past its time limit (BaseException: the CLI's handlers must not swallow it)."""


@contextlib.contextmanager
def time_limit(seconds: int) -> Iterator[None]:
    def on_alarm(signum: int, frame: Any) -> None:
        raise Timeout()

    old = signal.signal(signal.SIGALRM, on_alarm)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)


def _tree_hash(p: Path) -> str:
    h = hashlib.sha256()
    items = sorted(p.rglob("*")) if p.is_dir() else [p]
    for f in items:
        h.update(str(f.relative_to(p.parent)).encode())
        if f.is_file():
            h.update(f.read_bytes())
    return h.hexdigest()


def _cli(args: list[str]) -> tuple[int, str]:
    from memlog.cli.app import main

    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            code = main(args)
        except SystemExit as exc:
            code = int(exc.code or 0)
    return code, err.getvalue()


def _temp_files() -> set[str]:
    return {p.name for p in Path(tempfile.gettempdir()).iterdir()}


@dataclass
class Outcome:
    case: str
    kind: str
    source: str
    codes: dict[str, int] = field(default_factory=dict)
    problems: list[str] = field(default_factory=list)
    seconds: float = 0.0
    got: int = 0
    expected: int | None = None

    @property
    def result(self) -> str:
        if self.problems:
            return "FAIL"
        worst = max(self.codes.values()) if self.codes else 0
        return {0: "clean (exit 0)", 1: "refused (exit 1)", 3: "damage reported (exit 3)"}.get(worst, f"exit {worst}")


def run_case(case: Case, work: Path, limit: int = 120) -> Outcome:
    """Build the case in ``work``, then read it (messages, frames with pixel decoding), inspect it
    and convert it; every problem found is listed in the outcome."""
    from memlog.errors import ImageDecodeError, LogReadError
    from memlog.io import open_log

    out = Outcome(case.name, case.kind, case.source)
    inp_dir = work / "in"
    out_dir = work / "out"
    tmp_dir = work / "tmp"  # the temporary directory of this case (other processes use the system one)
    for d in (inp_dir, out_dir, tmp_dir):
        shutil.rmtree(d, ignore_errors=True)
        d.mkdir(parents=True)
    path = case.build(inp_dir)
    before = _tree_hash(path)
    old_tmp, tempfile.tempdir = tempfile.tempdir, str(tmp_dir)
    temps = _temp_files()
    t0 = time.perf_counter()
    got: list[Key] = []
    bad_frames = 0
    try:
        with time_limit(limit):
            try:
                with open_log(path) as log:
                    log.on_warning = lambda text: None
                    got = keys_of(log)
                    for f in log.frames():
                        try:
                            f.decode_bgr()
                        except ImageDecodeError as exc:
                            log.decode_error(f, exc)
                            bad_frames += 1
                out.codes["read"] = 0 if log.report.ok else 3
            except LogReadError:
                out.codes["read"] = 1
            for cmd in (["inspect", str(path)], ["convert", str(path), "-o", str(out_dir / "out.mcap")]):
                code, err = _cli(cmd)
                out.codes[cmd[0]] = code
                if "internal error" in err or "Traceback" in err:
                    out.problems.append(f"{cmd[0]}: {err.strip().splitlines()[-1][:200]}")
                if code not in (0, 1, 3):
                    out.problems.append(f"{cmd[0]}: exit {code}")
    except Timeout:
        out.problems.append(f"hang: over {limit} s")
    except Exception as exc:  # noqa: BLE001 - a reader that raises anything but LogReadError is a defect
        out.problems.append(f"read raised {type(exc).__name__}: {exc}")
    out.seconds = time.perf_counter() - t0
    out.got = len(got)
    from memlog.io import clear_cache

    clear_cache()  # what opening the log learned (its temporary copies) is kept until the process ends
    if _tree_hash(path) != before:
        out.problems.append("input modified")
    left = _temp_files() - temps
    tempfile.tempdir = old_tmp
    if left:
        out.problems.append(f"temporary files left: {sorted(left)}")
    extra = [p.name for p in out_dir.iterdir() if p.name != "out.mcap"]
    if extra:
        out.problems.append(f"leftover files in the output directory: {extra}")
    conv = out.codes.get("convert")
    if conv not in (0, 3) and (out_dir / "out.mcap").exists():
        out.problems.append("convert failed but left an output")
    if conv in (0, 3) and got:
        with open_log(out_dir / "out.mcap") as back:
            back.on_warning = lambda text: None
            if Counter(keys_of(back)) != Counter(got):
                out.problems.append("the converted log holds other messages than the reader returned")
    if bad_frames < case.bad_frames:
        out.problems.append(f"{bad_frames} frame(s) reported as not decodable, expected {case.bad_frames}")
    expected = case.expect(path)
    if expected is not None:
        out.expected = len(expected)
        missing = Counter(expected) - Counter(got)
        if missing:
            out.problems.append(f"lost {sum(missing.values())} readable message(s) of {len(expected)}")
    if case.checksummed and case.original is not None:
        foreign = Counter(got) - Counter(case.original())
        if foreign:
            out.problems.append(f"{sum(foreign.values())} message(s) that are not in the intact log (damage read as data)")
    original = case.original() if case.original is not None else None
    if original is not None and Counter(got) != Counter(original) and out.codes and max(out.codes.values()) == 0:
        if case.checksummed:
            out.problems.append("damaged input called clean (exit 0) although messages differ")
    return out


# ------------------------------------------------------------------ the whole pipeline on damage


def pipeline_cases(fixtures: Path) -> list[Case]:
    """Damaged copies of the fixture logs with several chunks, for :func:`run_pipeline_case`: a
    chunk failing its CRC in an indexed log, unfinished recordings (cut, cut + zeros), a damaged
    index, a cut ROS 1 bag and a cut ROS 2 sqlite bag."""
    demo = fixtures / "demo.mcap"
    data = demo.read_bytes()
    pieces = mcap_pieces(demo)
    chunks = [p for p in pieces if data[p.start] == 0x06]
    _, _, srecs = _mcap_layout(data)
    ci = [o for o, op, _ in srecs if op == 0x08]
    cases: list[Case] = []

    def add(name: str, build: Callable[[Path], Path], source: str = "demo.mcap") -> None:
        cases.append(Case(source, "pipeline", f"{source}:{name}", build, lambda _p: None))

    for k in (1, len(chunks) // 2):
        at = chunks[k].end - 30  # inside the compressed records of chunk k
        add(f"chunk-{k}-crc", _patch(demo, lambda b, at=at: _flip(b, at)))
    add("cut@70%", _patch(demo, lambda b: b[: int(len(b) * 0.7)]))
    add("cut@85%+zeros", _patch(demo, lambda b: b[: int(len(b) * 0.85)] + bytes(4096)))
    add("cut@85%+chunk-1-crc", _patch(demo, lambda b, at=chunks[1].end - 30: _flip(b, at)[: int(len(b) * 0.85)]))
    if ci:
        add("chunk-index-offset+7", _patch(demo, lambda b, o=ci[0] + 9: _fix_summary_crc(_add_u64(b, o + 16, 7))))
    bag = fixtures / "ros1.bag"
    add("cut@70%", _patch(bag, lambda b: b[: int(len(b) * 0.7)]), "ros1.bag")

    def ros2_cut(d: Path) -> Path:
        out = _copy(fixtures / "ros2_sqlite", d)
        db = next(out.glob("*.db3"))
        db.write_bytes(db.read_bytes()[: int(db.stat().st_size * 0.9)])
        return out

    add("cut@90%", ros2_cut, "ros2_sqlite")
    return cases


def _decodable_frames(path: Path) -> tuple[dict[tuple[str, int], Any], bool]:
    """Every frame of ``path`` that reads and decodes: (topic, index) -> Frame (pixels kept), and
    whether reading them found damage."""
    from memlog.errors import ImageDecodeError
    from memlog.io import open_log

    out = {}
    with open_log(path) as log:
        log.quiet_warnings()
        for f in log.frames():
            try:
                f.decode_bgr()
            except ImageDecodeError:
                log.report.undecodable_frames += 1
                continue
            out[(f.topic, f.index)] = f
        return out, not log.report.ok


def _normalised(path: Path) -> Any:
    from tests.same_outputs import normalised_map

    msgs, scores, meta = normalised_map(path)
    meta = {k: {kk: vv for kk, vv in v.items() if kk not in ("seconds",)} if isinstance(v, dict) else v
            for k, v in meta.items()}
    return msgs, scores, meta.get("memlog_map", {}).get("selection")


def _check_map(out: "Outcome", case: Case, mp: Path, frames: dict[tuple[str, int], Any], label: str) -> None:
    """The map holds only frames of the input, each with its own bytes and its own scores, and
    it was selected from every readable frame."""
    import numpy as np

    from memlog.io import open_log
    from memlog.outputs.annotated import read_scores
    from memlog.scoring.config import ScoreConfig
    from memlog.scoring.scorer import Scorer

    by_time = {(t, f.log_time_ns): f for (t, _), f in frames.items()}
    with open_log(mp) as m:
        meta = dict(m.metadata()).get("memlog_map", {})
        images: dict[int, list[Any]] = {}
        for g in m.frames():  # a raw input frame is written JPEG-encoded on TOPIC/compressed
            images.setdefault(g.log_time_ns, []).append(g)
    if int(meta.get("frames_in", -1)) != len(frames):
        out.problems.append(f"{label}: selected from {meta.get('frames_in')} frames, {len(frames)} are readable")
    scorer = Scorer(ScoreConfig(all_scores=True))
    for topic, recs in read_scores(mp).items():
        for r in recs:
            f = frames.get((topic, r["frame_index"]))
            if f is None or f.log_time_ns != r["log_time"]:
                out.problems.append(f"{label}: {topic} frame {r['frame_index']} of the map is not that frame of the "
                                    "input (another frame's scores)")
                continue
            if by_time.get((topic, r["log_time"])) is not f:
                out.problems.append(f"{label}: two input frames share {topic} log time {r['log_time']}")
            want = f.decode_bgr()
            c = scorer.cheap(want, keep_maps=False)
            if abs(float(c.ss) - float(r["ss"])) > 1e-6 or abs(float(c.es) - float(r["es"])) > 1e-6:
                out.problems.append(f"{label}: {topic} frame {r['frame_index']} carries scores that are not its own")
            same = False
            for g in images.get(r["log_time"], []):
                if g.topic not in (topic, f"{topic}/compressed"):
                    continue
                if g.payload.data == f.payload.data:
                    same = True
                    continue
                img = g.decode_bgr().astype(np.int16)  # re-encoded: nearer this frame than any other
                dist = {k: float(np.abs(img - o.decode_bgr().astype(np.int16)).mean()) for k, o in frames.items()
                        if k[0] == topic and o.decode_bgr().shape == img.shape}
                if dist and min(dist, key=lambda k: dist[k]) == (topic, r["frame_index"]):
                    same = True
            if not same:
                out.problems.append(f"{label}: {topic} frame {r['frame_index']}: the map does not hold its pixels")


def run_pipeline_case(case: Case, work: Path, limit: int = 600) -> Outcome:
    """``memlog map`` (default, and ``--workers 2``), ``memlog batch`` and ``memlog evaluate`` on a
    damaged log: exit 3 (or 1 when nothing can be made), no traceback, hang or partial output; the
    map selected from every readable frame, holds each kept frame's own bytes and scores, and is
    the same on two workers and in batch."""
    import json

    out = Outcome(case.name, case.kind, case.source)
    inp, res = work / "in", work / "out"
    for d in (inp, res):
        shutil.rmtree(d, ignore_errors=True)
        d.mkdir(parents=True)
    path = case.build(inp)
    before = _tree_hash(path)
    frames, damaged = _decodable_frames(path)
    t0 = time.perf_counter()
    n_q = 0
    from memlog.io import open_log

    with open_log(path) as log:
        log.quiet_warnings()
        cams = log.camera_topics()
        if cams:
            from memlog.io.base import FrameWindow

            n_q = log.count_frames(FrameWindow((cams[0],)))
    truth = res / "truth.json"
    truth.write_text(json.dumps({"matches": [[q] for q in range(n_q)]}))
    runs = {
        "map": ["map", str(path), "-o", str(res / "m1.mcap")],
        "map --workers 2": ["map", str(path), "-o", str(res / "m2.mcap"), "--workers", "2"],
        "batch": ["batch", str(path), "-o", str(res / "batch"), "--workers", "2"],
        "evaluate": ["evaluate", "--reference", str(path), "--query", str(path), "--truth", str(truth),
                     "-o", str(res / "eval")],
    }
    try:
        with time_limit(limit):
            for label, args in runs.items():
                code, err = _cli(args)
                out.codes[label] = code
                if "internal error" in err or "Traceback" in err:
                    out.problems.append(f"{label}: {err.strip().splitlines()[-1][:200]}")
                if code not in (1, 3) if damaged else code != 0:
                    out.problems.append(f"{label}: exit {code}{' (damage not reported)' if damaged else ''}: "
                                        f"{err.strip().splitlines()[-1][:160] if err.strip() else ''}")
    except Timeout:
        out.problems.append(f"hang: over {limit} s")
    out.seconds = time.perf_counter() - t0
    out.got = len(frames)
    maps = {"map": res / "m1.mcap", "map --workers 2": res / "m2.mcap",
            "batch": res / "batch" / f"{path.name.removesuffix('.mcap').removesuffix('.bag')}.map.mcap"}
    for label, mp in maps.items():
        code = out.codes.get(label)
        if code in (0, 3) and not mp.exists():
            out.problems.append(f"{label}: exit {code} but no map")
        elif code not in (0, 3) and mp.exists():
            out.problems.append(f"{label}: failed but left a map")
        elif mp.exists():
            _check_map(out, case, mp, frames, label)
    if maps["map"].exists():
        first = _normalised(maps["map"])
        for label in ("map --workers 2", "batch"):
            if maps[label].exists() and _normalised(maps[label]) != first:
                out.problems.append(f"{label}: another map than one process wrote")
    ev = out.codes.get("evaluate")
    if ev in (0, 3) and not (res / "eval" / "results.json").exists():
        out.problems.append("evaluate: exit 0/3 but no results.json")
    left = [p.name for d in (res, res / "batch", res / "eval") if d.exists() for p in d.iterdir()
            if p.name.endswith(".tmp")]
    if left:
        out.problems.append(f"temporary files left: {left}")
    if _tree_hash(path) != before:
        out.problems.append("input modified")
    from memlog.io import clear_cache

    clear_cache()
    return out

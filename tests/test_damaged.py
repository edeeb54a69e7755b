"""Bad input: clear errors naming file/topic/message, reads up to the damage, inputs untouched."""

from __future__ import annotations

import hashlib
import subprocess
import sys
from pathlib import Path

import pytest
from mcap.reader import make_reader

from memlog.errors import ImageDecodeError, LogReadError
from memlog.io import McapLogWriter, open_log
from tests.conftest import FIXTURES


def _sha(p: Path) -> str:
    return hashlib.sha256(p.read_bytes()).hexdigest()


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "memlog", *args], capture_output=True, text=True)


def _frames_and_report(path: Path):  # type: ignore[no-untyped-def]
    with open_log(path) as log:
        frames = list(log.frames())
        return frames, log.report, log.report.warnings


def test_not_a_log(tmp_path: Path) -> None:
    p = tmp_path / "notes.mcap"
    p.write_text("hello, I am not a log\n")
    with pytest.raises(LogReadError, match="notes.mcap: not a log"):
        open_log(p)
    r = _cli("inspect", str(p))
    assert r.returncode == 1 and "not a log" in r.stderr and "Traceback" not in r.stderr
    empty = tmp_path / "empty.bag"
    empty.write_bytes(b"")
    with pytest.raises(LogReadError, match="empty"):
        open_log(empty)


def test_truncated_mcap_is_read_up_to_the_damage(copy_of) -> None:  # type: ignore[no-untyped-def]
    p = copy_of("demo.mcap")
    full, _, _ = _frames_and_report(FIXTURES / "demo.mcap")
    data = p.read_bytes()
    p.write_bytes(data[: len(data) // 2])
    before = _sha(p)
    frames, report, warnings = _frames_and_report(p)
    assert report.truncated and any("truncated" in w and str(p) in w for w in warnings)
    assert 0 < len(frames) < len(full)
    # what was read is exactly the start of the full stream
    assert [(f.topic, f.index, f.payload.data) for f in frames] == [
        (f.topic, f.index, f.payload.data) for f in full[: len(frames)]
    ]
    assert _sha(p) == before
    r = _cli("inspect", str(p))
    assert r.returncode == 3 and "truncated" in r.stderr and "Traceback" not in r.stderr


def _write_uncompressed_copy(src: Path, dst: Path) -> None:
    """An MCAP with uncompressed one-message chunks, so a flipped byte hits exactly one chunk's CRC."""
    with open_log(src) as log, McapLogWriter(dst, profile=log.profile, compression="none", chunk_size=1) as w:
        for m in log.messages():
            w.write_raw(m)


def test_crc_mismatch_skips_one_chunk(tmp_path: Path) -> None:
    p = tmp_path / "crc.mcap"
    _write_uncompressed_copy(FIXTURES / "demo.mcap", p)
    with open(p, "rb") as fh:
        chunks = make_reader(fh).get_summary().chunk_indexes  # type: ignore[union-attr]
    target = sorted(chunks, key=lambda c: c.chunk_start_offset)[3]
    data = bytearray(p.read_bytes())
    data[target.chunk_start_offset + target.chunk_length - 20] ^= 0xFF  # inside the message payload
    p.write_bytes(bytes(data))
    frames, report, warnings = _frames_and_report(p)
    assert report.skipped_chunks == 1
    assert any("CRC" in w and str(target.chunk_start_offset) in w for w in warnings)
    full, _, _ = _frames_and_report(FIXTURES / "demo.mcap")
    assert len(frames) == len(full) - 1  # one message per chunk: exactly one frame lost
    r = _cli("convert", str(p), "-o", str(tmp_path / "out.mcap"))
    assert r.returncode == 3 and "CRC" in r.stderr and "Traceback" not in r.stderr


def test_message_that_does_not_deserialize_is_reported_and_skipped(tmp_path: Path) -> None:
    src = FIXTURES / "demo.mcap"
    p = tmp_path / "badmsg.mcap"
    with open_log(src) as log, McapLogWriter(p, profile="ros2") as w:
        for m in log.messages():
            data = m.data
            if m.channel.topic == "/camera/image/compressed" and m.log_time == 1_700_000_000_200_000_000:
                data = b"\x00\x01\x00\x00\xff\xff\xff\x7f"  # CDR header, then an absurd string length
            w.write(w.channel_for(m.channel), m.log_time, data, m.publish_time, m.sequence)
    frames, report, warnings = _frames_and_report(p)
    assert report.bad_messages == 1
    (w,) = [w for w in warnings if "deserialize" in w]
    assert str(p) in w and "/camera/image/compressed" in w and "message 2" in w
    comp = [f.index for f in frames if f.topic == "/camera/image/compressed"]
    assert comp == [0, 1, 3, 4, 5, 6, 7]  # indices stay positions on the topic


def test_image_that_does_not_decode_names_topic_and_index() -> None:
    with open_log(FIXTURES / "encodings.mcap") as log:
        frames = list(log.frames(["/compressed"]))
        bad = frames[4]
        with pytest.raises(ImageDecodeError) as exc:
            bad.decode_bgr()
        err = log.decode_error(bad, exc.value)
        assert log.report.undecodable_frames == 1
        text = str(err)
        assert "encodings.mcap" in text and "/compressed" in text and "message 4" in text


def test_truncated_ros1_bag(copy_of) -> None:  # type: ignore[no-untyped-def]
    p = copy_of("ros1.bag")
    data = p.read_bytes()
    p.write_bytes(data[: int(len(data) * 0.6)])
    frames, report, warnings = _frames_and_report(p)
    assert report.truncated and any("index" in w for w in warnings)
    full, _, _ = _frames_and_report(FIXTURES / "ros1.bag")
    assert 0 < len(frames) < len(full)
    got = {(f.topic, f.index): f.payload.data for f in frames}
    want = {(f.topic, f.index): f.payload.data for f in full}
    assert all(got[k] == want[k] for k in got)


def test_truncated_ros2_sqlite_bag_gives_clear_error(copy_of) -> None:  # type: ignore[no-untyped-def]
    d = copy_of("ros2_sqlite")
    db = d / "ros2_sqlite.db3"
    data = db.read_bytes()
    db.write_bytes(data[: len(data) // 2])
    r = _cli("inspect", str(d))
    assert r.returncode in (1, 3) and "Traceback" not in r.stderr
    assert "ros2_sqlite" in r.stderr


def test_missing_file_and_usage_errors(tmp_path: Path) -> None:
    r = _cli("inspect", str(tmp_path / "nope.mcap"))
    assert r.returncode == 1 and "no such file" in r.stderr
    r = _cli("convert", str(FIXTURES / "demo.mcap"))
    assert r.returncode == 2  # -o is required
    r = _cli("convert", str(FIXTURES / "demo.mcap"), "-o", str(tmp_path / "missing_dir" / "x.mcap"))
    assert r.returncode == 2 and "does not exist" in r.stderr and not (tmp_path / "missing_dir").exists()


# -- issue 10: damaged input, nothing readable lost, nothing damaged called clean --------------


def _messages(path: Path) -> list[tuple[str, int, bytes]]:
    with open_log(path) as log:
        log.on_warning = lambda text: None
        return [(m.channel.topic, m.log_time, m.data) for m in log.messages()]


def test_inspect_reads_the_data_of_an_indexed_mcap(tmp_path: Path) -> None:
    """A flipped byte inside a chunk of an indexed MCAP: inspect used to trust the summary (exit 0)."""
    p = tmp_path / "crc.mcap"
    _write_uncompressed_copy(FIXTURES / "demo.mcap", p)
    with open(p, "rb") as fh:
        target = make_reader(fh).get_summary().chunk_indexes[2]  # type: ignore[union-attr]
    data = bytearray(p.read_bytes())
    data[target.chunk_start_offset + target.chunk_length - 20] ^= 0xFF
    p.write_bytes(bytes(data))
    r = _cli("inspect", str(p))
    assert r.returncode == 3 and "CRC" in r.stderr and "Traceback" not in r.stderr
    assert "messages:  23" in r.stdout  # the data's count, not the index's 24


def test_inspect_says_when_damage_cannot_be_detected(tmp_path: Path) -> None:
    crc0 = FIXTURES / "ros2_mcap" / "ros2_mcap.mcap"  # rosbags writes chunk CRC 0
    unchunked = tmp_path / "unchunked.mcap"
    from mcap.writer import Writer

    with open(unchunked, "wb") as fh:
        w = Writer(fh, use_chunking=False)
        w.start()
        s = w.register_schema("x", "jsonschema", b"{}")
        c = w.register_channel("/x", "json", s)
        w.add_message(c, log_time=1, data=b"{}", publish_time=1)
        w.finish()
    for path in (FIXTURES / "ros1.bag", FIXTURES / "ros2_sqlite", crc0, unchunked):
        r = _cli("inspect", str(path))
        assert r.returncode == 0 and "no checksums: damage cannot be detected" in r.stdout, (path, r.stdout)
    r = _cli("inspect", str(FIXTURES / "demo.mcap"))
    assert r.returncode == 0 and "covered by a checksum, and each was checked" in r.stdout


def test_zero_filled_tail_is_named_where_the_zeros_start(tmp_path: Path) -> None:
    for name, at_frac in (("demo.mcap", 0.5), ("ros1.bag", 0.5)):
        src = FIXTURES / name
        data = src.read_bytes()
        p = tmp_path / name
        cut = int(len(data) * at_frac)
        p.write_bytes(data[:cut] + bytes(32 << 20))
        with open_log(p) as log:
            log.on_warning = lambda text: None
            n = sum(1 for _ in log.messages())
            text = " ".join(log.report.warnings)
        assert n > 0 and "zero-filled from byte" in text
        start = int(text.split("zero-filled from byte ")[1].split()[0])
        assert start <= cut and bytes(32 << 20).startswith(p.read_bytes()[start:start + 1024])  # zeros from there
        r = _cli("convert", str(p), "-o", str(tmp_path / "out.mcap"))
        assert r.returncode == 3 and "Traceback" not in r.stderr


def test_interrupted_ros1_recordings_exit_3(tmp_path: Path) -> None:
    data = (FIXTURES / "ros1.bag").read_bytes()
    import struct

    at = data.index(b"index_pos=") + len(b"index_pos=")
    index_pos = struct.unpack("<Q", data[at : at + 8])[0]  # where the index section starts
    for label, content in (("no-index", data[:index_pos]), ("magic-only", b"#ROSBAG V2.0\n")):
        p = tmp_path / f"{label}.bag"
        p.write_bytes(content)
        for cmd in (["inspect", str(p)], ["convert", str(p), "-o", str(tmp_path / f"{label}.mcap")]):
            r = _cli(*cmd)
            assert r.returncode == 3 and "Traceback" not in r.stderr, (label, cmd[0], r.stderr)
    assert len(_messages(tmp_path / "no-index.bag")) == len(_messages(FIXTURES / "ros1.bag"))


def test_named_pipe_is_refused_before_opening(tmp_path: Path) -> None:
    import os

    fifo = tmp_path / "drive.mcap"
    os.mkfifo(fifo)
    r = subprocess.run([sys.executable, "-m", "memlog", "inspect", str(fifo)], capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 1 and "named pipe" in r.stderr and str(fifo) in r.stderr


def test_cut_db3_keeps_every_row_sqlite_reads(tmp_path: Path) -> None:
    from tests.conftest import shared
    from tests.damage_kit import sqlite_rows

    src = shared("euroc_micro_ros2_db3")
    d = tmp_path / "bag"
    import shutil

    shutil.copytree(src, d)
    db = next(d.glob("*.db3"))
    db.chmod(0o644)
    db.write_bytes(db.read_bytes()[: db.stat().st_size // 2 + 1234])
    expected = sqlite_rows(db, next(src.glob("*.db3")))
    assert len(expected) > 20
    got = _messages(d)
    assert sorted(got) == sorted(expected)
    assert [t for _, t, _ in got] == sorted(t for _, t, _ in got)  # log-time order
    r = _cli("inspect", str(d))
    assert r.returncode == 3 and "Traceback" not in r.stderr


def test_ros2_sqlite_rows_come_in_log_time_order_and_bad_rows_are_named(tmp_path: Path) -> None:
    import shutil
    import sqlite3

    d = tmp_path / "bag"
    shutil.copytree(FIXTURES / "ros2_sqlite", d)
    db = d / "ros2_sqlite.db3"
    con = sqlite3.connect(db)
    con.execute("UPDATE messages SET timestamp = 4000000000000000000 - timestamp")  # last row first in time
    con.execute("UPDATE messages SET timestamp = 'noon' WHERE id = 2")
    con.commit()
    con.close()
    with open_log(d) as log:
        log.on_warning = lambda text: None
        got = list(log.messages())
        assert [m.log_time for m in got] == sorted(m.log_time for m in got) and len(got) == 4
        assert log.report.retimed_messages == 1  # row 2 kept at its header stamp (tests/test_leftovers.py)
        assert any("row 2" in w and "noon" in w and "ros2_sqlite.db3" in w for w in log.report.warnings)
    r = _cli("convert", str(d), "-o", str(tmp_path / "out.mcap"))
    assert r.returncode == 3 and "internal error" not in r.stderr


def test_pixel_cap_is_checked_from_the_header(monkeypatch: pytest.MonkeyPatch) -> None:
    import cv2
    import numpy as np

    from memlog.io.image import decode_bgr, image_size, set_max_pixels
    from memlog.io.types import ImagePayload
    from memlog.runtime import current, use
    from tests.damage_kit import png_bomb

    bomb = png_bomb(32768, 32768)
    assert len(bomb) < 2_000_000 and image_size(bomb) == (32768, 32768)
    with pytest.raises(ImageDecodeError, match="32768x32768.*max-pixels"):
        decode_bgr(ImagePayload("compressed", "png", bomb))
    img = (np.arange(50 * 70 * 3) % 255).astype(np.uint8).reshape(50, 70, 3)
    for ext in (".png", ".jpg", ".bmp", ".webp", ".ppm"):
        data = cv2.imencode(ext, img)[1].tobytes()
        dec = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
        assert image_size(data) == (dec.shape[1], dec.shape[0]), ext
    with use(current().replace(max_pixels=100_000_000)):  # the context in force now is put back after
        set_max_pixels(70 * 50 - 1)  # configurable: now the small frame is over the cap
        with pytest.raises(ImageDecodeError, match="70x50"):
            decode_bgr(ImagePayload("compressed", "png", cv2.imencode(".png", img)[1].tobytes()))
        with pytest.raises(ImageDecodeError, match="70x50"):
            decode_bgr(ImagePayload("raw", "bgr8", img.tobytes(), 70, 50, 210))
        set_max_pixels(70 * 50)
        assert decode_bgr(ImagePayload("raw", "bgr8", img.tobytes(), 70, 50, 210)).shape == (50, 70, 3)


def test_max_pixels_flag_is_checked() -> None:
    r = _cli("localize", "m.parquet", str(FIXTURES / "demo.mcap"), "-o", "x.parquet", "--max-pixels", "0")
    assert r.returncode == 2 and "--max-pixels" in r.stderr

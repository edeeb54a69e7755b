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

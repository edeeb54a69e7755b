"""One frame numbering for every path, and a damaged or unfinished log read once.

A frame's index is its position in its topic's frame table (:mod:`memlog.io.frame_table`): the
index's entries when the log has a trusted index, else what the one scan of the data found. So
a full stream, a time window starting at any frame, a stride, and the chunks of frames that
workers read (``plan_chunks``) must give every frame the same index, with its own bytes; and a
damaged chunk of an indexed log must not renumber the frames after it (the intact log's numbers
are the independent expectation).
"""

from __future__ import annotations

import logging
import shutil
import struct
from pathlib import Path

import pytest

from memlog.io import clear_cache, open_log
from memlog.io._opened import scans
from memlog.io.base import FrameWindow
from memlog.steps.score import plan_chunks
from tests.conftest import FIXTURES

Frames = dict[tuple[str, int], tuple[int, bytes]]


def _chunks(path: Path) -> list[tuple[int, int]]:
    """(offset, length) of the chunk records of an MCAP file."""
    data = path.read_bytes()
    pos, out = 8, []
    while pos < len(data):
        op, n = data[pos], struct.unpack_from("<Q", data, pos + 1)[0]
        if op == 0x06:
            out.append((pos, n))
        if op == 0x0F:
            break
        pos += 9 + n
    return out


def _flip_in_chunk(src: Path, dst: Path, k: int) -> None:
    b = bytearray(src.read_bytes())
    pos, n = _chunks(src)[k]
    b[pos + 9 + n - 40] ^= 0xFF  # inside the compressed records: CRC or decompression fails
    dst.write_bytes(bytes(b))


def _cut(src: Path, dst: Path, fraction: float) -> None:
    data = src.read_bytes()
    dst.write_bytes(data[: int(len(data) * fraction)])


def _crc_and_cut(src: Path, dst: Path) -> None:
    _flip_in_chunk(src, dst, 2)
    data = dst.read_bytes()
    dst.write_bytes(data[: int(len(data) * 0.8)])


def _ros2_cut(src: Path, dst: Path) -> None:
    shutil.copytree(src, dst)
    db = next(dst.glob("*.db3"))
    data = db.read_bytes()
    db.write_bytes(data[: int(len(data) * 0.8)])


CASES = {
    "mcap-crc": ("demo.mcap", lambda s, d: _flip_in_chunk(s, d, 3)),
    "mcap-cut": ("demo.mcap", lambda s, d: _cut(s, d, 0.7)),
    "mcap-crc+cut": ("demo.mcap", _crc_and_cut),
    "ros1-cut": ("ros1.bag", lambda s, d: _cut(s, d, 0.7)),
    "ros2-sqlite-cut": ("ros2_sqlite", _ros2_cut),
}


@pytest.fixture(autouse=True)
def _fresh() -> None:
    clear_cache()


def _damaged(name: str, tmp_path: Path) -> Path:
    src_name, build = CASES[name]
    dst = tmp_path / src_name
    build(FIXTURES / src_name, dst)
    return dst


def _frames(path: Path, **kw: object) -> Frames:
    with open_log(path) as log:
        log.quiet_warnings()
        return {(f.topic, f.index): (f.log_time_ns, f.payload.data) for f in log.frames(**kw)}  # type: ignore[arg-type]


@pytest.mark.parametrize("name", list(CASES))
def test_windows_strides_and_chunks_number_frames_alike(name: str, tmp_path: Path) -> None:
    path = _damaged(name, tmp_path)
    full = _frames(path)
    assert full, "the damaged log still holds readable frames"
    with open_log(path) as log:
        log.quiet_warnings()
        assert log.report.damage() or name == "mcap-crc", "the damage is found when the log is opened"
        for (topic, idx), (t, data) in full.items():  # a window starting at each frame
            first = next(f for f in log.frames([topic], start_ns=t))
            assert (first.index, first.payload.data) == (idx, data), (topic, t)
        for stride in (2, 3):
            got = {k for k in _frames(path, stride=stride)}
            assert got == {k for k in full if k[1] % stride == 0}
        window = FrameWindow()
        seen: Frames = {}
        for chunk in plan_chunks(log, window, 3):  # what workers read, one job each
            part = {(f.topic, f.index): (f.log_time_ns, f.payload.data)
                    for f in log.frames(None, chunk.start_ns, chunk.end_ns, indices=chunk.indices)}
            assert set(part) <= {(t, i) for t, ix in chunk.indices.items() for i in ix}
            seen.update(part)
        assert seen == full


def test_a_damaged_chunk_does_not_renumber_the_frames_after_it(tmp_path: Path) -> None:
    path = _damaged("mcap-crc", tmp_path)
    intact = {(t, lt): i for (t, i), (lt, _) in _frames(FIXTURES / "demo.mcap").items()}
    damaged = _frames(path)
    assert len(damaged) < len(intact)
    for (topic, idx), (lt, _) in damaged.items():
        assert intact[(topic, lt)] == idx
    with open_log(path) as log:  # the unreadable frames are still counted: the recording had them
        assert log.count_frames(FrameWindow()) == len(intact)


@pytest.mark.parametrize("name", ["mcap-cut", "mcap-crc+cut", "ros1-cut"])
def test_an_unfinished_log_is_scanned_once_and_warned_once(name: str, tmp_path: Path,
                                                           caplog: pytest.LogCaptureFixture) -> None:
    path = _damaged(name, tmp_path)
    caplog.set_level(logging.WARNING, logger="memlog")
    reports = []
    for _ in range(6):  # six steps or jobs open the same log
        with open_log(path) as log:
            list(log.frames())
            reports.append(log.report)
    assert scans(str(path)) == 1
    texts = [r.getMessage() for r in caplog.records]
    assert texts and len(texts) == len(set(texts)), texts
    assert all(r.damage() == reports[0].damage() != [] for r in reports)  # every reader still reports it


def test_map_reads_an_unfinished_log_once(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                          caplog: pytest.LogCaptureFixture) -> None:
    """`memlog map` (cheap pass, segment jobs, final write: many readers of one log) on a cut
    recording: its data is scanned once, and each of its warnings is said once."""
    from memlog.steps.map import make_map
    from tests.stand_in import use_stand_in

    use_stand_in(monkeypatch)
    path = _damaged("mcap-cut", tmp_path)
    opened = []
    import memlog.io.mcap.reader as reader_mod

    real_open = open

    def counting_open(file, *a, **kw):  # type: ignore[no-untyped-def]
        if str(file) == str(path):
            opened.append(file)
        return real_open(file, *a, **kw)

    monkeypatch.setattr(reader_mod, "open", counting_open, raising=False)
    caplog.set_level(logging.WARNING, logger="memlog")
    res = make_map(path, tmp_path / "map.mcap")
    assert res.report is not None and res.report.truncated
    assert scans(str(path)) == 1
    texts = [r.getMessage() for r in caplog.records if str(path) in r.getMessage()]
    assert texts and len(texts) == len(set(texts)), texts
    assert len(opened) >= 3  # several readers opened it: each started from the one scan


def test_a_zstd_compressed_ros2_bag_is_decompressed_once(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:

    import memlog.io.rosbag2.reader as r2

    from tests.conftest import zstd_bag

    bag = zstd_bag(tmp_path / "zbag")
    calls = []
    real = r2.Ros2BagLog._unzstd

    def counting(self, f):  # type: ignore[no-untyped-def]
        calls.append(f)
        return real(self, f)

    monkeypatch.setattr(r2.Ros2BagLog, "_unzstd", counting)
    want = _frames(FIXTURES / "ros2_sqlite")
    for _ in range(4):
        assert _frames(bag) == want
    assert len(calls) == 1

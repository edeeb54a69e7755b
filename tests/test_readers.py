"""Readers: every fixture format streams the right frames, pixels equal the source images."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from memlog.errors import ImageDecodeError, TopicError
from memlog.io import McapLogWriter, open_log
from memlog.io.camera import camera_kind
from tests.conftest import FIXTURES, SHARED_LOGS, shared

T0 = 1_700_000_000_000_000_000
DT = 100_000_000


def _frames(path: Path, topic: str) -> list:
    with open_log(path) as log:
        return list(log.frames([topic]))


def _max_diff(a: np.ndarray, b: np.ndarray) -> int:
    return int(np.abs(a.astype(int) - b.astype(int)).max())


@pytest.mark.parametrize(
    "name,fmt,topics",
    [
        ("demo.mcap", "mcap", {"/camera/image/compressed": 8, "/camera/image_raw": 8, "/gps/fix": 8}),
        ("ros1.bag", "ros1bag", {"/camera/image_raw": 4, "/camera/image/compressed": 4, "/gps/fix": 4}),
        ("ros2_sqlite", "ros2bag", {"/camera/image/compressed": 4}),
        ("ros2_mcap", "ros2bag", {"/camera/image_raw": 4}),
        ("foxglove_json.mcap", "mcap", {"/cam/compressed": 3, "/cam/raw": 1}),
        ("foxglove_proto.mcap", "mcap", {"/cam/compressed": 3, "/cam/raw": 3}),
        ("ros2idl.mcap", "mcap", {"/camera/image_raw": 2}),
        ("ros1.mcap", "mcap", {"/camera/image_raw": 2}),
    ],
)
def test_topic_table(name: str, fmt: str, topics: dict[str, int]) -> None:
    with open_log(FIXTURES / name) as log:
        info = log.info()
        assert info.format == fmt
        assert {t.topic: t.count for t in info.topics} == topics
        assert set(info.camera_topics) == {t for t in topics if t != "/gps/fix"}
        assert info.start_ns is not None and info.start_ns >= T0
        # the counts the index reports equal a full scan
        scanned: dict[str, int] = {}
        times: dict[str, list[int]] = {}
        for m in log.messages(log_time_order=False):
            scanned[m.channel.topic] = scanned.get(m.channel.topic, 0) + 1
            times.setdefault(m.channel.topic, []).append(m.log_time)
        assert scanned == topics
        # a topic's time range, where the index gives one, holds every message of the topic (an MCAP
        # chunk index gives its chunks' ranges, so it may be wider; a ROS 1 bag's is exact)
        for t in info.topics:
            if fmt == "ros2bag":  # (a ROS 2 bag's metadata gives the whole bag's range only)
                continue
            assert t.start_ns is not None and t.end_ns is not None and info.end_ns is not None
            assert info.start_ns <= t.start_ns <= min(times[t.topic]), t.topic
            assert max(times[t.topic]) <= t.end_ns <= info.end_ns, t.topic
            if fmt == "ros1bag":
                assert (t.start_ns, t.end_ns) == (min(times[t.topic]), max(times[t.topic])), t.topic


@pytest.mark.parametrize(
    "name,topic,exact,convert",
    [
        ("demo.mcap", "/camera/image_raw", True, None),
        ("demo.mcap", "/camera/image/compressed", False, None),
        ("ros1.bag", "/camera/image_raw", True, None),
        ("ros1.bag", "/camera/image/compressed", True, None),
        ("ros2_sqlite", "/camera/image/compressed", False, None),
        ("ros2_mcap", "/camera/image_raw", True, "gray"),
        ("foxglove_json.mcap", "/cam/compressed", True, None),
        ("foxglove_json.mcap", "/cam/raw", True, None),
        ("foxglove_proto.mcap", "/cam/compressed", False, None),
        ("foxglove_proto.mcap", "/cam/raw", True, None),
        ("ros2idl.mcap", "/camera/image_raw", True, None),
        ("ros1.mcap", "/camera/image_raw", True, None),
    ],
)
def test_pixels_match_source(
    name: str, topic: str, exact: bool, convert: str | None, source_frames: list, fixture_script
) -> None:  # type: ignore[no-untyped-def]
    frames = _frames(FIXTURES / name, topic)
    assert frames, "no frames"
    for f in frames:
        src = source_frames[f.index]
        if convert == "gray":
            got, want = f.decode_gray(), cv2.cvtColor(src, cv2.COLOR_BGR2GRAY)
        else:
            got, want = f.decode_bgr(), src
        assert got.shape == want.shape and got.dtype == np.uint8
        if not exact:  # JPEG: the same bytes decoded by OpenCV directly
            want = cv2.imdecode(np.frombuffer(fixture_script.jpeg(want), np.uint8), cv2.IMREAD_COLOR)
        assert np.array_equal(got, want), f"{name} {topic} frame {f.index}"


def test_frame_fields_and_order() -> None:
    frames = _frames(FIXTURES / "demo.mcap", "/camera/image/compressed")
    assert [f.index for f in frames] == list(range(8))
    assert [f.log_time_ns for f in frames] == [T0 + i * DT for i in range(8)]
    assert all(f.stamp_ns == f.log_time_ns and f.frame_id == "camera" for f in frames)
    assert all(f.payload.kind == "compressed" and f.payload.encoding == "jpeg" for f in frames)
    with open_log(FIXTURES / "demo.mcap") as log:
        both = list(log.frames())
    assert [f.log_time_ns for f in both] == sorted(f.log_time_ns for f in both)
    assert {f.topic for f in both} == {"/camera/image/compressed", "/camera/image_raw"}


def test_time_window_and_stride_keep_topic_indices() -> None:
    with open_log(FIXTURES / "demo.mcap") as log:
        win = list(log.frames(["/camera/image/compressed"], start_ns=T0 + 3 * DT, end_ns=T0 + 6 * DT))
        assert [f.index for f in win] == [3, 4, 5]
        strided = list(log.frames(["/camera/image/compressed"], stride=3))
        assert [f.index for f in strided] == [0, 3, 6]
        with pytest.raises(TopicError, match="not a camera topic"):
            list(log.frames(["/gps/fix"]))
        with pytest.raises(TopicError, match="no topic /nope"):
            list(log.frames(["/nope"]))


def test_every_raw_encoding(fixture_script) -> None:  # type: ignore[no-untyped-def]
    small = cv2.resize(fixture_script.source_frames()[1], (32, 24), interpolation=cv2.INTER_AREA)
    grey = cv2.cvtColor(small, cv2.COLOR_BGR2GRAY)
    with open_log(FIXTURES / "encodings.mcap") as log:
        frames = {f.topic: f for f in log.frames([t for t in log.camera_topics() if t.startswith("/raw/")])}
    assert len(frames) == 18
    for topic, f in frames.items():
        enc = topic.split("/")[-1]
        got = f.decode_bgr()
        assert got.shape == (24, 32, 3), enc
        if enc in ("mono8", "8UC1", "mono16", "16UC1", "32FC1"):
            assert _max_diff(f.decode_gray(), grey) <= (1 if enc == "32FC1" else 0), enc
        elif enc.startswith("bayer"):
            # the measured channel at each site survives demosaicing; compare green sites away from the border
            assert np.abs(got[2:-2, 2:-2].astype(int) - small[2:-2, 2:-2]).mean() < 12, enc
        elif enc in ("yuv422", "uyvy", "yuyv", "yuv422_yuy2"):
            assert np.abs(got.astype(int) - small).mean() < 6, enc
        else:
            assert np.array_equal(got, small), enc


def test_compressed_variants_and_undecodable() -> None:
    with open_log(FIXTURES / "encodings.mcap") as log:
        frames = list(log.frames(["/compressed"]))
    assert [f.payload.encoding for f in frames][:3] == ["jpeg", "png", "bgr8; jpeg compressed bgr8"]
    for f in frames[:3]:
        assert f.decode_bgr().shape == (24, 32, 3)
    with pytest.raises(ImageDecodeError, match="compressedDepth"):
        frames[3].decode_bgr()
    with pytest.raises(ImageDecodeError):
        frames[4].decode_bgr()


def test_log_time_order_across_overlapping_chunks(tmp_path: Path) -> None:
    """Messages written out of order over many small chunks come back sorted by log time."""
    from memlog.io.records import ChannelInfo, SchemaInfo

    src = FIXTURES / "demo.mcap"
    with open_log(src) as log:
        msgs = list(log.messages(["/camera/image/compressed"]))
    rng = np.random.default_rng(0)
    order = rng.permutation(len(msgs))
    out = tmp_path / "shuffled.mcap"
    with McapLogWriter(out, profile="ros2", chunk_size=1) as w:  # one message per chunk
        for i in order:
            w.write_raw(msgs[i])
    with open_log(out) as log:
        got = list(log.frames())
    assert [f.log_time_ns for f in got] == sorted(m.log_time for m in msgs)
    assert [f.index for f in got] == list(range(len(msgs)))
    assert isinstance(msgs[0].channel, ChannelInfo) and isinstance(msgs[0].channel.schema, SchemaInfo)


def test_sniffs_content_not_extension(tmp_path: Path) -> None:
    odd = tmp_path / "drive.dat"
    odd.write_bytes((FIXTURES / "ros1.bag").read_bytes())
    with open_log(odd) as log:
        assert log.format == "ros1bag"
    # a ROS 2 bag opened through its .db3 file
    with open_log(FIXTURES / "ros2_sqlite" / "ros2_sqlite.db3") as log:
        assert log.format == "ros2bag"


def test_camera_kind_names() -> None:
    assert camera_kind("sensor_msgs/msg/Image") == "raw"
    assert camera_kind("sensor_msgs/Image") == "raw"
    assert camera_kind("sensor_msgs/msg/CompressedImage") == "compressed"
    assert camera_kind("foxglove.RawImage") == "raw"
    assert camera_kind("foxglove_msgs/msg/CompressedImage") == "compressed"
    assert camera_kind("sensor_msgs/msg/NavSatFix") is None


@pytest.mark.parametrize("name", SHARED_LOGS)
def test_shared_logs_stream_and_decode(name: str) -> None:
    path = shared(name)
    with open_log(path) as log:
        info = log.info()
        cams = info.camera_topics
        assert cams
        n = 0
        for f in log.frames(cams[:1]):
            img = f.decode_bgr()
            assert img.ndim == 3 and img.dtype == np.uint8
            n += 1
        expected = {t.topic: t.count for t in info.topics}[cams[0]]
        assert n == expected
        assert log.report.ok


@pytest.mark.parametrize("name", ["demo.mcap", "ros1.bag", "ros2_sqlite", "ros2_mcap", "foxglove_json.mcap",
                                  "foxglove_proto.mcap", "ros2idl.mcap", "ros1.mcap", "encodings.mcap"])
def test_topic_times_and_frame_totals_come_from_the_index(name: str) -> None:
    """topic_times equals the log times a full read finds (without reading message data), messages
    come in log-time order, and count_frames gives the number of frames stream() yields for
    any window and stride (the progress bars' totals)."""
    from memlog.io import FrameWindow

    with open_log(FIXTURES / name) as log:
        times = [m.log_time for m in log.messages()]
        assert times == sorted(times)
        for topic in log.camera_topics():
            seen = [m.log_time for m in log.messages([topic])]
            got = log.topic_times(topic)
            assert got is not None and list(got) == seen
            for start, end, stride in ((None, None, 2), (seen[len(seen) // 2], None, 1),
                                       (seen[0] + 1, seen[-1], 3), (None, seen[-1], 2)):
                if start is not None and end is not None and end <= start:
                    continue
                w = FrameWindow((topic,), start, end, stride)
                n = sum(1 for _ in log.stream([topic], start_ns=start, end_ns=end, stride=stride))
                assert log.count_frames(w) == n, (topic, start, end, stride)


def test_progress_lines_off_a_terminal_have_totals_and_eta(monkeypatch: pytest.MonkeyPatch, capsys) -> None:  # type: ignore[no-untyped-def]
    import memlog.progress as progress
    from memlog.cli.app import show_messages

    clock = iter(range(0, 1000, 10))
    monkeypatch.setattr(progress.time, "monotonic", lambda: float(next(clock)))
    show_messages(quiet=False)  # what the command line shows
    assert list(progress.progress(range(4), total=4, desc="score", unit="frame", every_s=15.0)) == [0, 1, 2, 3]
    lines = capsys.readouterr().err.strip().splitlines()
    # the first line comes before any item after the first was timed: no estimate yet (the wait for
    # the first item, model loading, is not item time); then the time left, then the total
    assert lines[0].startswith("memlog: score: 1/4 frames (25 %)") and "estimating the time left" in lines[0]
    assert any("s left" in ln and "about" in ln for ln in lines[1:-1]), lines
    assert lines[-1].startswith("memlog: score: 4/4 frames (100 %) in ")

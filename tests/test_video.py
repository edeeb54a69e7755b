"""Camera topics recorded as video (issue 40): H.264, H.265, VP9 and AV1 packets in
``foxglove.CompressedVideo`` (JSON, protobuf, ROS 2 MCAP and sqlite3 bag, ROS 1) and ``FFMPEGPacket``,
read as frames.

Every log here is encoded by ``fixtures/video_logs.py`` with PyAV from real photos (a camera panning
across scikit-image's astronaut) or from the shared Stromovka drives. Checked against independent
expectations: decoded frames against the source frames (PSNR), keyframes found in the packets
against the encoder's own flags, a window's, a chunk's and a worker's frames against the frames of
one decode of the whole stream, damage (a stream cut before its first keyframe, a packet that does
not decode) against the frames that depend on it, and localization on H.264 logs against the same
drives as JPEG.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pyarrow.parquet as pq
import pytest
from mcap.reader import make_reader

from fixtures.video_logs import FAMILIES, encode, reencode_log, write_video_log
from memlog.io.open import open_log
from memlog.io.video import codec_of, is_keyframe
from tests.conftest import shared
from tests.test_drive_pair import _scores
from tests.same_outputs import normalised_map, normalised_parquet, normalised_scored

T0 = 1_700_000_000_000_000_000
DT = 100_000_000
TOPIC = "/camera/video"
#: Decoded frames against their source: every codec at its fixture settings stays above this.
MIN_PSNR_DB = 30.0


def main(argv: list[str]) -> int:
    """``memlog ARGV`` in its own process, as a user runs it (its workers, models and threads end with it)."""
    proc = subprocess.run([sys.executable, "-m", "memlog", *argv], capture_output=True, text=True)
    sys.stderr.write(proc.stderr)
    return proc.returncode


def pan(n: int, size: tuple[int, int] = (320, 240), step: int = 4) -> list[np.ndarray]:
    """A camera panning across a real photo: ``n`` BGR frames of ``size`` (width, height)."""
    import skimage.data

    photo = cv2.cvtColor(skimage.data.astronaut(), cv2.COLOR_RGB2BGR)
    photo = cv2.resize(photo, (size[0] + step * n, size[1] + step * n // 4))
    return [np.ascontiguousarray(photo[i * step // 4: i * step // 4 + size[1], i * step: i * step + size[0]])
            for i in range(n)]


def stamps(n: int) -> list[int]:
    return [T0 + i * DT for i in range(n)]


def log_path(tmp: Path, name: str, family: str) -> Path:
    return tmp / {"ros1": f"{name}.bag", "ros2bag": name}.get(family, f"{name}.mcap")


@pytest.fixture(scope="module")
def frames() -> list[np.ndarray]:
    return pan(36)


@pytest.fixture(scope="module")
def packets(frames: list[np.ndarray]) -> dict[str, list[tuple[bytes, bool]]]:
    return {codec: encode(frames, codec, gop=12) for codec in ("h264", "h265", "vp9", "av1")}


def decoded(path: Path, **window: Any) -> dict[int, np.ndarray]:
    with open_log(path) as log:
        return {f.index: f.decode_bgr() for f in log.frames([TOPIC], **window)}


CASES = [("h264", fam) for fam in FAMILIES] + [(c, f) for c in ("h265", "vp9", "av1") for f in ("json", "ffmpeg")]


@pytest.mark.parametrize("codec, family", CASES)
def test_a_video_topic_round_trips_as_frames(tmp_path: Path, frames: list[np.ndarray],
                                             packets: dict[str, list[tuple[bytes, bool]]], codec: str,
                                             family: str) -> None:
    path = write_video_log(log_path(tmp_path, "v", family), packets[codec], stamps(len(frames)), codec=codec,
                           family=family, size=(320, 240))
    with open_log(path) as log:
        info = log.info()
        assert info.camera_topics == [TOPIC]
        got = list(log.frames([TOPIC]))
        assert log.report.ok
    assert [f.index for f in got] == list(range(len(frames)))
    assert [f.stamp_ns for f in got] == stamps(len(frames))
    for f in got:
        psnr = cv2.PSNR(f.decode_bgr(), frames[f.index])
        assert psnr >= MIN_PSNR_DB, (codec, family, f.index, psnr)


@pytest.mark.parametrize("codec", ["h264", "h265", "vp9", "av1"])
def test_keyframes_are_found_in_the_packets(packets: dict[str, list[tuple[bytes, bool]]], codec: str) -> None:
    flags = [key for _data, key in packets[codec]]
    assert flags[0] and sum(flags) == 3  # a keyframe every 12 frames
    assert [is_keyframe(codec, data) for data, _key in packets[codec]] == flags
    assert [is_keyframe(codec, data, flags=int(key)) for data, key in packets[codec]] == flags


def test_codec_names() -> None:
    assert [codec_of(n) for n in ("h264", "H265", "hevc", "libx264", "hevc_nvenc", "libvpx-vp9", "av1", "libsvtav1",
                                  "mjpeg", "")] == ["h264", "h265", "h265", "h264", "h265", "vp9", "av1", "av1", None,
                                                    None]


@pytest.mark.parametrize("codec", ["h264", "av1"])
def test_a_window_starting_mid_stream_decodes_from_the_keyframe_before_it(
        tmp_path: Path, frames: list[np.ndarray], packets: dict[str, list[tuple[bytes, bool]]], codec: str) -> None:
    path = write_video_log(tmp_path / "v.mcap", packets[codec], stamps(len(frames)), codec=codec)
    whole = decoded(path)
    for window, want in (({"start_ns": stamps(36)[17]}, range(17, 36)), ({"stride": 5}, range(0, 36, 5)),
                         ({"start_ns": stamps(36)[13], "end_ns": stamps(36)[22], "stride": 4}, [16, 20]),
                         ({"indices": {TOPIC: {9, 30}}}, [9, 30])):
        part = decoded(path, **window)
        assert sorted(part) == list(want), window
        for i, img in part.items():
            assert np.array_equal(img, whole[i]), (window, i)


def test_a_stream_cut_before_its_first_keyframe_is_damage(tmp_path: Path, frames: list[np.ndarray],
                                                          packets: dict[str, list[tuple[bytes, bool]]],
                                                          capfd: pytest.CaptureFixture[str]) -> None:
    """A recording that starts mid-GOP: its frames before the first keyframe cannot be decoded; they
    are reported with topic and index, exit 3, and every frame from the keyframe on is scored."""
    path = write_video_log(tmp_path / "cut.mcap", packets["h264"][5:], stamps(31))  # keyframe at 7 (was 12)
    assert main(["score", str(path), "-o", str(tmp_path / "cut.scored.mcap")]) == 3
    err = capfd.readouterr().err
    assert f"topic {TOPIC} message 0" in err and "no keyframe" in err and "Traceback" not in err
    assert "7 frame(s) did not decode" in err
    with open_log(path) as log:
        got = [f.index for f in log.frames([TOPIC])]
        assert got == list(range(7, 31))
        assert log.report.undecodable_frames == 7


def test_a_packet_that_does_not_decode_is_damage_up_to_the_next_keyframe(
        tmp_path: Path, frames: list[np.ndarray], packets: dict[str, list[tuple[bytes, bool]]]) -> None:
    bad = list(packets["h264"])
    bad[15] = (bytes(np.random.default_rng(1).integers(0, 256, len(bad[15][0]), dtype=np.uint8)), False)
    path = write_video_log(tmp_path / "bad.mcap", bad, stamps(36))
    whole = decoded(write_video_log(tmp_path / "good.mcap", packets["h264"], stamps(36)))
    with open_log(path) as log:
        got = {f.index: f.decode_bgr() for f in log.frames([TOPIC])}
        assert log.report.undecodable_frames == 24 - 15  # 15 refers to nothing valid, 16..23 to 15
    assert sorted(got) == list(range(15)) + list(range(24, 36))
    assert all(np.array_equal(got[i], whole[i]) for i in got)


def test_a_format_memlog_does_not_decode_is_reported(tmp_path: Path,
                                                     packets: dict[str, list[tuple[bytes, bool]]]) -> None:
    path = write_video_log(tmp_path / "x.mcap", packets["h264"][:3], stamps(3), codec="mjpeg-video")
    with open_log(path) as log:
        assert list(log.frames([TOPIC])) == []
        assert log.report.bad_messages == 3
        assert any("'mjpeg-video' is not one memlog decodes" in w for w in log.report.warnings)


def test_a_log_without_a_camera_topic_is_a_usage_error_that_lists_its_topics(
        tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    from mcap.writer import Writer

    path = tmp_path / "gps.mcap"
    with open(path, "wb") as fh:
        w = Writer(fh)
        w.start()
        ch = w.register_channel("/gps", "json", w.register_schema("foxglove.LocationFix", "jsonschema", b"{}"))
        w.add_message(ch, log_time=T0, publish_time=T0, data=b"{}")
        w.finish()
    assert main(["-q", "map", str(path), "-o", str(tmp_path / "m.mcap")]) == 2
    err = capfd.readouterr().err
    assert "no camera topic memlog can read" in err and "/gps (foxglove.LocationFix)" in err
    assert "foxglove.CompressedVideo" in err  # what it reads


@pytest.fixture(scope="module")
def drive(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A longer H.264 drive (150 frames, a keyframe every 30): jobs of 64 frames start mid-GOP."""
    d = tmp_path_factory.mktemp("video_drive")
    imgs = pan(150, (160, 120), step=2)
    return write_video_log(d / "drive.mcap", encode(imgs, "h264", gop=30), stamps(150))


def test_workers_decode_the_same_frames_as_one_process(drive: Path, tmp_path: Path) -> None:
    """``map`` and ``score`` with --workers 2 (each job starts at its own frame, decoding from the
    keyframe before it) write what one process writes, timing fields aside."""
    for workers in ("1", "2"):  # the same names in two directories (the map records its Parquet's name)
        (tmp_path / workers).mkdir()
        assert main(["-q", "map", str(drive), "-o", str(tmp_path / workers / "m.mcap"), "--workers", workers]) == 0
        assert main(["-q", "score", str(drive), "-o", str(tmp_path / workers / "s.mcap"), "--workers", workers,
                     "--stride", "7"]) == 0
    one, two = tmp_path / "1", tmp_path / "2"
    assert normalised_map(one / "m.mcap") == normalised_map(two / "m.mcap")
    assert normalised_parquet(one / "m.parquet") == normalised_parquet(two / "m.parquet")
    assert normalised_scored(one / "s.mcap") == normalised_scored(two / "s.mcap")


def _records(path: Path) -> dict[str, list[tuple[int, bytes]]]:
    out: dict[str, list[tuple[int, bytes]]] = {}
    with open(path, "rb") as fh:
        for _s, ch, m in make_reader(fh).iter_messages(log_time_order=False):
            out.setdefault(ch.topic, []).append((m.log_time, bytes(m.data)))
    return out


def test_the_annotated_log_keeps_the_video_and_annotates_its_frames(drive: Path, tmp_path: Path) -> None:
    out = tmp_path / "scored.mcap"
    assert main(["-q", "score", str(drive), "-o", str(out), "--stride", "10"]) == 0
    src, got = _records(drive), _records(out)
    assert got[TOPIC] == src[TOPIC]  # the video, every packet byte for byte
    notes = [json.loads(data) for _t, data in got[f"{TOPIC}/memlog/annotations"]]
    want = [T0 + i * DT for i in range(0, 150, 10)]
    assert [n["timestamp"]["sec"] * 1_000_000_000 + n["timestamp"]["nsec"] for n in notes] == want


def test_the_map_log_keeps_its_frames_as_jpeg_images(drive: Path, tmp_path: Path) -> None:
    out = tmp_path / "map.mcap"
    assert main(["-q", "map", str(drive), "-o", str(out)]) == 0
    with open(out, "rb") as fh:
        r = make_reader(fh)
        chans = {c.topic: r.get_summary().schemas[c.schema_id].name for c in r.get_summary().channels.values()}
        meta = {m.name: m.metadata for m in r.iter_metadata()}
    assert chans[f"{TOPIC}/compressed"] == "foxglove.CompressedImage" and TOPIC not in chans
    encoded = json.loads(meta["memlog_map"]["frames_encoded_as"])
    assert encoded == {TOPIC: {"topic": f"{TOPIC}/compressed", "from": "foxglove.CompressedVideo",
                               "how": "each kept frame decoded from the video stream and encoded as an image"}}
    kept = sorted(pq.read_table(out.with_suffix(".parquet")).to_pydict()["frame_index"])
    images = [json.loads(d) for _t, d in _records(out)[f"{TOPIC}/compressed"]]
    index = [(i["timestamp"]["sec"] * 1_000_000_000 + i["timestamp"]["nsec"] - T0) // DT for i in images]
    assert index == kept and all(i["format"] == "jpeg" for i in images)
    whole = decoded(drive)
    import base64

    for k, i in zip(index, images):  # each is its frame of the video
        jpg = cv2.imdecode(np.frombuffer(base64.b64decode(i["data"]), np.uint8), cv2.IMREAD_COLOR)
        assert cv2.PSNR(jpg, whole[k]) > 30  # JPEG quality 90 of the decoded frame


def test_evaluate_and_batch_take_video_topics(drive: Path, tmp_path: Path) -> None:
    truth = tmp_path / "truth.json"
    truth.write_text(json.dumps({"matches": [[i] for i in range(150)]}))
    assert main(["-q", "evaluate", "--reference", str(drive), "--query", str(drive), "--truth", str(truth), "-o",
                 str(tmp_path / "ev"), "--seeds", "1", "--no-report", "--max-frames", "60"]) == 0
    res = json.loads((tmp_path / "ev" / "results.json").read_text())
    assert res["settings"]["reference_topic"] == TOPIC and res["full"]["frames"] <= 60
    assert res["full"]["recall@1"] >= 0.5  # the drive against itself (chance: 1 in 60)
    assert main(["-q", "batch", str(drive), "-o", str(tmp_path / "b"), "--workers", "1"]) == 0
    assert (tmp_path / "b" / "drive.map.parquet").is_file()


@pytest.mark.parametrize("pair", ["stromovka", "stromovka_drive"])
def test_stromovka_as_h264_localizes_as_the_jpeg_logs(tmp_path: Path, pair: str,
                                                     request: pytest.FixtureRequest) -> None:
    """Both Stromovka pairs re-encoded as H.264 (Foxglove JSON), through `memlog map --keep-fraction 1`
    then `memlog localize`, as the JPEG logs: R@1 within 0.02 on the frame-aligned pair; on the drive
    pair (whose matching is far more sensitive to small changes of the frames) no worse by more than 0.02."""
    logs = {s: shared(f"{pair}_{s}.mcap") for s in ("autumn", "winter")}
    truth = json.loads(shared(f"{pair}_truth.json").read_text())["matches"]
    r1 = {}
    for kind in ("jpeg", "h264"):
        ref, query = logs["autumn"], logs["winter"]
        if kind == "jpeg" and pair == "stromovka_drive":  # the same commands, run once for the session
            r1[kind] = _scores(request.getfixturevalue("drive_pair_maps")["full"][1], truth)[0]
            continue
        if kind == "h264":
            ref, _ = reencode_log(ref, tmp_path / "autumn.h264.mcap")
            query, _ = reencode_log(query, tmp_path / "winter.h264.mcap")
        m = tmp_path / f"{kind}.map.mcap"
        assert main(["-q", "map", str(ref), "-o", str(m), "--keep-fraction", "1"]) == 0
        assert main(["-q", "localize", str(m.with_suffix(".parquet")), str(query), "-o",
                     str(tmp_path / f"{kind}.x.parquet"), "--map", str(m)]) == 0
        r1[kind] = _scores(tmp_path / f"{kind}.x.parquet", truth)[0]  # R@1, the hits counted by hand
    if pair == "stromovka":
        assert abs(r1["h264"] - r1["jpeg"]) <= 0.02 + 1e-9, r1
    else:
        assert r1["h264"] >= r1["jpeg"] - 0.02 - 1e-9, r1

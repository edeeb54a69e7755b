"""Writer and convert: every input record survives, bit-exact, in an indexed MCAP."""

from __future__ import annotations

import hashlib
from pathlib import Path

import pytest
from mcap.reader import make_reader

from memlog.steps.convert import convert
from memlog.errors import OutputPathError
from memlog.io import McapLogWriter, open_log
from tests.conftest import FIXTURE_LOGS, FIXTURES, SHARED_LOGS, shared


def _digest(path: Path) -> str:
    h = hashlib.sha256()
    files = sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path]
    for p in files:
        h.update(p.read_bytes())
    return h.hexdigest()


def _input_records(path: Path) -> tuple[list, list, list]:
    with open_log(path) as log:
        msgs = sorted(
            (m.channel.topic, m.log_time, m.publish_time, m.sequence, m.data) for m in log.messages(log_time_order=False)
        )
        meta = sorted((n, sorted(d.items())) for n, d in log.metadata())
        atts = sorted((a.name, a.media_type, a.log_time, a.create_time, a.data) for a in log.attachments())
    return msgs, meta, atts


def _mcap_records(path: Path) -> tuple[list, list, list, dict, str]:
    """Read back with the reference mcap reader, CRCs validated."""
    with open(path, "rb") as fh:
        r = make_reader(fh, validate_crcs=True)
        msgs = sorted(
            (ch.topic, m.log_time, m.publish_time, m.sequence, bytes(m.data)) for _, ch, m in r.iter_messages()
        )
        meta = sorted((m.name, sorted(m.metadata.items())) for m in r.iter_metadata())
        atts = sorted((a.name, a.media_type, a.log_time, a.create_time, bytes(a.data)) for a in r.iter_attachments())
        summary = r.get_summary()
        assert summary is not None and summary.chunk_indexes and summary.statistics is not None
        assert all(ci.compression == "zstd" for ci in summary.chunk_indexes)
        schemas = {
            ch.topic: (summary.schemas[ch.schema_id].name, summary.schemas[ch.schema_id].encoding,
                       bytes(summary.schemas[ch.schema_id].data), ch.message_encoding)
            for ch in summary.channels.values()
        }
        profile = r.get_header().profile
    # data-section CRC and every chunk CRC, via the streaming reader too
    from mcap.stream_reader import StreamReader

    with open(path, "rb") as fh:
        for _ in StreamReader(fh, validate_crcs=True).records:
            pass
    return msgs, meta, atts, schemas, profile


def _check_convert(src: Path, out: Path) -> None:
    before = _digest(src)
    res = convert(src, out)
    assert _digest(src) == before, "input log was modified"
    in_msgs, in_meta, in_atts = _input_records(src)
    out_msgs, out_meta, out_atts, schemas, profile = _mcap_records(out)
    assert res.messages == len(in_msgs) == len(out_msgs)
    assert out_msgs == in_msgs
    assert out_meta == in_meta and out_atts == in_atts
    with open_log(src) as log:
        assert profile == log.profile
        for ch in log.channels():
            assert schemas[ch.topic] == (ch.schema.name, ch.schema.encoding, ch.schema.data, ch.message_encoding)


@pytest.mark.parametrize("name", FIXTURE_LOGS)
def test_convert_fixture_keeps_every_record(name: str, tmp_path: Path) -> None:
    _check_convert(FIXTURES / name, tmp_path / "out.mcap")


@pytest.mark.parametrize("name", SHARED_LOGS)
def test_convert_shared_log(name: str, tmp_path: Path) -> None:
    _check_convert(shared(name), tmp_path / "out.mcap")


@pytest.mark.parametrize("name", ["ros2_sqlite", "ros2_mcap", "demo.mcap"])
def test_ros2_output_reads_back_through_rosbags(name: str, tmp_path: Path) -> None:
    from rosbags.highlevel import AnyReader

    out = tmp_path / "out.mcap"
    convert(FIXTURES / name, out)
    with open_log(FIXTURES / name) as log:
        want = sorted((m.channel.topic, m.log_time, m.data) for m in log.messages())
    with AnyReader([out]) as r:
        got = sorted((c.topic, t, bytes(raw)) for c, t, raw in r.messages())
        # and the messages deserialize with rosbags' own types
        for c, _, raw in r.messages(connections=[c for c in r.connections if "Image" in c.msgtype][:1]):
            msg = r.deserialize(raw, c.msgtype)
            assert msg.header.frame_id
    assert got == want


def test_ros1_bag_output_is_ros1_profile_and_decodes(tmp_path: Path) -> None:
    from mcap_ros1.decoder import DecoderFactory

    out = tmp_path / "out.mcap"
    convert(FIXTURES / "ros1.bag", out)
    with open(out, "rb") as fh:
        r = make_reader(fh, decoder_factories=[DecoderFactory()], validate_crcs=True)
        assert r.get_header().profile == "ros1"
        n = 0
        for schema, ch, _, msg in r.iter_decoded_messages(topics=["/camera/image_raw"]):
            assert schema.encoding == "ros1msg" and schema.name == "sensor_msgs/Image"
            assert ch.metadata["md5sum"] == "060021388200f6f0f447d0fcd9c64743"
            assert msg.encoding == "rgb8" and msg.width == 96
            n += 1
    assert n == 4


def test_writer_is_atomic(tmp_path: Path) -> None:
    target = tmp_path / "out.mcap"
    target.write_bytes(b"previous run")
    with pytest.raises(RuntimeError):
        with McapLogWriter(target) as w:
            cid = w.add_json_channel("/x", "x", {"type": "object"})
            w.write_json(cid, 1, {"a": 1})
            raise RuntimeError("boom")
    assert target.read_bytes() == b"previous run"
    assert [p.name for p in tmp_path.iterdir()] == ["out.mcap"], "temporary file left behind"


def test_writer_adds_json_channels_next_to_passthrough(tmp_path: Path) -> None:
    out = tmp_path / "out.mcap"
    with open_log(FIXTURES / "demo.mcap") as log, McapLogWriter(out, profile=log.profile) as w:
        cid = w.add_json_channel("/camera/image/compressed/memlog/scores", "memlog.FrameScores", {"type": "object"})
        for m in log.messages():
            w.write_raw(m)
            if m.channel.topic == "/camera/image/compressed":
                w.write_json(cid, m.log_time, {"ms": 0.5})
    with open(out, "rb") as fh:
        r = make_reader(fh, validate_crcs=True)
        counts: dict[str, int] = {}
        for _, ch, _m in r.iter_messages():
            counts[ch.topic] = counts.get(ch.topic, 0) + 1
    assert counts["/camera/image/compressed/memlog/scores"] == 8
    assert counts["/camera/image/compressed"] == 8 and counts["/gps/fix"] == 8


def test_convert_refuses_to_overwrite_its_input(tmp_path: Path) -> None:
    src = tmp_path / "a.mcap"
    src.write_bytes((FIXTURES / "demo.mcap").read_bytes())
    before = src.read_bytes()
    with pytest.raises(OutputPathError, match="overwrite the input"):
        convert(src, src)
    link = tmp_path / "link.mcap"
    link.hardlink_to(src)  # another name for the same file
    with pytest.raises(OutputPathError, match="overwrite the input"):
        convert(src, link)
    assert src.read_bytes() == before

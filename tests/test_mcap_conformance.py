"""The official MCAP conformance corpus (``../shared/data/mcap_conformance``, 416 valid files with
the records a reader must yield beside each): memlog's reader, ``memlog inspect`` and ``memlog
convert`` agree with the expected records on every file, keep channel and schema ids, and exit 0
(:mod:`tests.mcap_corpus`; ``python benchmarks/mcap_conformance.py`` prints the same per feature).
Camera logs written with every optional part of the format left out give the same frames. And
every checksum the format has is checked: chunk, data-section and summary CRCs."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import hashlib

import pytest
from mcap.reader import make_reader
from mcap.writer import IndexType, Writer

from tests.conftest import FIXTURES, shared, skip_or_fail
from tests.mcap_corpus import (CASES, CORPUS, check_convert, check_inspect, check_read, expected, library_read,
                               memlog_read, run_cli)

def _files(case: str) -> list[Path]:
    files = sorted((CORPUS / case).glob("*.mcap"))
    if not files:
        skip_or_fail(f"{CORPUS / case} is missing: the MCAP conformance corpus is part of the shared data "
                     "(../shared/data/mcap_conformance, see its README)")
    return files


def _failures(case: str, check) -> str:  # type: ignore[no-untyped-def]
    wrong = {p.name: check(p) for p in _files(case)}
    return "\n".join(f"{name}: {w}" for name, w in wrong.items() if w)


@pytest.mark.shared
@pytest.mark.parametrize("case", CASES)
def test_reader_yields_the_expected_records(case: str) -> None:
    """Messages (channel id, sequence, times, data) in file order, channels and schemas with their
    ids, attachments and metadata, and no damage reported: on every file of the case."""
    assert not _failures(case, check_read)


@pytest.mark.shared
@pytest.mark.parametrize("case", CASES)
def test_inspect_counts_every_message_and_exits_0(case: str) -> None:
    assert not _failures(case, check_inspect)


@pytest.mark.shared
@pytest.mark.parametrize("case", CASES)
def test_convert_keeps_every_record_and_id(case: str, tmp_path: Path) -> None:
    """``memlog convert`` exits 0; the output, read by the mcap library with CRCs validated, holds
    exactly the expected messages, channels, schemas (ids included), attachments and metadata, and
    its statistics count the input's channels and schemas, no more."""
    assert not _failures(case, lambda p: check_convert(p, tmp_path / f"{p.stem}.out.mcap"))


@pytest.mark.shared
def test_the_checks_fail_on_a_wrong_reader(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """The checks can fail: a reader that renumbers channels, or drops a message, is caught."""
    path = _files("TenMessages")[0].parent / "TenMessages-ch-chx-mx.mcap"
    assert check_read(path) == [] and check_convert(path, tmp_path / "a.mcap") == []
    from memlog.io.mcap.writer import McapLogWriter

    register = McapLogWriter.register_input

    def renumbering(self: McapLogWriter, reader) -> None:  # type: ignore[no-untyped-def]
        self.add_channel("/first", "json", 0)  # takes channel id 1
        register(self, reader)

    monkeypatch.setattr(McapLogWriter, "register_input", renumbering)
    assert "output channels" in check_convert(path, tmp_path / "b.mcap")
    want = expected(path)
    monkeypatch.setattr("tests.mcap_corpus.expected", lambda p: {**want, "messages": want["messages"][1:]})
    assert check_read(path) == ["messages"]


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "memlog", *args], capture_output=True, text=True)


@pytest.mark.shared
@pytest.mark.parametrize("name", ["OneMessage-ch-chx-mx.mcap", "OneMessage-ch-chx-mx-pad-rch-st-sum.mcap",
                                  "TenMessages-ch-mx-rch.mcap", "OneAttachment-ax-pad.mcap"])
def test_the_memlog_command_agrees(name: str, tmp_path: Path) -> None:
    """The corpus runs through ``memlog.cli.main`` in this process; the ``memlog`` command itself, in
    a process of its own, gives the same on a file of each kind that failed before (channels only in
    the data; channels in the summary, schemas only in the data; an attachment): exit 0, no
    warning, the expected records."""
    path = CORPUS / name.split("-")[0] / name
    if not path.exists():
        skip_or_fail(f"{path} is missing: the MCAP conformance corpus is part of the shared data")
    out = tmp_path / "out.mcap"
    for args in (["inspect", str(path)], ["convert", str(path), "-o", str(out)]):
        r = _cli(*args)
        assert r.returncode == 0 and "warning" not in r.stderr, (args, r.stderr)
    assert library_read(out)[0] == expected(path)


@pytest.mark.shared
def test_inspect_names_each_checksum_and_how_it_fared() -> None:
    unchunked = _files("TenMessages")[0].parent / "TenMessages.mcap"
    chunked = unchunked.parent / "TenMessages-ch-chx-mx-st-sum.mcap"
    checks = {}
    for path in (unchunked, chunked):
        rc, out, _ = run_cli("inspect", "--json", "-q", str(path))
        assert rc == 0
        checks[path.name] = json.loads(out)["checksum_checks"]
    assert checks == {
        "TenMessages.mcap": {"chunks": "none", "data_section": "held", "summary": "none", "attachments": "none"},
        "TenMessages-ch-chx-mx-st-sum.mcap": {"chunks": "held", "data_section": "unchecked", "summary": "held",
                                              "attachments": "none"},
    }


@pytest.mark.shared
def test_an_attachment_that_fails_its_crc_is_reported_and_skipped(tmp_path: Path) -> None:
    src = _files("OneAttachment")[0].parent / "OneAttachment-ax.mcap"
    rc, out, _ = run_cli("inspect", "--json", "-q", str(src))
    assert rc == 0 and json.loads(out)["checksum_checks"]["attachments"] == "held"
    data = bytearray(src.read_bytes())
    (name, media_type, _lt, _ct, _data), = expected(src)["attachments"]
    data[data.index(media_type.encode()) + len(media_type) + 8] ^= 0xFF  # the first byte of its data
    bad = tmp_path / "attachment.mcap"
    bad.write_bytes(bytes(data))
    rc, out, _ = run_cli("inspect", "--json", "-q", str(bad))
    report = json.loads(out)
    assert rc == 3 and report["checksum_checks"]["attachments"] == "failed"
    assert any(f"attachment {name!r} fails its CRC check" in w for w in report["warnings"])
    rc, _, err = run_cli("convert", "-q", str(bad), "-o", str(tmp_path / "out.mcap"))
    assert rc == 3 and library_read(tmp_path / "out.mcap")[0]["attachments"] == []


@pytest.mark.shared
def test_a_byte_flipped_in_an_unchunked_data_section_fails_its_crc(tmp_path: Path) -> None:
    """The DataEnd CRC covers an unchunked file's records: a flipped byte inside a message's data
    is damage (exit 3, the CRC named), and every message is still kept."""
    src = _files("TenMessages")[0].parent / "TenMessages.mcap"
    want = expected(src)
    data = bytearray(src.read_bytes())
    payload = want["messages"][4][4]
    at = data.index(payload, data.index(bytes([4]), 8))  # the fifth message's data, after the channel record
    data[at] ^= 0xFF
    bad = tmp_path / "flipped.mcap"
    bad.write_bytes(bytes(data))
    out = tmp_path / "out.mcap"
    r = _cli("convert", str(bad), "-o", str(out))
    assert r.returncode == 3, r.stderr
    assert "data section fails its CRC check" in r.stderr and "Traceback" not in r.stderr
    got, _ = library_read(out)
    assert len(got["messages"]) == len(want["messages"])
    assert sum(m != g for m, g in zip(want["messages"], got["messages"])) == 1  # only the flipped one differs
    r = _cli("inspect", str(bad))
    assert r.returncode == 3 and "data-section CRC: FAILED" in r.stdout
    assert bad.read_bytes() == bytes(data)  # the input is left as it was


@pytest.mark.shared
def test_a_summary_that_fails_its_crc_is_not_used(tmp_path: Path) -> None:
    """A byte flipped in the summary: the footer's summary CRC fails, the reader says so, reads the
    data instead (every message kept) and ends with exit 3."""
    src = _files("TenMessages")[0].parent / "TenMessages-ch-chx-mx-st-sum.mcap"
    data = bytearray(src.read_bytes())
    summary_start = int.from_bytes(data[-8 - 20: -8 - 12], "little")  # Footer: summary_start, offset start, crc
    data[summary_start + 12] ^= 0xFF
    bad = tmp_path / "summary.mcap"
    bad.write_bytes(bytes(data))
    rc, out, _ = run_cli("inspect", "--json", "-q", str(bad))
    report = json.loads(out)
    assert rc == 3 and report["checksum_checks"]["summary"] == "failed"
    assert any("summary section fails its CRC check" in w for w in report["warnings"])
    got, damage = memlog_read(bad)
    assert got["messages"] == expected(src)["messages"] and damage


def test_ids_that_leave_a_gap_are_numbered_anew_and_said(tmp_path: Path) -> None:
    """The mcap library numbers channels 1, 2, ... as they come: an input whose channel ids leave a
    gap (3 and 2 here) cannot keep them; its channels are written in the order of their ids, each
    message stays with its topic, and the log says which channel got which id."""
    from mcap.data_stream import RecordBuilder
    from mcap.records import Channel, DataEnd, Footer, Header, Message, Schema

    b = RecordBuilder()
    Header(profile="", library="test").write(b)
    Schema(id=1, name="s", encoding="jsonschema", data=b"{}").write(b)
    for cid in (3, 2):
        Channel(id=cid, topic=f"/c{cid}", message_encoding="json", schema_id=1, metadata={}).write(b)
        Message(channel_id=cid, sequence=cid, log_time=cid, publish_time=cid, data=b"{}").write(b)
    DataEnd(0).write(b)
    Footer(0, 0, 0).write(b)
    magic = b"\x89MCAP0\r\n"
    src = tmp_path / "gap.mcap"
    src.write_bytes(magic + b.end() + magic)
    rc, _, err = run_cli("convert", str(src), "-o", str(tmp_path / "out.mcap"))
    assert rc == 0, err
    got, _ = library_read(tmp_path / "out.mcap")
    assert {i: c[0] for i, c in got["channels"].items()} == {1: "/c2", 2: "/c3"}
    assert [(got["channels"][m[0]][0], m[1]) for m in got["messages"]] == [("/c3", 3), ("/c2", 2)]
    assert "channel 3 (/c3) is written as channel 2" in err


#: the mcap library's writer options that leave out an optional part of an MCAP file
VARIANTS: dict[str, dict[str, object]] = {
    "no message indexes": {"index_types": IndexType.CHUNK},
    "no message indexes, no statistics": {"index_types": IndexType.CHUNK, "use_statistics": False},
    "no indexes at all": {"index_types": IndexType.NONE},
    "no channels or schemas in the summary": {"repeat_channels": False, "repeat_schemas": False},
    "channels in the summary without their schemas": {"repeat_schemas": False},
    "no summary offsets": {"use_summary_offsets": False},
    "unchunked": {"use_chunking": False},
    "unchunked, with a data-section CRC": {"use_chunking": False, "enable_data_crcs": True},
}


def _rewrite(src: Path, dst: Path, options: dict[str, object]) -> None:
    """``src`` written again by the mcap library with ``options`` (same ids, records and order)."""
    with open(src, "rb") as fh, open(dst, "wb") as out:
        reader = make_reader(fh)
        summary = reader.get_summary()
        assert summary is not None
        w = Writer(out, chunk_size=64 * 1024, **options)  # type: ignore[arg-type]
        w.start(reader.get_header().profile, "test")
        for sid in sorted(summary.schemas):
            s = summary.schemas[sid]
            assert w.register_schema(s.name, s.encoding, s.data) == sid
        for cid in sorted(summary.channels):
            c = summary.channels[cid]
            assert w.register_channel(c.topic, c.message_encoding, c.schema_id, c.metadata) == cid
        for _, c, m in reader.iter_messages(log_time_order=False):
            w.add_message(c.id, m.log_time, m.data, m.publish_time, m.sequence)
        w.finish()


def _frames(path: Path) -> tuple[list[tuple[str, int, int, str]], list[str]]:
    from memlog.io import open_log
    from memlog.io._opened import clear_cache

    clear_cache()
    with open_log(path) as log:
        log.quiet_warnings()
        frames = [(f.topic, f.index, f.log_time_ns, hashlib.sha256(f.decode_bgr().tobytes()).hexdigest())
                  for f in log.frames()]
        return frames, log.report.damage()


@pytest.mark.parametrize("log", [FIXTURES / "demo.mcap", "euroc_micro_ros2.mcap"], ids=["demo", "euroc"])
@pytest.mark.parametrize("variant", list(VARIANTS))
def test_a_camera_log_without_optional_parts_gives_the_same_frames(log: Path | str, variant: str,
                                                                   tmp_path: Path) -> None:
    """The corpus has no camera topic: a camera log written with an optional part of the format
    left out (message indexes, statistics, the summary's channels or schemas, chunks) numbers and
    decodes the same frames as the log as recorded, reports no damage, and ``memlog inspect``
    exits 0."""
    src = log if isinstance(log, Path) else shared(log)
    variant_log = tmp_path / "variant.mcap"
    _rewrite(src, variant_log, VARIANTS[variant])
    want, damage = _frames(src)
    assert want and not damage
    assert _frames(variant_log) == (want, [])
    rc, _, err = run_cli("inspect", "-q", str(variant_log))
    assert rc == 0, err

"""The official MCAP conformance corpus (``../shared/data/mcap_conformance``, 416 valid files with
the records a reader must yield beside each): memlog's reader, ``memlog inspect`` and ``memlog
convert`` agree with the expected records on every file, keep channel and schema ids, and exit 0
(:mod:`tests.mcap_corpus`; ``python benchmarks/mcap_conformance.py`` prints the same per feature).
And every checksum the format has is checked: chunk, data-section and summary CRCs."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import skip_or_fail
from tests.mcap_corpus import (CASES, CORPUS, check_convert, check_inspect, check_read, expected, library_read,
                               memlog_read, run_cli)

pytestmark = pytest.mark.shared


def _files(case: str) -> list[Path]:
    files = sorted((CORPUS / case).glob("*.mcap"))
    if not files:
        skip_or_fail(f"{CORPUS / case} is missing: the MCAP conformance corpus is part of the shared data "
                     "(../shared/data/mcap_conformance, see its README)")
    return files


def _failures(case: str, check) -> str:  # type: ignore[no-untyped-def]
    wrong = {p.name: check(p) for p in _files(case)}
    return "\n".join(f"{name}: {w}" for name, w in wrong.items() if w)


@pytest.mark.parametrize("case", CASES)
def test_reader_yields_the_expected_records(case: str) -> None:
    """Messages (channel id, sequence, times, data) in file order, channels and schemas with their
    ids, attachments and metadata, and no damage reported: on every file of the case."""
    assert not _failures(case, check_read)


@pytest.mark.parametrize("case", CASES)
def test_inspect_counts_every_message_and_exits_0(case: str) -> None:
    assert not _failures(case, check_inspect)


@pytest.mark.parametrize("case", CASES)
def test_convert_keeps_every_record_and_id(case: str, tmp_path: Path) -> None:
    """``memlog convert`` exits 0; the output, read by the mcap library with CRCs validated, holds
    exactly the expected messages, channels, schemas (ids included), attachments and metadata, and
    its statistics count the input's channels and schemas, no more."""
    assert not _failures(case, lambda p: check_convert(p, tmp_path / f"{p.stem}.out.mcap"))


def test_the_checks_fail_on_a_wrong_reader(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """The checks can fail: a reader that renumbers channels, or drops a message, is caught."""
    path = _files("TenMessages")[0].parent / "TenMessages-ch-chx-mx.mcap"
    assert check_read(path) == [] and check_convert(path, tmp_path / "a.mcap") == []
    from memlog.io.mcap import writer

    monkeypatch.setattr(writer, "_place", lambda table, key, wanted: max(table, default=0) + 7)
    assert "output channels" in check_convert(path, tmp_path / "b.mcap")
    want = expected(path)
    monkeypatch.setattr("tests.mcap_corpus.expected", lambda p: {**want, "messages": want["messages"][1:]})
    assert check_read(path) == ["messages"]


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "memlog", *args], capture_output=True, text=True)


def test_inspect_names_each_checksum_and_how_it_fared() -> None:
    unchunked = _files("TenMessages")[0].parent / "TenMessages.mcap"
    chunked = unchunked.parent / "TenMessages-ch-chx-mx-st-sum.mcap"
    checks = {}
    for path in (unchunked, chunked):
        rc, out, _ = run_cli("inspect", "--json", "-q", str(path))
        assert rc == 0
        checks[path.name] = json.loads(out)["checksum_checks"]
    assert checks == {
        "TenMessages.mcap": {"chunks": "none", "data_section": "held", "summary": "none"},
        "TenMessages-ch-chx-mx-st-sum.mcap": {"chunks": "held", "data_section": "unchecked", "summary": "held"},
    }


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

"""A job reads each chunk of its log once (memlog.io.spool): later passes, workers and batch's map
read the chunks the job kept, a damaged chunk is reported again without being read again, and an
unfinished MCAP is scanned from its message indexes. Checked by counting the reads of the log
(in the process, and under strace for every process of the CLI) and against the same reads with
the spool off."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from memlog.io import spool
from memlog.io.mcap import reader as mcap_reader
from memlog.io.open import open_log
from memlog.runtime import current, use
from tests.conftest import FIXTURES, ROOT, count_chunk_reads, cut_copy, shared, skip_or_fail
from tests.same_outputs import normalised_map, normalised_parquet


def _crc(src: Path, dst: Path) -> Path:
    """``src`` with one byte flipped inside the data of its middle chunk (its CRC no longer matches)."""
    from mcap.reader import make_reader

    with open(src, "rb") as fh:
        summary = make_reader(fh).get_summary()
    assert summary is not None and summary.chunk_indexes
    data = bytearray(src.read_bytes())
    ci = summary.chunk_indexes[len(summary.chunk_indexes) // 2]
    data[ci.chunk_start_offset + ci.chunk_length - ci.compressed_size // 2] ^= 0xFF
    dst.write_bytes(bytes(data))
    return dst


def _frames(path: Path) -> tuple[list[tuple[str, int, int, bytes]], list[str]]:
    with open_log(path) as log:
        log.quiet_warnings()
        frames = [(f.topic, f.index, f.log_time_ns, bytes(f.payload.data)) for f in log.frames()]
        return frames, log.report.damage()


def test_a_job_keeps_its_chunks_until_the_outer_job_ends(tmp_path: Path) -> None:
    log = cut_copy(FIXTURES / "demo.mcap", tmp_path / "demo.mcap")
    with use(current().replace(cache_dir=str(tmp_path / "cache"))):
        want = _frames(log)
        root = tmp_path / "cache" / "spool"
        assert spool.spool_of(log) is None  # no job: nothing kept
        with spool.job(log):
            (folder,) = root.iterdir()
            with spool.job(log):  # batch around score and map
                assert _frames(log) == want
            assert folder.is_dir() and list(folder.glob("*.chunk"))  # the outer job still runs
            assert _frames(log) == want  # read back from the spool: the same frames and damage
        assert not folder.exists()
        with use(current().replace(spool_bytes=0)), spool.job(log):
            assert not root.exists() or not list(root.iterdir())  # off: nothing made
            assert _frames(log) == want


def test_each_chunk_is_read_from_the_log_once_per_job(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    log = cut_copy(FIXTURES / "demo.mcap", tmp_path / "demo.mcap")
    with use(current().replace(cache_dir=str(tmp_path / "cache"))):
        reads = count_chunk_reads(monkeypatch)
        want = _frames(log)
        reads.clear()
        with spool.job(log):
            for _ in range(3):
                assert _frames(log) == want
        assert reads and max(reads.values()) == 1, reads
        reads.clear()
        with use(current().replace(spool_bytes=0)), spool.job(log):
            for _ in range(3):
                _frames(log)
        assert min(reads.values()) >= 3  # without it, every pass reads the log
        # bounded: a process keeps no more than spool_bytes of one log
        reads.clear()
        with use(current().replace(spool_bytes=50_000)), spool.job(log):
            _frames(log)
            folder = next((tmp_path / "cache" / "spool").iterdir())
            kept = sum(p.stat().st_size for p in folder.glob("*.chunk"))
            assert 0 < kept <= 50_000
            _frames(log)
        assert max(reads.values()) == 2 and min(reads.values()) == 1  # the rest read from the log again


def test_a_damaged_chunk_is_reported_again_without_being_read_again(tmp_path: Path,
                                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    log = _crc(shared("stromovka_autumn.mcap"), tmp_path / "crc.mcap")
    with use(current().replace(cache_dir=str(tmp_path / "cache"))):
        reads = count_chunk_reads(monkeypatch)
        want = _frames(log)
        assert want[1] and len(want[0]) < 101  # the damage is found, its frames are missing
        reads.clear()
        with spool.job(log):
            assert _frames(log) == want
            assert _frames(log) == want  # the same frames, the same damage reported
        assert max(reads.values()) == 1


def test_an_unfinished_mcap_is_scanned_from_its_message_indexes(tmp_path: Path,
                                                                monkeypatch: pytest.MonkeyPatch) -> None:
    """The scan of a log without a summary reads the chunks' message indexes, not their data (only a
    chunk whose Channel record it needs); its frame tables are what reading every chunk gives."""
    log = cut_copy(shared("stromovka_autumn.mcap"), tmp_path / "cut.mcap")
    with use(current().replace(cache_dir=str(tmp_path / "cache"))):
        decompressed: list[int] = []
        real = mcap_reader.chunk_data

        def counting(body: bytes, pos: int, validate: bool) -> tuple[bytes, bool]:
            decompressed.append(pos)
            return real(body, pos, validate)

        monkeypatch.setattr(mcap_reader, "chunk_data", counting)
        with open_log(log) as reader:
            reader.quiet_warnings()
            topic = reader.camera_topics()[0]
            table = reader.frame_table(topic).entries()
            counts = reader.message_counts()
            damage = reader.report.damage()
        assert len(decompressed) <= 2 and len(table[0]) == 81, decompressed  # of the 9 whole chunks before the cut
        assert damage  # the cut is still reported
        # against the scan that reads every chunk (the indexes taken away)
        from memlog.io import _opened

        _opened.clear_cache()
        shutil.rmtree(tmp_path / "cache" / "scans")
        from memlog.io.mcap import scan

        real_parse = scan.parse_record

        def no_index(cls, body, pos):  # type: ignore[no-untyped-def]
            if cls is scan.MessageIndex:
                raise scan.RecordDamage(pos, "index taken away")
            return real_parse(cls, body, pos)

        monkeypatch.setattr(scan, "parse_record", no_index)
        decompressed.clear()
        with open_log(log) as reader:
            reader.quiet_warnings()
            assert all(np.array_equal(a, b) for a, b in zip(reader.frame_table(topic).entries(), table))
            assert reader.message_counts() == counts and reader.report.damage() == damage
        assert len(decompressed) == 9  # the chunks before the cut


def test_a_ros1_bag_is_read_once_per_job(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from memlog.io.rosbag1 import reader as ros1

    log = cut_copy(FIXTURES / "ros1.bag", tmp_path / "ros1.bag")
    with use(current().replace(cache_dir=str(tmp_path / "cache"))):
        want = _frames(log)
        chunks: Counter[int] = Counter()
        real = ros1._Ros1Scanner._chunk_data

        def counting(self, fields, data, pos):  # type: ignore[no-untyped-def]
            chunks[pos] += 1
            return real(self, fields, data, pos)

        monkeypatch.setattr(ros1._Ros1Scanner, "_chunk_data", counting)
        with spool.job(log):
            assert _frames(log) == want
            assert _frames(log) == want
        assert chunks and max(chunks.values()) == 1


def test_map_with_and_without_the_spool_writes_the_same_map(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """`memlog map` on a damaged log: every chunk read from the log once, the same map as with the
    spool off (which reads each chunk once per pass)."""
    from memlog.steps.map import make_map
    from tests.stand_in import use_stand_in

    use_stand_in(monkeypatch)
    log = _crc(shared("stromovka_autumn.mcap"), tmp_path / "crc.mcap")
    reads = count_chunk_reads(monkeypatch)  # (the models' cache directory, so the spool's, is the user's)
    for d in ("on", "off"):
        (tmp_path / d).mkdir()
    on = make_map(log, tmp_path / "on" / "map.mcap")
    assert reads and max(reads.values()) == 1, reads
    reads.clear()
    with use(current().replace(spool_bytes=0)):
        off = make_map(log, tmp_path / "off" / "map.mcap")
    assert max(reads.values()) >= 2
    assert on.report is not None and off.report is not None and on.report.damage() == off.report.damage() != []
    assert normalised_map(tmp_path / "on" / "map.mcap") == normalised_map(tmp_path / "off" / "map.mcap")
    assert normalised_parquet(tmp_path / "on" / "map.parquet") == normalised_parquet(tmp_path / "off" / "map.parquet")
    name = spool._identity(log)
    assert name is not None and not (current().cache_path() / "spool" / name).exists()  # the job's chunks are gone


@pytest.mark.parametrize("case", ["crc", "cut"])
def test_workers_and_batch_read_each_chunk_of_a_damaged_log_once(case: str, tmp_path: Path) -> None:
    """Through the CLI, as users run it, every process counted (tests/read_hook: no strace): `map
    --workers 2` reads each chunk of the crc-damaged and of the cut copy of Stromovka from the log once,
    and `batch --workers 2` too, but for what its preflight scan of the cut copy decompressed before the
    log's job began (its first chunk, for the Channel record)."""
    src = shared("stromovka_autumn.mcap")
    log = (_crc(src, tmp_path / "crc.mcap") if case == "crc" else cut_copy(src, tmp_path / "cut.mcap"))
    from mcap.reader import make_reader

    with open(src, "rb") as fh:
        summary = make_reader(fh).get_summary()
    assert summary is not None
    n_chunks = len(summary.chunk_indexes)
    for name, argv in (("map", ["map", str(log), "-o", str(tmp_path / "map.mcap"), "--workers", "2"]),
                       ("batch", ["batch", str(log), "-o", str(tmp_path / "batch"), "--workers", "2", "--fast"])):
        (tmp_path / "batch").mkdir(exist_ok=True)
        reads = tmp_path / f"{name}.reads"
        env = dict(os.environ, PYTHONPATH=f"{ROOT / 'tests' / 'read_hook'}{os.pathsep}{ROOT}",
                   MEMLOG_TEST_CHUNK_READS=str(reads), MEMLOG_CACHE_DIR=str(current().cache_path()))
        res = subprocess.run([sys.executable, "-m", "memlog", "-q", *argv], capture_output=True, text=True,
                             env=env, cwd=tmp_path, timeout=900)
        assert res.returncode == 3, res.stderr[-2000:]  # the damage is reported
        offsets = Counter(int(line.split()[1]) for line in reads.read_text().splitlines()
                          if line.split()[2] == os.path.realpath(log))
        pids = {line.split()[0] for line in reads.read_text().splitlines()}
        assert len(offsets) >= (n_chunks if case == "crc" else 9), (name, offsets)  # every chunk was read
        again = {o: k for o, k in offsets.items() if k > 1}
        if name == "batch" and case == "cut":
            assert len(again) <= 1 and max(offsets.values()) == 2, offsets
        else:
            assert not again, (name, again)
        assert name == "batch" or len(pids) >= 2  # the workers' reads are counted too
        log.touch()  # (another identity: the next command learns the file afresh)


def test_the_cli_reads_a_damaged_or_unfinished_log_about_once(tmp_path: Path) -> None:
    """benchmarks/read_count.py (strace, every process): `map --workers 2` and `batch --workers 2`
    read the crc-damaged and the cut copy of Stromovka at most 1.5 times (issue 39 asks for 2)."""
    if shutil.which("strace") is None:
        skip_or_fail("strace is not installed (Debian: apt-get install strace)")
    probe = subprocess.run(["strace", "-f", "-qq", "-o", os.devnull, "true"], capture_output=True, text=True)
    if probe.returncode != 0:  # a container without ptrace (the chunk counts of the test above run everywhere)
        pytest.skip(f"strace cannot trace here: {probe.stderr.strip()[:200]}")
    shared("stromovka_autumn.mcap")
    res = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "read_count.py"), "--work", str(tmp_path),
                          "--commands", "map-w2,batch"], capture_output=True, text=True, timeout=1200,
                         env=dict(os.environ, PYTHONPATH=str(ROOT)))
    assert res.returncode == 0, res.stderr[-3000:]
    rows = [line.split("|")[1:-1] for line in res.stdout.splitlines() if line.startswith(("| crc", "| cut"))]
    assert len(rows) == 4, res.stdout
    for case, command, _size, _read, times, _opens, written, _back in (map(str.strip, r) for r in rows):
        assert float(times.rstrip("x")) <= 1.5, (case, command, res.stdout)
        assert float(written) > 0  # the later passes read the job's spool


def test_the_spool_bound_is_read_from_the_environment_once() -> None:
    from memlog.errors import ConfigError
    from memlog.runtime import DEFAULT_SPOOL_BYTES, Runtime

    assert Runtime.from_environment({}).spool_bytes == DEFAULT_SPOOL_BYTES
    assert Runtime.from_environment({"MEMLOG_SPOOL_BYTES": "0"}).spool_bytes == 0
    assert Runtime.from_environment({"MEMLOG_SPOOL_BYTES": "1000"}).spool_bytes == 1000
    for bad in ("-1", "8G", "1.5"):
        with pytest.raises(ConfigError, match="MEMLOG_SPOOL_BYTES"):
            Runtime.from_environment({"MEMLOG_SPOOL_BYTES": bad})

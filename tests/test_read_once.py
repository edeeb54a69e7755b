"""A damaged or unfinished log is learned once per job, not once per process or pass: the scan is kept
on disk for other processes (workers, Ray actors, later runs), a reader keeps the chunks it read last,
and the jobs given to workers end where a chunk of the log ends. Checked against what a fresh scan
finds, and by counting the chunk reads and the bytes read from the log."""

from __future__ import annotations

import os
import pickle
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from memlog.io import _opened
from memlog.io.base import FrameWindow
from memlog.io.open import open_log
from memlog.runtime import current, use
from tests.conftest import FIXTURES, ROOT, count_chunk_reads, cut_copy, shared


def _frames(path: Path) -> list[tuple[str, int, int, bytes]]:
    with open_log(path) as log:
        log.quiet_warnings()
        return [(f.topic, f.index, f.log_time_ns, bytes(f.payload.data)) for f in log.frames()]


_CHILD = """
import json, sys
from memlog.io.open import open_log
from memlog.io._opened import scans
path = sys.argv[1]
with open_log(path) as log:
    log.quiet_warnings()
    frames = [[f.topic, f.index, f.log_time_ns, len(f.payload.data)] for f in log.frames()]
    damage = log.report.damage()
print(json.dumps({"scans": scans(path), "frames": frames, "damage": damage}))
"""


@pytest.mark.parametrize("name", ["demo.mcap", "ros1.bag"])
def test_a_scan_is_kept_for_other_processes(name: str, tmp_path: Path) -> None:
    import json

    log = cut_copy(FIXTURES / name, tmp_path / name)
    cache = tmp_path / "cache"
    with use(current().replace(cache_dir=str(cache))):
        want = _frames(log)
        assert _opened.scans(str(log)) == 1
        with open_log(log) as reader:
            reader.quiet_warnings()
            damage = reader.report.damage()
        assert damage and list((cache / "scans").glob("*.pickle"))
    env = dict(os.environ, MEMLOG_CACHE_DIR=str(cache), PYTHONPATH=str(ROOT))
    res = subprocess.run([sys.executable, "-c", _CHILD, str(log)], capture_output=True, text=True, env=env, check=True)
    got = json.loads(res.stdout)
    assert got["scans"] == 0  # the other process started from the first one's scan
    assert got["frames"] == [[t, i, ts, len(d)] for t, i, ts, d in want]
    assert got["damage"] == damage  # and still reports the damage
    # a changed file is another file: scanned again
    with open(log, "ab") as fh:
        fh.write(b"\0" * 16)
    res = subprocess.run([sys.executable, "-c", _CHILD, str(log)], capture_output=True, text=True, env=env, check=True)
    assert json.loads(res.stdout)["scans"] == 1


def test_a_broken_or_foreign_scan_record_is_not_used(tmp_path: Path) -> None:
    log = cut_copy(FIXTURES / "demo.mcap", tmp_path / "demo.mcap")
    with use(current().replace(cache_dir=str(tmp_path / "cache"))):
        want = _frames(log)
        _opened.clear_cache()
        key = _opened.file_key("mcap", str(log), True)
        record = _opened.scan_record_path(key)
        assert record.is_file()

        from memlog.io.atomic import write_bytes_atomic

        class Evil:
            def __reduce__(self):  # type: ignore[no-untyped-def]
                return (os.system, ("echo owned > " + str(tmp_path / "owned"),))

        class EvilNumpy:
            def __reduce__(self):  # type: ignore[no-untyped-def]
                return (np.savetxt, (str(tmp_path / "owned"), np.zeros(1)))

        class EvilMemlog:  # a function of memlog's own is no class: refused too
            def __reduce__(self):  # type: ignore[no-untyped-def]
                return (write_bytes_atomic, (str(tmp_path / "owned"), b"x"))

        for content in (b"not a pickle", pickle.dumps((1, "0.0.0", key, None)), pickle.dumps(Evil()),
                        pickle.dumps(EvilNumpy()), pickle.dumps(EvilMemlog())):
            record.write_bytes(content)
            _opened.clear_cache()
            before = _opened.scans(str(log))
            assert _frames(log) == want
            assert _opened.scans(str(log)) == before + 1  # scanned again
        assert not (tmp_path / "owned").exists()


def test_the_staged_detector_reads_each_chunk_once(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """`memlog map` on one process: pass 1, the staged detector (a few frames of each segment at a
    time) and the map writer each read a chunk of the log at most once, also without the job's
    spool (tests/test_spool.py: with it, once in all)."""
    from memlog.steps.map import make_map
    from tests.stand_in import use_stand_in

    use_stand_in(monkeypatch)
    log = shared("stromovka_autumn.mcap")
    reads = count_chunk_reads(monkeypatch)
    with use(current().replace(spool_bytes=0)):  # (the spool off: each pass reads the log)
        make_map(log, tmp_path / "map.mcap")
    assert reads and max(reads.values()) <= 3, reads  # three passes; the detector's segments share chunks


def test_jobs_end_where_a_chunk_of_the_log_ends() -> None:
    from memlog.steps.score import plan_chunks

    log = shared("stromovka_autumn.mcap")
    with open_log(log) as reader:
        topic = reader.camera_topics()[0]
        containers = reader.frame_table(topic).entries()[1]
        jobs = plan_chunks(reader, FrameWindow(), 16)
    firsts = [min(j.indices[topic]) for j in jobs]
    assert sorted(i for j in jobs for i in j.indices[topic]) == list(range(len(containers)))  # every frame once
    for first in firsts[1:]:
        assert containers[first] != containers[first - 1], "a job starts inside a chunk the one before read"
    sizes = [len(j.indices[topic]) for j in jobs]
    assert max(sizes) <= 2 * 16 and np.mean(sizes) >= 16 * 0.9

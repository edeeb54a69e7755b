"""One log scored by several worker processes: the same output as one process (timing aside)."""

from __future__ import annotations

import json
from pathlib import Path

from mcap.reader import make_reader

from memlog.io import FrameWindow
from memlog.scoring.config import ScoreConfig
from memlog.steps.parallel import InProcess, Processes, threads_per_worker
from memlog.steps.score import plan_chunks, score
from memlog.io.open import open_log
from tests.conftest import FIXTURES


def _normalised(path: Path) -> tuple[list[tuple], dict[str, dict[str, str]]]:
    """Every message (topic, times, sequence, bytes), with the timing fields of score records
    removed; and the metadata with the run's timing removed."""
    msgs = []
    with open(path, "rb") as fh:
        r = make_reader(fh, validate_crcs=True)
        for _, ch, m in r.iter_messages(log_time_order=False):
            data = bytes(m.data)
            if ch.topic.endswith("/memlog/scores"):
                rec = json.loads(data)
                rec.pop("timing_ms")
                data = json.dumps(rec, sort_keys=True).encode()
            msgs.append((ch.topic, m.log_time, m.publish_time, m.sequence, data))
        meta = {md.name: dict(md.metadata) for md in r.iter_metadata()}
    summary = {k: json.loads(v) for k, v in meta["memlog_summary"].items()}
    summary.pop("seconds")
    summary.pop("output")
    for t in summary["topics"].values():
        t.pop("mean_ms_per_frame")
    meta["memlog_summary"] = summary
    return msgs, meta


def test_two_workers_write_the_same_log_as_one(tmp_path: Path) -> None:
    log = FIXTURES / "demo.mcap"
    cfg = ScoreConfig(all_scores=True)
    window = FrameWindow(("/camera/image/compressed",), stride=2)
    one = score(log, tmp_path / "one.mcap", cfg, window)
    two = score(log, tmp_path / "two.mcap", cfg, window, workers=2, chunk_frames=1)
    assert one.topics["/camera/image/compressed"].scored == two.topics["/camera/image/compressed"].scored == 4
    a_msgs, a_meta = _normalised(tmp_path / "one.mcap")
    b_msgs, b_meta = _normalised(tmp_path / "two.mcap")
    assert a_msgs == b_msgs  # same records, same order in the file
    assert a_meta == b_meta  # same config, model hashes, devices, counts


def test_chunks_cover_the_window_in_order() -> None:
    with open_log(FIXTURES / "demo.mcap") as log:
        window = FrameWindow(stride=3)
        chunks = plan_chunks(log, window, 4)
        want = [(f.topic, f.index, f.log_time_ns) for f in log.frames(stride=3)]
    got = []
    for c in chunks:
        assert c.n <= 4
        got.extend(sorted((t, i) for t, idx in c.indices.items() for i in idx))
    assert sorted(got) == sorted((t, i) for t, i, _ in want)
    assert sum(c.n for c in chunks) == len(want)
    assert all(a.end_ns <= b.start_ns + 1 for a, b in zip(chunks, chunks[1:]))  # log-time order
    for c in chunks:  # every frame of a chunk lies in its time range
        for t, i, ts in want:
            if i in c.indices.get(t, ()):
                assert c.start_ns <= ts < c.end_ns


def test_executors_keep_job_order() -> None:
    jobs = [(i,) for i in range(12)]
    assert list(InProcess().map_ordered(abs, jobs)) == list(range(12))
    ex = Processes(2, ahead=3)
    try:
        assert list(ex.map_ordered(abs, [(-i,) for i in range(12)])) == list(range(12))
    finally:
        ex.close()
    assert threads_per_worker(2, 0) >= 1 and threads_per_worker(4, 3) == 3

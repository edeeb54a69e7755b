"""One log scored by several worker processes: the same output as one process (timing aside)."""

from __future__ import annotations

import os
import time
from pathlib import Path

import pytest

from memlog.io import FrameWindow
from memlog.scoring.config import ScoreConfig
from memlog.steps.parallel import InProcess, Processes, threads_per_worker
from memlog.steps.score import plan_chunks, score
from memlog.io.open import open_log
from tests.conftest import FIXTURES, repeating_log
from tests.same_outputs import normalised_scored as _normalised


def test_two_workers_write_the_same_log_as_one(tmp_path: Path) -> None:
    log = FIXTURES / "demo.mcap"
    cfg = ScoreConfig(all_scores=True)
    window = FrameWindow(("/camera/image/compressed",), stride=2)
    one = score(log, tmp_path / "one.mcap", cfg, window)
    two = score(log, tmp_path / "two.mcap", cfg, window, workers=2, chunk_frames=1)
    assert one.topics["/camera/image/compressed"].scored == two.topics["/camera/image/compressed"].scored == 4
    a_msgs, a_scores, a_meta = _normalised(tmp_path / "one.mcap")
    b_msgs, b_scores, b_meta = _normalised(tmp_path / "two.mcap")
    assert a_msgs == b_msgs  # same records (annotations incl.), same order in the file
    assert a_scores == b_scores  # same scores, bit for bit
    assert a_meta == b_meta  # same config, model hashes, devices, counts


@pytest.mark.parametrize("indexed", [True, False])
def test_chunks_cover_the_window_in_order(indexed: bool) -> None:
    with open_log(FIXTURES / "demo.mcap") as log:
        if not indexed:  # plan by reading the messages, as for a log without an index
            log.topic_times = lambda topic: None  # type: ignore[method-assign]
        window = FrameWindow(stride=3)
        chunks = plan_chunks(log, window, 4)
        want = [(f.topic, f.index, f.log_time_ns) for f in log.frames(stride=3)]
    got = []
    for c in chunks:
        assert c.n <= 4 or len({ts for t, i, ts in want if i in c.indices.get(t, ())}) == 1
        got.extend(sorted((t, i) for t, idx in c.indices.items() for i in idx))
    assert sorted(got) == sorted((t, i) for t, i, _ in want)
    assert sum(c.n for c in chunks) == len(want)
    assert all(a.end_ns <= b.start_ns + 1 for a, b in zip(chunks, chunks[1:]))  # log-time order
    for c in chunks:  # every frame of a chunk lies in its time range
        for t, i, ts in want:
            if i in c.indices.get(t, ()):
                assert c.start_ns <= ts < c.end_ns


def _finish_late(i: int, delay: float) -> tuple[int, float]:
    """A job that sleeps ``delay`` seconds, then says which job it was and when it finished."""
    time.sleep(delay)
    return i, time.monotonic()


def _pid_after(delay: float) -> int:
    time.sleep(delay)
    return os.getpid()


def _started(ex: Processes) -> Processes:
    """``ex`` once each of its workers has run a job (spawned workers start one by one, each
    importing the jobs' modules), so jobs timed next start when they are handed out."""
    seen: set[int] = set()
    deadline = time.monotonic() + 60
    while len(seen) < ex.workers and time.monotonic() < deadline:
        seen |= set(ex.map_ordered(_pid_after, [(0.2,)] * ex.workers))
    return ex


# Earlier jobs take longer: on two workers job 1 and 2 finish before job 0 (job 0 holds one
# worker for 0.8 s while the other runs 1, then 2, ...), so an executor that gave results back
# as they complete would return 1 before 0.
_LATE_JOBS = [(0, 0.8), (1, 0.4), (2, 0.0), (3, 0.0), (4, 0.0), (5, 0.0)]


@pytest.mark.parametrize("make", [InProcess, lambda: _started(Processes(2, ahead=3))], ids=["InProcess", "Processes"])
def test_executors_keep_job_order(make) -> None:  # type: ignore[no-untyped-def]
    ex = make()
    try:
        got = list(ex.map_ordered(_finish_late, _LATE_JOBS))
    finally:
        ex.close()
    assert [i for i, _ in got] == [i for i, _ in _LATE_JOBS]  # job order ...
    finished = [i for i, _ in sorted(got, key=lambda r: r[1])]
    if ex.workers > 1:  # ... although the jobs did finish in another order (one process runs them in turn)
        assert finished.index(1) < finished.index(0), finished
    assert threads_per_worker(2, 0) >= 1 and threads_per_worker(4, 3) == 3


def test_a_pool_that_lost_a_worker_says_it_is_broken() -> None:
    """``Processes.broken`` turns true when a worker dies, so ``memlog batch`` starts no log on it."""
    from concurrent.futures.process import BrokenProcessPool

    from tests.worker_kill import die_now

    ex = Processes(2)
    try:
        assert list(ex.map_ordered(_finish_late, [(0, 0.0)])) and not ex.broken
        with pytest.raises(BrokenProcessPool):
            list(ex.map_ordered(die_now, [(1,)]))
        assert ex.broken
    finally:
        ex.close()


def test_repeated_frames_share_one_scoring_across_workers(tmp_path: Path) -> None:
    from memlog.outputs.annotated import read_scores

    log = tmp_path / "stop.mcap"
    repeating_log(log)
    cfg = ScoreConfig(all_scores=True)
    one = score(log, tmp_path / "one.mcap", cfg)
    score(log, tmp_path / "two.mcap", cfg, workers=2, chunk_frames=2)  # a chunk starts inside the stop
    assert _normalised(tmp_path / "one.mcap") == _normalised(tmp_path / "two.mcap")
    recs = read_scores(tmp_path / "one.mcap")["/camera/image/compressed"]
    shared = [(r["frame_index"], r["shared"], r["shared_from"]) for r in recs]
    assert shared == [(0, False, 0), (1, False, 1), (2, True, 1), (3, True, 1), (4, False, 4), (5, False, 5),
                      (6, False, 6), (7, False, 7)]  # the loop is no repeat of the previous frame
    for k in (2, 3):
        for key in ("ms", "ss", "es", "memorability", "selected"):
            assert recs[k][key] == recs[1][key]
    off = score(log, tmp_path / "off.mcap", cfg.replace(duplicates="off"))
    frame1 = recs[1]["crops_scored"]  # the two repeats of frame 1 did not go through ResMem again
    assert one.topics["/camera/image/compressed"].crops_run == off.topics["/camera/image/compressed"].crops_run - 2 * frame1
    assert frame1 > 0


def test_near_duplicates_are_shared_only_when_asked() -> None:
    """``duplicates="near"`` (fast mode) treats a re-encoded copy of a frame as the same frame, a
    different view never; ``identical`` only pixel-identical frames."""
    import cv2
    import numpy as np

    with open_log(FIXTURES / "demo.mcap") as log:
        frames = [f.decode_bgr() for f in log.frames(["/camera/image/compressed"])]
    a, other = frames[0], frames[4]
    ok, jpg = cv2.imencode(".jpg", a, [cv2.IMWRITE_JPEG_QUALITY, 80])
    assert ok
    recoded = cv2.imdecode(jpg, cv2.IMREAD_COLOR)  # the same view, other pixels (a camera's noise)
    assert not np.array_equal(recoded, a)
    from memlog.scoring.scorer import Scorer

    near = Scorer(ScoreConfig(mode="fast", duplicates="near"))
    same = Scorer(ScoreConfig())
    assert near.same_frame(near.duplicate_key(a), near.duplicate_key(recoded.copy()))
    assert not near.same_frame(near.duplicate_key(a), near.duplicate_key(other))
    assert same.same_frame(same.duplicate_key(a), same.duplicate_key(a.copy()))
    assert not same.same_frame(same.duplicate_key(a), same.duplicate_key(recoded))

"""How memlog's worker processes start and what reaches them: local workers are spawned (never a
fork of the driver), given what the driver's settings say, and their log records come back to the
driver's loggers; a ROS 2 bag's sqlite connection is never used across a fork; whether a pool lost a
worker is known without the standard library's private state."""

from __future__ import annotations

import ast
import hashlib
import logging
import os
import signal
import time
from pathlib import Path

import pytest

from memlog.errors import LogReadError
from memlog.io.image import max_pixels, set_max_pixels
from memlog.io.open import open_log
from memlog.progress import info, is_quiet, warning
from memlog.runtime import current, use
from memlog.steps.parallel import Processes
from tests.conftest import FIXTURES, ROOT, shared

#: Set by a test in the driver after import: a spawned worker imports this module afresh and sees None.
_DRIVER_MARK: str | None = None


def _what_the_worker_sees() -> tuple[int, str | None, bool, int]:
    return os.getppid(), _DRIVER_MARK, is_quiet(), max_pixels()


def _pid() -> int:
    time.sleep(0.2)  # long enough for the other job to be taken by the other worker
    return os.getpid()


def _log(text: str, fail: bool) -> str:
    warning(f"worker {text}")
    info(f"worker info {text}")
    logging.getLogger("memlog").debug(f"worker debug {text}")
    logging.getLogger("memlog.io").warning(f"worker reader {text}")  # (the job's report takes it back)
    if fail:
        raise LogReadError(f"job {text} failed")
    return text


def test_local_workers_are_spawned_not_forked(monkeypatch: pytest.MonkeyPatch) -> None:
    """A worker is a new interpreter: a module global the driver set after import is not there."""
    from tests import test_start_method

    monkeypatch.setattr(test_start_method, "_DRIVER_MARK", "set in the driver")
    ex = Processes(2)
    try:
        (ppid, mark, _, _), = ex.map_ordered(_what_the_worker_sees, [()])
    finally:
        ex.close()
    assert ppid == os.getpid()  # a child of this process ...
    assert mark is None  # ... that imported this module itself (a fork would see "set in the driver")


@pytest.mark.parametrize("quiet", [True, False])
def test_quiet_and_the_pixel_cap_reach_the_workers(quiet: bool) -> None:
    with use(current()):  # the runtime context in force now is put back after the test
        set_max_pixels(12345)
        ex = Processes(2, quiet=quiet)
        try:
            (_, _, got_quiet, cap), = ex.map_ordered(_what_the_worker_sees, [()])
        finally:
            ex.close()
    assert (got_quiet, cap) == (quiet, 12345)


def test_what_a_worker_logs_is_said_by_the_drivers_loggers(caplog: pytest.LogCaptureFixture) -> None:
    """A job's records reach the driver's handlers (here pytest's), at the driver's levels, in job
    order, also those of a job that failed (before its exception); its readers' warnings do not
    (they come back in its report, and the driver's reader says them once)."""
    caplog.set_level(logging.INFO, logger="memlog")
    ex = Processes(2)
    try:
        assert list(ex.map_ordered(_log, [("a", False), ("b", False)])) == ["a", "b"]
        with pytest.raises(LogReadError, match="job c failed"):
            list(ex.map_ordered(_log, [("c", True)]))
    finally:
        ex.close()
    got = [(r.name, r.levelname, r.getMessage()) for r in caplog.records if "worker" in r.getMessage()]
    assert got == [("memlog", "WARNING", "worker a"), ("memlog", "INFO", "worker info a"),
                   ("memlog", "WARNING", "worker b"), ("memlog", "INFO", "worker info b"),
                   ("memlog", "WARNING", "worker c"), ("memlog", "INFO", "worker info c")]
    assert all(r.process != os.getpid() for r in caplog.records if "worker" in r.getMessage())


def test_a_worker_that_dies_between_jobs_breaks_the_pool() -> None:
    """A worker killed while it waits for a job (the kernel's OOM killer picks any process): no job
    failed, yet the pool says it is broken, so ``memlog batch`` starts no log on it."""
    ex = Processes(2)
    try:
        pids = set(ex.map_ordered(_pid, [(), ()]))
        assert not ex.broken
        os.kill(next(iter(pids)), signal.SIGKILL)
        deadline = time.monotonic() + 30
        while not ex.broken and time.monotonic() < deadline:
            time.sleep(0.1)
        assert ex.broken
    finally:
        ex.close()


def _private_names_read(path: Path) -> list[str]:
    """``getattr(x, "_name")``-style reads of a private attribute by name, and ``self.a._b``: another
    object's private attribute reached through one of ours."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and \
                node.func.id in ("getattr", "hasattr", "setattr", "delattr") and len(node.args) >= 2:
            name = node.args[1]
            if isinstance(name, ast.Constant) and isinstance(name.value, str) and name.value.startswith("_") \
                    and not name.value.startswith("__"):
                found.append(f"{path.name}:{node.lineno}: {node.func.id}(..., {name.value!r})")
        if isinstance(node, ast.Attribute) and node.attr.startswith("_") and not node.attr.startswith("__") and \
                isinstance(node.value, ast.Attribute) and isinstance(node.value.value, ast.Name) and \
                node.value.value.id == "self" and path.parent.name == "steps":
            found.append(f"{path.name}:{node.lineno}: self.{node.value.attr}.{node.attr}")
    return found


def test_no_private_attribute_of_another_library_is_read() -> None:
    """Whether a pool is broken comes from its jobs (``BrokenProcessPool``, public), not from
    ``ProcessPoolExecutor._broken``, which a Python release may rename."""
    found = [hit for path in sorted((ROOT / "memlog").rglob("*.py")) for hit in _private_names_read(path)]
    assert not found, found


def _frames(reader) -> list[tuple[str, int, int, str]]:  # type: ignore[no-untyped-def]
    return [(f.topic, f.index, f.log_time_ns, hashlib.sha256(f.payload.data).hexdigest()) for f in reader.frames()]


@pytest.mark.parametrize("bag", [pytest.param("fixture", id="fixture"),
                                 pytest.param("euroc", id="euroc", marks=pytest.mark.shared)])
def test_a_forked_child_opens_its_own_sqlite_connection(bag: str) -> None:
    """A process forked from one that has a ROS 2 .db3 bag open (other code's fork: memlog's own
    workers are spawned) reads it through a connection of its own; the parent's still works."""
    path = FIXTURES / "ros2_sqlite" if bag == "fixture" else shared("euroc_micro_ros2_db3")
    with open_log(path) as reader:
        dbs = reader._dbs  # type: ignore[attr-defined]
        assert dbs
        ours = [db.con for db in dbs]
        want = _frames(reader)
        assert want
        pid = os.fork()
        if pid == 0:  # the child: a new connection per file, the same frames; no cleanup (as a killed process)
            code = 3
            try:
                theirs = [db.con for db in dbs]
                code = 1 if any(a is b for a, b in zip(theirs, ours)) else 2 if _frames(reader) != want else 0
                if code == 0 and [db.con for db in dbs] != theirs:
                    code = 4  # opened again on every use
            finally:
                os._exit(code)
        _, status = os.waitpid(pid, 0)
        code = os.waitstatus_to_exitcode(status)
        assert code == 0, {1: "the child used the parent's connection", 2: "the child read other frames",
                           3: "the child failed", 4: "the child opened a connection per use"}.get(code, code)
        assert [db.con for db in dbs] == ours and _frames(reader) == want  # the parent's, untouched


def test_a_damaged_log_on_workers_is_warned_once(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                 caplog: pytest.LogCaptureFixture) -> None:
    """Each spawned worker learns a cut log itself (its warnings, said as it opens the log, come
    back in its jobs' reports), yet each warning is said once, by the driver."""
    from memlog.steps.map import MapConfig, make_map
    from tests.stand_in import use_stand_in
    from tests.test_numbering import _damaged

    use_stand_in(monkeypatch)
    path = _damaged("mcap-cut", tmp_path)
    caplog.set_level(logging.WARNING, logger="memlog")
    res = make_map(path, tmp_path / "map.mcap", MapConfig(workers=2))
    assert res.report is not None and res.report.truncated
    texts = [r.getMessage() for r in caplog.records if str(path) in r.getMessage()]
    assert texts and len(texts) == len(set(texts)), texts


def _count_frames(path: str) -> int:
    with open_log(path) as reader:
        reader.quiet_warnings()
        return sum(1 for _ in reader.frames())


def test_the_temporary_files_of_a_worker_are_removed_when_the_pool_closes(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A worker that opens a file-compressed ROS 2 bag decompresses it into a temporary file of its
    own (kept for its next jobs); a spawned worker ends as a process does, removing it (a forked
    one ended without cleaning up, leaving one copy of the bag per worker)."""
    import tempfile


    temp = tmp_path / "temp"
    temp.mkdir()
    monkeypatch.setenv("TMPDIR", str(temp))
    monkeypatch.setattr(tempfile, "tempdir", str(temp))
    from tests.conftest import zstd_bag

    bag = zstd_bag(tmp_path / "zbag")
    ex = Processes(2)
    try:
        assert list(ex.map_ordered(_count_frames, [(str(bag),)] * 4)) == [4] * 4
    finally:
        ex.close()
    assert sorted(p.name for p in temp.iterdir()) == []

"""The runtime context (:mod:`memlog.runtime`): the environment read once into it, settings that reach
the worker processes with it, and the caches it owns (the opened-log cache, the bounded model cache)."""

from __future__ import annotations

import os
import pickle
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from memlog.errors import ConfigError, ImageDecodeError, MemlogError, ScoringError
from memlog.io import _opened
from memlog.io.image import DEFAULT_MAX_PIXELS, decode_bgr, max_pixels, set_max_pixels
from memlog.io.types import ImagePayload
from memlog.models.fetch import cache_dir
from memlog.runtime import ModelCache, OpenedLogs, Runtime, current, install, use
from memlog.scoring.entropy import entropy_kernel
from memlog.steps.parallel import cached, make_executor
from tests.conftest import ROOT

W, H = 70, 50


def _decode_in_worker() -> tuple[int, int, str]:
    """A job: this worker's pid and pixel cap, and what decoding a 70x50 raw frame gives."""
    img = np.zeros((H, W, 3), np.uint8)
    try:
        shape = decode_bgr(ImagePayload("raw", "bgr8", img.tobytes(), W, H, W * 3)).shape
        what = f"decoded {shape}"
    except ImageDecodeError as exc:
        what = f"refused: {exc}"
    return os.getpid(), max_pixels(), what


def _worker_settings() -> tuple[int, str, int, str | None]:
    return os.getpid(), entropy_kernel(), current().model_cache_size, current().cache_dir


# ------------------------------------------------------------------------- from the environment


def test_from_environment_reads_the_mapping_it_is_given() -> None:
    rt = Runtime.from_environment({"MEMLOG_MAX_PIXELS": " 1234 ", "MEMLOG_ENTROPY_KERNEL": "NumPy",
                                   "MEMLOG_DEBUG": "1", "MEMLOG_CACHE_DIR": "~/models", "XDG_CACHE_HOME": "/xdg",
                                   "RAY_ADDRESS": "ray://head:10001", "PATH": "/bin"})
    assert (rt.max_pixels, rt.entropy_kernel, rt.debug, rt.cache_dir, rt.ray_address) == (
        1234, "numpy", True, "~/models", "ray://head:10001")
    assert rt.cache_path() == Path("~/models").expanduser()
    xdg = Runtime.from_environment({"XDG_CACHE_HOME": "/xdg"})
    assert xdg.cache_dir == str(Path("/xdg") / "memlog") and xdg.cache_path() == Path("/xdg/memlog")
    # unset or empty: the defaults
    empty = {"MEMLOG_MAX_PIXELS": "", "MEMLOG_ENTROPY_KERNEL": "", "MEMLOG_DEBUG": "", "MEMLOG_CACHE_DIR": "",
             "XDG_CACHE_HOME": "", "RAY_ADDRESS": ""}
    assert Runtime.from_environment({}) == Runtime.from_environment(empty) == Runtime()
    assert Runtime().cache_path() == Path.home() / ".cache" / "memlog"
    assert Runtime.from_environment({"MEMLOG_ENTROPY_KERNEL": "auto"}).entropy_kernel == "auto"


def test_from_environment_does_not_read_os_environ(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("MEMLOG_MAX_PIXELS", "7")
    monkeypatch.setenv("MEMLOG_ENTROPY_KERNEL", "numpy")
    monkeypatch.setenv("MEMLOG_CACHE_DIR", "/somewhere")
    assert Runtime.from_environment({}) == Runtime()
    before = current()
    assert max_pixels() == before.max_pixels  # the process's context did not change either


@pytest.mark.parametrize(("name", "value", "error"), [
    ("MEMLOG_MAX_PIXELS", "lots", ConfigError),
    ("MEMLOG_MAX_PIXELS", "0", ConfigError),
    ("MEMLOG_MAX_PIXELS", "-5", ConfigError),
    ("MEMLOG_MAX_PIXELS", "1e6", ConfigError),
    ("MEMLOG_ENTROPY_KERNEL", "fortran", ScoringError),
    ("MEMLOG_DEVICE", "gpu", ConfigError),
])
def test_a_bad_value_names_its_variable(name: str, value: str, error: type[MemlogError]) -> None:
    with pytest.raises(error, match=name):
        Runtime.from_environment({name: value})
    seen: list[MemlogError] = []
    rt = Runtime.from_environment({name: value, "MEMLOG_DEBUG": "yes"}, on_error=seen.append)
    assert [type(e) for e in seen] == [error] and name in str(seen[0])
    assert rt == Runtime(debug=True)  # the bad one at its default, the others read


def test_settings_are_checked() -> None:
    with pytest.raises(ConfigError, match="max pixels"):
        Runtime(max_pixels=0)
    with pytest.raises(ScoringError, match="entropy kernel"):
        Runtime(entropy_kernel="gpu")  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="model cache"):
        Runtime(model_cache_size=0)
    with pytest.raises(ValueError, match="max pixels"):
        set_max_pixels(0)


def test_the_cli_reads_the_environment(tmp_path: Path) -> None:
    """The command reads the environment itself (a bad value is a usage error naming it); the
    library does not (``MEMLOG_MAX_PIXELS`` in a subprocess's environment still sets the cap)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("MEMLOG_")}
    env["PYTHONPATH"] = str(ROOT)
    args = [sys.executable, "-m", "memlog", "convert", str(tmp_path / "missing.mcap"), "-o", str(tmp_path / "o.mcap")]
    r = subprocess.run(args, env={**env, "MEMLOG_MAX_PIXELS": "lots"}, capture_output=True, text=True, cwd=ROOT)
    assert r.returncode == 2 and "MEMLOG_MAX_PIXELS must be an integer >= 1, got 'lots'" in r.stderr, r.stderr
    assert r.stderr.count("MEMLOG_MAX_PIXELS") == 1, r.stderr  # said once, by the command (not also by the import)
    r = subprocess.run([sys.executable, "-c", "import memlog"], env={**env, "MEMLOG_DEVICE": "gpu"},
                       capture_output=True, text=True, cwd=ROOT)
    assert r.returncode == 0 and "MEMLOG_DEVICE must be auto, cpu or cuda, got 'gpu'; the default is used" in r.stderr
    code = "import memlog.runtime as r; print(r.current().max_pixels, r.current().entropy_kernel)"
    r = subprocess.run([sys.executable, "-c", code], env={**env, "MEMLOG_MAX_PIXELS": "321",
                                                          "MEMLOG_ENTROPY_KERNEL": "numpy"},
                       capture_output=True, text=True, cwd=ROOT)
    assert r.stdout.split() == ["321", "numpy"], r.stderr


def test_current_default() -> None:
    """With no memlog variable set, the context the package's import installs is the default one."""
    env = {k: v for k, v in os.environ.items() if not k.startswith(("MEMLOG_", "XDG_CACHE_HOME", "RAY_ADDRESS"))}
    code = ("from memlog.runtime import Runtime, current; from memlog.io.image import max_pixels;"
            "print(current() == Runtime(), max_pixels())")
    r = subprocess.run([sys.executable, "-c", code], env={**env, "PYTHONPATH": str(ROOT)}, capture_output=True,
                       text=True, cwd=ROOT)
    assert r.stdout.split() == ["True", str(DEFAULT_MAX_PIXELS)], r.stderr
    rt = Runtime()
    assert (rt.max_pixels, rt.entropy_kernel, rt.model_cache_size, rt.cache_dir, rt.debug, rt.ray_address) == (
        100_000_000, "auto", 8, None, False, None)


# ------------------------------------------------------------------------- installing


def test_install_use_and_replace() -> None:
    before = current()
    with use(before.replace(max_pixels=99)) as rt:
        assert current() is rt and max_pixels() == 99
        assert rt.opened is before.opened and rt.models is before.models  # this process's caches
        set_max_pixels(98)  # installs a replaced context
        assert current() is not rt and max_pixels() == 98 and current().opened is before.opened
    assert current() is before
    old = install(before.replace(cache_dir="/tmp/memlog-models"))
    try:
        assert old is before and cache_dir() == Path("/tmp/memlog-models")
    finally:
        install(old)
    assert current() is before
    with pytest.raises(TypeError):
        install("not a runtime")  # type: ignore[arg-type]


def test_a_pickled_runtime_has_its_settings_and_empty_caches() -> None:
    rt = Runtime(max_pixels=5, entropy_kernel="numpy", model_cache_size=3, cache_dir="/c", debug=True)
    rt.models.get("k", object)
    got = pickle.loads(pickle.dumps(rt))
    assert got == rt and got.settings() == rt.settings()
    assert got.models is not rt.models and len(got.models) == 0 and got.models.max_entries == 3
    assert got.opened is not rt.opened and len(got.opened) == 0


# ------------------------------------------------------------------------- workers


def test_the_pixel_cap_reaches_a_worker_process() -> None:
    """``--workers 2``: the cap set here (after the import, so not by the environment) is installed
    in each worker, which refuses a frame over it."""
    with use(current()):
        set_max_pixels(W * H - 1)
        here = _decode_in_worker()
        assert here[1] == W * H - 1 and here[2].startswith("refused") and "70x50" in here[2]
        ex = make_executor(2)
        try:
            got = list(ex.map_ordered(_decode_in_worker, [(), ()]))
        finally:
            ex.close()
    assert all(pid != os.getpid() for pid, _, _ in got)
    assert all(cap == W * H - 1 and what.startswith("refused") and "70x50" in what for _, cap, what in got), got
    assert max_pixels() != W * H - 1  # put back after the with block


def test_the_entropy_kernel_and_cache_settings_reach_a_worker_process() -> None:
    with use(current().replace(entropy_kernel="numpy", model_cache_size=3, cache_dir="/models/here")):
        ex = make_executor(2)
        try:
            got = list(ex.map_ordered(_worker_settings, [()]))
        finally:
            ex.close()
    (pid, kernel, size, where), = got
    assert pid != os.getpid() and (kernel, size, where) == ("numpy", 3, "/models/here")


# ------------------------------------------------------------------------- the caches


def test_the_model_cache_evicts_beyond_its_bound() -> None:
    made: list[str] = []

    def make(key: str) -> object:
        made.append(key)
        return object()

    cache = ModelCache(2)
    a = cache.get("a", lambda: make("a"))
    cache.get("b", lambda: make("b"))
    assert cache.get("a", lambda: make("a")) is a  # kept; now the most recently used
    cache.get("c", lambda: make("c"))  # over the bound: b (least recently used) goes
    assert "b" not in cache and "a" in cache and "c" in cache and len(cache) == 2
    cache.get("b", lambda: make("b"))
    assert made == ["a", "b", "c", "b"]
    cache.resize(1)
    assert len(cache) == 1 and "b" in cache
    with pytest.raises(ConfigError):
        ModelCache(0)


def test_cached_uses_the_bounded_cache_of_the_context() -> None:
    with use(Runtime(model_cache_size=2)) as rt:
        for k in range(5):
            assert cached(("test", k), lambda k=k: k * 10) == k * 10  # type: ignore[misc]
        assert len(rt.models) == 2 and ("test", 4) in rt.models and ("test", 0) not in rt.models
    assert ("test", 4) not in current().models


class _Entry:
    """A stand-in for what a reader learned about one log."""

    def __init__(self) -> None:
        self.said: set[str] = set()
        self.closed = False

    def close(self) -> None:
        self.closed = True


def test_the_opened_log_cache_counts_its_users_and_scans() -> None:
    logs = OpenedLogs(max_entries=1)
    a, made = logs.learned("a", _Entry)
    assert made and logs.users("a") == 1
    again, made = logs.learned("a", _Entry)
    assert again is a and not made and logs.users("a") == 2
    b, _ = logs.learned("b", _Entry)
    assert len(logs) == 2  # both in use: none is dropped
    logs.release("a")
    logs.release("a")
    assert logs.users("a") == 0 and a.closed and "a" not in logs  # unused, over the bound: dropped
    logs.release("b")
    assert not b.closed and "b" in logs  # within the bound: kept for the next reader
    logs.clear()
    assert b.closed and len(logs) == 0
    logs.count_scan("/x.mcap")
    logs.count_scan("/x.mcap")
    assert logs.scans() == {"/x.mcap": 2}


def test_the_opened_helpers_use_the_context_cache(tmp_path: Path) -> None:
    log = tmp_path / "x.mcap"
    log.write_bytes(b"")
    real = os.path.realpath(log)
    with use(Runtime()) as rt:
        key = _opened.file_key("mcap", str(log))
        entry, made = _opened.learned(key, _Entry)
        assert made and key in rt.opened and rt.opened.users(key) == 1
        _opened.counted_scan(real)
        assert _opened.scans(str(log)) == 1 and _opened.scans() == {real: 1}
        _opened.release(key)
        _opened.clear_cache()
        assert entry.closed and key not in rt.opened
    assert _opened.scans(str(log)) == 0  # another context's counts


def test_a_reader_releases_its_entry_where_it_learned_it(tmp_path: Path) -> None:
    """A reader opened under one runtime context and closed under another gives its entry back to the
    cache it came from (it is then unused there, and dropped by clear())."""
    from memlog.io.open import open_log
    from tests.conftest import FIXTURES

    log = tmp_path / "cut.mcap"
    data = (FIXTURES / "demo.mcap").read_bytes()
    log.write_bytes(data[: len(data) * 3 // 4])
    inner = Runtime(cache_dir=str(tmp_path / "cache"))
    with use(inner):
        reader = open_log(log)
        reader.quiet_warnings()
    key = reader._key
    assert inner.opened.users(key) == 1
    reader.close()  # (the package's context in force now)
    assert inner.opened.users(key) == 0
    inner.opened.clear()
    assert key not in inner.opened

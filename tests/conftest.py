"""Shared test fixtures: paths to the repo's fixtures and to the shared real-camera logs.

The shared logs (EuRoC, Nordland) sit in ``../shared/data`` beside the repository (or
``$MEMLOG_SHARED_DATA``). A user's clone does not have them: tests that need them skip, saying
where the data comes from. CI sets ``MEMLOG_REQUIRE_SHARED=1`` (``.ci/run``), which turns
every such skip into a failure, so CI always runs them.
"""

from __future__ import annotations

import importlib.util
import os
import shutil
from pathlib import Path
from collections import Counter
from collections.abc import Iterator
from types import ModuleType
from typing import NoReturn

import pytest

ROOT = Path(__file__).resolve().parent.parent
FIXTURES = ROOT / "fixtures"
SHARED = Path(os.environ.get("MEMLOG_SHARED_DATA", ROOT.parent / "shared" / "data"))

SHARED_LOGS = [
    "euroc_micro_ros2.mcap",
    "euroc_micro_foxglove.mcap",
    "euroc_micro_ros1.bag",
    "euroc_micro_ros2_db3",
    "nordland_dev_summer.mcap",
    "nordland_dev_winter.mcap",
]
FIXTURE_LOGS = [
    "demo.mcap",
    "ros1.bag",
    "ros2_sqlite",
    "ros2_mcap",
    "foxglove_json.mcap",
    "foxglove_proto.mcap",
    "ros2idl.mcap",
    "ros1.mcap",
    "encodings.mcap",
]


REQUIRE_SHARED = os.environ.get("MEMLOG_REQUIRE_SHARED", "") not in ("", "0")


def skip_or_fail(why: str) -> NoReturn:
    """Skip a test that cannot run on this machine (a user's clone); in CI
    (``MEMLOG_REQUIRE_SHARED=1``, set by ``.ci/run``) every test must run, so it fails instead."""
    if REQUIRE_SHARED:
        pytest.fail(why + "; MEMLOG_REQUIRE_SHARED=1 requires them")
    pytest.skip(why)


def shared(name: str) -> Path:
    """Path of a shared log or file; skips (fails when ``MEMLOG_REQUIRE_SHARED=1``) without it."""
    path = SHARED / name
    if not path.exists():
        skip_or_fail(f"{path} is missing: the shared EuRoC/Nordland logs are the project's shared data "
                     "(../shared/data beside the repository, or $MEMLOG_SHARED_DATA)")
    return path


def chromium() -> str:
    """The headless Chromium that renders the HTML report; skips (fails when ``MEMLOG_REQUIRE_SHARED=1``) without it."""
    path = shutil.which("chromium") or shutil.which("chromium-browser")
    if path is None:
        skip_or_fail("chromium is missing: the report's rendering tests need a headless Chromium "
                     "(Debian: apt-get install chromium; .ci/run installs it)")
    return path


def load_fixture_script() -> ModuleType:
    spec = importlib.util.spec_from_file_location("make_fixtures", FIXTURES / "make_fixtures.py")
    assert spec and spec.loader
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _logger_state() -> tuple[list[object], int, bool, bool]:
    from memlog.progress import LOGGER, is_quiet

    return list(LOGGER.handlers), LOGGER.level, LOGGER.propagate, is_quiet()


def _set_logger_state(state: tuple[list[object], int, bool, bool]) -> None:
    from memlog.progress import LOGGER, set_quiet

    LOGGER.handlers[:] = state[0]  # type: ignore[assignment]
    LOGGER.setLevel(state[1])
    LOGGER.propagate = state[2]
    set_quiet(state[3])


#: the ``memlog`` logger as the library leaves it, before any test ran the CLI in-process
_PRISTINE = _logger_state()


@pytest.fixture(autouse=True)
def _memlog_logger_restored() -> Iterator[None]:
    """Each test starts and ends with the ``memlog`` logger as the library leaves it: running the CLI
    in-process (``memlog.cli.app.main``, also in module-scoped fixtures, which run before this one)
    makes it print to stderr and stop propagating, which would hide the records of every later test
    from ``caplog``."""
    _set_logger_state(_PRISTINE)
    yield
    _set_logger_state(_PRISTINE)


@pytest.fixture(scope="session")
def fixture_script() -> ModuleType:
    return load_fixture_script()


@pytest.fixture(scope="session")
def source_frames(fixture_script: ModuleType) -> list:
    return fixture_script.source_frames()


@pytest.fixture(scope="session")
def drive_pair_evaluation(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``memlog evaluate`` of the Stromovka drive pair (``--seeds 2 --no-report``), run once for the
    session in its own process, as users run it, from a folder with ``-o evaluate``: that folder (the
    paths ``evaluate/results.json`` records are relative to it). ``test_drive_pair`` checks it
    against maps ``memlog map`` writes."""
    import subprocess
    import sys

    autumn, winter = shared("stromovka_drive_autumn.mcap"), shared("stromovka_drive_winter.mcap")
    truth = shared("stromovka_drive_truth.json")
    out = tmp_path_factory.mktemp("drive_pair_evaluation")
    cmd = [sys.executable, "-m", "memlog", "-q", "evaluate", "--reference", str(autumn), "--query", str(winter),
           "--truth", str(truth), "-o", "evaluate", "--seeds", "2", "--no-report"]
    proc = subprocess.run(cmd, cwd=out, env={**os.environ, "PYTHONPATH": str(ROOT)}, capture_output=True, text=True)
    assert proc.returncode == 0, f"memlog evaluate: exit {proc.returncode}\n{proc.stderr[-3000:]}"
    return out


@pytest.fixture(scope="session")
def drive_pair_maps(tmp_path_factory: pytest.TempPathFactory) -> dict[str, tuple[Path, Path]]:
    """The Stromovka drive pair through the CLI once for the session: ``memlog map`` of the autumn
    drive with ``--keep-fraction 1`` (``full``) and with the defaults (``default``), each then
    ``memlog localize`` of the winter drive: name -> (the map's Parquet, the match table)."""
    from memlog.cli.app import main

    autumn, winter = shared("stromovka_drive_autumn.mcap"), shared("stromovka_drive_winter.mcap")
    d = tmp_path_factory.mktemp("drive_pair_maps")
    out = {}
    for name, args in (("full", ["--keep-fraction", "1"]), ("default", [])):
        m = d / f"{name}.mcap"
        assert main(["-q", "map", str(autumn), "-o", str(m), *args]) == 0
        assert main(["-q", "localize", str(m.with_suffix(".parquet")), str(winter), "-o", str(d / f"{name}.x.parquet"),
                     "--map", str(m)]) == 0
        out[name] = (m.with_suffix(".parquet"), d / f"{name}.x.parquet")
    return out


@pytest.fixture()
def copy_of(tmp_path: Path):  # type: ignore[no-untyped-def]
    """Copy a fixture (file or bag directory) into tmp_path, writable, for damaging."""

    def _copy(name: str, base: Path = FIXTURES) -> Path:
        src = base / name
        dst = tmp_path / name
        if src.is_dir():
            shutil.copytree(src, dst)
            for p in dst.rglob("*"):
                p.chmod(0o644)
        else:
            shutil.copyfile(src, dst)
            dst.chmod(0o644)
        return dst

    return _copy


def repeating_log(path: Path) -> None:
    """demo's compressed frames with a stop (frame 1 repeated 3x) and a loop (frames 0-1 again)."""
    from memlog.io import McapLogWriter, open_log

    with open_log(FIXTURES / "demo.mcap") as log:
        msgs = list(log.messages(["/camera/image/compressed"]))
    order = [0, 1, 1, 1, 2, 3, 0, 1]
    with McapLogWriter(path, profile="ros2") as w:
        for k, i in enumerate(order):
            w.write(w.channel_for(msgs[i].channel), 1_700_000_000_000_000_000 + k * 100_000_000, msgs[i].data)


def zstd_bag(dest: Path) -> Path:
    """A copy of the fixture ROS 2 sqlite bag at ``dest`` with its .db3 compressed as a whole file
    (zstd, ``compression_mode: FILE``), as ``ros2 bag record --compression-mode file`` writes it."""
    import shutil

    import zstandard

    shutil.copytree(FIXTURES / "ros2_sqlite", dest)
    db = next(dest.glob("*.db3"))
    (dest / (db.name + ".zstd")).write_bytes(zstandard.ZstdCompressor().compress(db.read_bytes()))
    db.unlink()
    meta = dest / "metadata.yaml"
    meta.write_text(meta.read_text().replace(f"- {db.name}", f"- {db.name}.zstd")
                    .replace("compression_format: ''", "compression_format: zstd")
                    .replace("compression_mode: ''", "compression_mode: FILE"))
    return dest


def cut_copy(src: Path, dst: Path, fraction: float = 0.85) -> Path:
    """``src``'s first ``fraction`` of bytes at ``dst``: a recording that was never finished."""
    data = src.read_bytes()
    dst.write_bytes(data[: int(len(data) * fraction)])
    return dst


def count_chunk_reads(monkeypatch: pytest.MonkeyPatch) -> Counter[int]:
    """Counts, by offset, the chunks this process reads from an MCAP log itself (not from a job's spool)."""
    from memlog.io.mcap import reader as mcap_reader

    reads: Counter[int] = Counter()
    real = mcap_reader.McapLog._read_chunk_now

    def counting(self, ref):  # type: ignore[no-untyped-def]
        reads[ref.offset] += 1
        return real(self, ref)

    monkeypatch.setattr(mcap_reader.McapLog, "_read_chunk_now", counting)
    return reads

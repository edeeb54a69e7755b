"""``memlog batch`` without Ray: placement, manifests, usage errors before any work, local worker
processes giving the one-process outputs, and resume. (Ray itself: ``tests/test_batch_ray.py``.)

The resume test scores with the stand-in ResMem (``tests/stand_in.py``; local worker processes are
forked from the test process and inherit it); the last test runs the real models on a fixture log
of every format.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from memlog.cli.app import main
from memlog.errors import ConfigError, OutputPathError
from memlog.steps.batch import BatchConfig, batch, read_manifest
from memlog.steps.map import MapConfig
from memlog.steps.ray_pool import Placement, plan_placement
from tests.same_outputs import assert_same_outputs, reference
from tests.conftest import FIXTURES
from tests.stand_in import use_stand_in


# -- placement --------------------------------------------------------------------------------------
@pytest.mark.parametrize("cpus,gpus,kw,want", [
    (2, 0, {}, Placement(2, 1, 0.0)),  # this machine: two single-threaded actors
    (2, 0, {"threads": 2}, Placement(1, 2, 0.0)),
    (16, 0, {"workers": 3, "threads": 4}, Placement(3, 4, 0.0)),
    (64, 8, {}, Placement(64, 1, 0.125)),  # every core feeds a GPU: 8 actors per GPU
    (256, 2, {}, Placement(32, 1, 1 / 16)),  # at most 16 per GPU
    (64, 8, {"threads": 4}, Placement(16, 4, 0.5)),  # 8 CPUs per GPU / 4 threads: 2 per GPU
    (64, 8, {"device": "cpu"}, Placement(64, 1, 0.0)),  # GPUs left alone
    (8, 1, {"actors_per_gpu": 2, "threads": 2}, Placement(2, 2, 0.5)),
    (4, 2, {"device": "cuda"}, Placement(4, 1, 0.5)),
    (64, 8, {"workers": 10}, Placement(10, 1, 0.125)),
])
def test_placement_fits_the_cluster(cpus: int, gpus: int, kw: dict, want: Placement) -> None:
    got = plan_placement(cpus, gpus, **kw)
    assert got == want
    assert got.actors * got.threads <= cpus and got.actors * got.gpus <= gpus + 1e-9


@pytest.mark.parametrize("cpus,gpus,kw,flag", [
    (2, 0, {"workers": 3}, "--workers 3"),
    (2, 0, {"threads": 4}, "--threads 4"),
    (4, 0, {"device": "cuda"}, "--device cuda"),
    (8, 1, {"workers": 3, "actors_per_gpu": 2}, "--workers 3"),
])
def test_placement_that_cannot_fit_names_the_flag(cpus: int, gpus: int, kw: dict, flag: str) -> None:
    with pytest.raises(ConfigError, match=flag):
        plan_placement(cpus, gpus, **kw)


# -- arguments ------------------------------------------------------------------------------------
def test_manifest_lists_logs_relative_to_itself(tmp_path: Path) -> None:
    (tmp_path / "sub").mkdir()
    m = tmp_path / "sub" / "fleet.txt"
    m.write_text(f"# drives of monday\n\n  a.mcap  \n{FIXTURES / 'ros1.bag'}\n# b.bag\nbags/c\n")
    assert read_manifest(m) == [str(tmp_path / "sub" / "a.mcap"), str(FIXTURES / "ros1.bag"),
                                str(tmp_path / "sub" / "bags" / "c")]
    with pytest.raises(ConfigError, match="--manifest"):
        read_manifest(tmp_path / "nope.txt")


def test_usage_errors_before_any_work(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                      monkeypatch: pytest.MonkeyPatch) -> None:
    out = tmp_path / "out"
    from memlog.steps import ray_pool

    monkeypatch.setattr(ray_pool, "ray_available", lambda: False)  # as without memlog[ray]
    assert main(["batch", str(FIXTURES / "ros1.bag"), "-o", str(out), "--ray"]) == 2
    assert "pip install 'memlog[ray]'" in capsys.readouterr().err
    assert not out.exists()  # nothing done
    twin = tmp_path / "ros1.bag"
    twin.write_bytes((FIXTURES / "ros1.bag").read_bytes())
    assert main(["batch", str(FIXTURES / "ros1.bag"), str(twin), "-o", str(out)]) == 2
    assert "named ros1" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:  # a log taken for the address
        main(["batch", "-o", str(out), "--ray", str(FIXTURES / "ros1.bag")])
    assert exc.value.code == 2 and "put --ray after the logs" in capsys.readouterr().err
    with pytest.raises(OutputPathError):
        batch([FIXTURES / "ros1.bag"], tmp_path / "missing" / "out")
    with pytest.raises(ConfigError, match="no logs"):
        batch([], out)
    assert not out.exists()


def test_config_file_batch_table_then_flags(tmp_path: Path) -> None:
    from memlog.cli.app import build_parser
    from memlog.cli.commands import batch_config

    conf = tmp_path / "fleet.toml"
    conf.write_text("[batch]\nworkers = 3\nlogs_at_once = 2\nmax_retries = 1\n[map]\nstride = 4\n[score]\nmt = 0.6\n")
    args = build_parser().parse_args(["batch", "a.mcap", "-o", "out", "--config", str(conf), "--workers", "5",
                                      "--ray", "auto"])
    cfg = batch_config(args)
    assert (cfg.workers, cfg.logs_at_once, cfg.max_retries, cfg.ray, cfg.ray_address) == (5, 2, 1, True, "auto")
    assert cfg.map.stride == 4 and cfg.map.score.mt == 0.6 and cfg.window().stride == 4
    conf.write_text("[batch]\nworkers = 0\n")
    with pytest.raises(ConfigError, match=r"\[batch\].*workers"):
        batch_config(build_parser().parse_args(["batch", "a.mcap", "-o", "out", "--config", str(conf)]))
    conf.write_text("[batch]\nmap = {stride = 2}\n")
    with pytest.raises(ConfigError, match=r"\[map\] table"):
        batch_config(build_parser().parse_args(["batch", "a.mcap", "-o", "out", "--config", str(conf)]))


# -- local worker processes, resume ----------------------------------------------------------------
def test_local_workers_write_what_one_process_writes_and_resume(tmp_path: Path,
                                                                monkeypatch: pytest.MonkeyPatch) -> None:
    use_stand_in(monkeypatch)
    logs = [FIXTURES / "ros2_sqlite", FIXTURES / "ros2_mcap"]
    cfg = BatchConfig(workers=2, chunk_frames=1)
    want = {log.name: reference(log, tmp_path / "ref", cfg, stand_in=True) for log in logs
            if (tmp_path / "ref").mkdir(exist_ok=True) is None}
    out = tmp_path / "out"
    res = batch(logs, out, cfg)
    assert [r.status for r in res.logs] == ["ok", "ok"] and res.exit_code == 0
    assert res.executor["kind"] == "processes" and res.executor["workers"] == 2
    for r in res.logs:
        assert_same_outputs(r.outputs, want[Path(r.log).name])
    summary = json.loads((out / "batch.json").read_text())
    assert [(d["name"], d["status"], d["frames"], d["kept"]) for d in summary["logs"]] == \
        [(r.name, "ok", r.frames, r.kept) for r in res.logs]
    assert summary["logs"][0]["frames"] == 4 and summary["totals"]["frames"] == sum(r.frames for r in res.logs)

    again = batch(logs, out, cfg)  # everything up to date: nothing runs, no worker starts
    assert [r.status for r in again.logs] == ["skipped", "skipped"]
    assert again.executor.get("started") is False and again.exit_code == 0
    assert [(r.frames, r.kept) for r in again.logs] == [(r.frames, r.kept) for r in res.logs]

    leftover = out / ".ros2_mcap.map.mcap.x1y2z3.tmp"  # as a killed run leaves it
    leftover.write_bytes(b"half a map")
    parquet = Path(res.logs[1].outputs["descriptors"])
    st = parquet.stat()
    os.utime(parquet, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))  # an output changed since
    third = batch(logs, out, cfg)
    assert [r.status for r in third.logs] == ["skipped", "ok"]
    assert_same_outputs(third.logs[1].outputs, want["ros2_mcap"])
    assert not leftover.exists()

    other = BatchConfig(map=MapConfig(jpeg_quality=80), workers=1)  # other settings: not up to date
    assert [r.status for r in batch(logs[:1], out, other).logs] == ["ok"]
    faster = BatchConfig(map=MapConfig(jpeg_quality=80), workers=2)  # workers/threads change no output
    assert [r.status for r in batch(logs[:1], out, faster).logs] == ["skipped"]
    assert [r.status for r in batch(logs[:1], out, BatchConfig(map=MapConfig(jpeg_quality=80), resume=False,
                                                               workers=1)).logs] == ["ok"]


# -- the real models, every fixture format ----------------------------------------------------------
#: one fixture per log format and message encoding memlog reads: MCAP (ROS 2 CDR, ROS 1, ROS 2 IDL,
#: Foxglove JSON and protobuf), ROS 1 bag, ROS 2 bag (sqlite3 and MCAP storage). (encodings.mcap,
#: the raw image encodings in a ROS 2 MCAP, is left out: 19 topics, a format already here.)
FORMATS = ["demo.mcap", "ros1.mcap", "ros2idl.mcap", "foxglove_json.mcap", "foxglove_proto.mcap", "ros1.bag",
           "ros2_sqlite", "ros2_mcap"]


def test_every_format_with_the_real_models_gives_the_one_process_outputs(tmp_path: Path) -> None:
    """The real ResMem, detector and descriptor on two local worker processes (one frame per job):
    each format's outputs are those of ``score`` + ``map`` on this process, timing fields aside."""
    import json as _json
    from collections import Counter

    from memlog.io.open import open_log
    from memlog.models.cache import recorded_sha256
    from memlog.scoring.memorability import resmem_onnx_path
    from mcap.reader import make_reader

    import shutil

    logs = [FIXTURES / n for n in FORMATS if n != "ros1.mcap"]
    logs.append(tmp_path / "ros1_profile.mcap")  # its outputs would be named like ros1.bag's
    shutil.copyfile(FIXTURES / "ros1.mcap", logs[-1])
    cfg = BatchConfig(map=MapConfig(stride=2), workers=2, chunk_frames=1)
    (tmp_path / "ref").mkdir()
    want = {log.name: reference(log, tmp_path / "ref", cfg, stand_in=False) for log in logs}
    res = batch(logs, tmp_path / "out", cfg)
    assert [r.status for r in res.logs] == ["ok"] * len(logs) and res.exit_code == 0
    assert res.executor["kind"] == "processes" and res.executor["workers"] == 2
    real = recorded_sha256(resmem_onnx_path())
    assert real
    for log, r in zip(logs, res.logs):
        assert_same_outputs(r.outputs, want[log.name])
        with open_log(log) as reader:  # every 2nd frame of each camera topic
            per_topic = Counter(f.topic for f in reader.frames())
        assert r.frames == sum((n + 1) // 2 for n in per_topic.values()), log.name
        with open(r.outputs["scored"], "rb") as fh:
            run = {m.name: m.metadata for m in make_reader(fh).iter_metadata()}["memlog_run"]
        assert _json.loads(run["models"])["resmem"] == real, log.name  # the real ResMem, not the stand-in
        with open(r.outputs["map"], "rb") as fh:
            made = {m.name: m.metadata for m in make_reader(fh).iter_metadata()}["memlog_map"]
        assert _json.loads(made["resmem_crops_run"]) > 0, log.name  # ResMem really ran on each log

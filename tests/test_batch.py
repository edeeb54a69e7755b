"""``memlog batch`` without Ray: placement, manifests, usage errors before any work, local worker
processes giving the one-process outputs, and resume. (Ray itself: ``tests/test_batch_ray.py``.)

The resume test scores with the stand-in ResMem (``tests/stand_in.py``; the local worker processes,
spawned, are given it when they start); the last test runs the real models on a fixture log of
every format.
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
from memlog.steps.ray_pool import Node, NodePlacement, Placement, plan_placement
from tests.same_outputs import assert_same_outputs, reference
from tests.conftest import FIXTURES
from tests.stand_in import use_stand_in


# -- placement --------------------------------------------------------------------------------------
# one node: the rule of plan_placement's docstring (these cases were written for cluster totals; as
# one node's resources they give the same actors)
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
def test_placement_fits_the_node(cpus: int, gpus: int, kw: dict, want: Placement) -> None:
    got = plan_placement([Node(cpus, gpus, "n1")], **kw)
    assert got == Placement(want.actors, want.threads, want.gpus, (NodePlacement("n1", want.actors, want.gpus),))
    assert got.actors * got.threads <= cpus and got.actors * got.gpus <= gpus + 1e-9


@pytest.mark.parametrize("cpus,gpus,kw,flag", [
    (2, 0, {"workers": 3}, "--workers 3"),
    (2, 0, {"threads": 4}, "--threads 4"),
    (4, 0, {"device": "cuda"}, "--device cuda"),
    (8, 1, {"workers": 3, "actors_per_gpu": 2}, "--workers 3"),
])
def test_placement_that_cannot_fit_names_the_flag(cpus: int, gpus: int, kw: dict, flag: str) -> None:
    with pytest.raises(ConfigError, match=flag):
        plan_placement([Node(cpus, gpus)], **kw)


HEAD, GPU = Node(4, 0, "head"), Node(2, 1, "gpu")  # a CPU-only head node and one small GPU node


@pytest.mark.parametrize("nodes,kw,want", [
    # CPU actors on the head, GPU actors sharing the GPU node's GPU by its own CPUs (totals, 6 CPUs and
    # 1 GPU, planned 6 actors each wanting 1/6 GPU: 4 of them fit no node)
    ([HEAD, GPU], {}, [("head", 4, 0.0), ("gpu", 2, 0.5)]),
    # 4 CPUs per actor: the GPU node has 2, so only the head holds one (totals planned 1 actor of
    # 4 CPUs + 1 GPU: no node has both)
    ([HEAD, GPU], {"threads": 4}, [("head", 1, 0.0)]),
    ([HEAD, GPU], {"device": "cuda"}, [("gpu", 2, 0.5)]),  # the models on a GPU: the head holds none
    ([HEAD, GPU], {"device": "cpu"}, [("head", 4, 0.0), ("gpu", 2, 0.0)]),
    ([HEAD, GPU], {"workers": 3}, [("head", 1, 0.0), ("gpu", 2, 0.5)]),  # the GPU node's actors first
    ([HEAD, GPU], {"workers": 2}, [("gpu", 2, 0.5)]),
    ([HEAD, GPU], {"actors_per_gpu": 1}, [("head", 4, 0.0), ("gpu", 1, 1.0)]),
    # two CPU nodes: each holds what its own CPUs hold (totals, 6 CPUs, planned 2 actors of 3 CPUs)
    ([Node(4, 0, "a"), Node(2, 0, "b")], {}, [("a", 4, 0.0), ("b", 2, 0.0)]),
    ([Node(4, 0, "a"), Node(2, 0, "b")], {"threads": 3}, [("a", 1, 0.0)]),
    ([Node(4, 0, "a"), Node(4, 0, "b")], {"workers": 3}, [("a", 2, 0.0), ("b", 1, 0.0)]),  # spread in turn
    # a node too small for an actor holds none; the others do
    ([Node(1, 0, "small"), Node(4, 0, "big")], {"threads": 2}, [("big", 2, 0.0)]),
    ([Node(0, 0, "driver"), HEAD], {}, [("head", 4, 0.0)]),  # a head with num-cpus 0
    # two GPU nodes of other shapes: each shares its own GPUs by its own CPUs per GPU
    ([Node(64, 8, "h100"), Node(8, 4, "t4")], {}, [("h100", 64, 0.125), ("t4", 8, 0.5)]),
])
def test_placement_is_planned_per_node(nodes: list[Node], kw: dict, want: list[tuple[str, int, float]]) -> None:
    got = plan_placement(nodes, **kw)
    assert [(p.node, p.actors, p.gpus) for p in got.nodes] == want
    assert got.actors == sum(a for _, a, _ in want) and got.gpus == max(g for _, _, g in want)
    by_id = {n.id: n for n in nodes}
    for p in got.nodes:  # every actor's CPUs and GPU share fit the node it is planned on
        node = by_id[p.node]
        assert p.actors * got.threads <= node.cpus and p.actors * p.gpus <= node.gpus + 1e-9


@pytest.mark.parametrize("nodes,kw,match", [
    ([Node(1, 0), Node(1, 0)], {"threads": 2}, r"--threads 2: an actor needs 2 CPU\(s\) on one node; the largest "
                                                r"node of the Ray cluster has 1"),  # totals: 2 CPUs, 1 actor
    ([HEAD, GPU], {"device": "cuda", "threads": 4}, r"--threads 4: .*the largest GPU node .* has 2"),
    ([Node(4, 0), Node(8, 0)], {"device": "cuda"}, "--device cuda: the Ray cluster has no GPU"),
    ([HEAD, GPU], {"workers": 7}, r"--workers 7: .*at most 6 actor"),
    ([Node(0, 0)], {}, "--threads 1"),  # no CPU anywhere
    ([], {}, "no alive node"),
])
def test_placement_no_node_holds_says_what_is_missing(nodes: list[Node], kw: dict, match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        plan_placement(nodes, **kw)


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


def test_resume_refuses_outputs_of_another_memlog_version_or_other_models(tmp_path: Path,
                                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    """An upgrade of memlog or a rebuilt model (another sha256) makes every output stale."""
    import memlog.steps.batch as batch_mod

    use_stand_in(monkeypatch)
    logs = [FIXTURES / "ros2_mcap"]
    out = tmp_path / "out"
    cfg = BatchConfig(workers=1)
    assert [r.status for r in batch(logs, out, cfg).logs] == ["ok"]
    assert [r.status for r in batch(logs, out, cfg).logs] == ["skipped"]
    real = batch_mod.model_versions
    monkeypatch.setattr(batch_mod, "model_versions",
                        lambda names: {**real(names), "resmem": "0" * 64})  # the model was rebuilt
    assert [r.status for r in batch(logs, out, cfg).logs] == ["ok"]
    assert [r.status for r in batch(logs, out, cfg).logs] == ["skipped"]
    monkeypatch.setattr(batch_mod, "__version__", "99.0.0")  # memlog was upgraded
    assert [r.status for r in batch(logs, out, cfg).logs] == ["ok"]


def test_resume_skips_a_map_without_descriptors(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    use_stand_in(monkeypatch)
    logs = [FIXTURES / "ros2_mcap"]
    out = tmp_path / "out"
    cfg = BatchConfig(map=MapConfig(descriptor=None), workers=1)
    first = batch(logs, out, cfg)
    assert [r.status for r in first.logs] == ["ok"] and "descriptors" not in first.logs[0].outputs
    assert not (out / "ros2_mcap.map.parquet").exists()
    assert [r.status for r in batch(logs, out, cfg).logs] == ["skipped"]


def test_batch_says_when_a_map_is_smaller_than_asked(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """As ``memlog map`` does (``tests/test_drive_selection.py``): frame 1 of the log stands still
    for two frames, so 6 of the 8 segments ``keep_fraction=1`` asks for hold a frame; the log's
    line and ``batch.json`` say so, and say nothing when every segment holds one."""
    from memlog.selection.config import SelectionConfig
    from tests.conftest import repeating_log

    use_stand_in(monkeypatch)
    log = tmp_path / "stop.mcap"
    repeating_log(log)
    for fraction, out in ((1.0, tmp_path / "all"), (0.25, tmp_path / "quarter")):
        cfg = BatchConfig(map=MapConfig(select=SelectionConfig(keep_fraction=fraction), descriptor=None), workers=1)
        r = batch([log], out, cfg).logs[0]
        assert r.status == "ok"
        summary = json.loads((out / "batch.json").read_text())["logs"][0]["notes"]
        if fraction == 1.0:
            assert r.notes == summary == ["/camera/image/compressed: fewer frames than --keep-fraction asks: 6 of "
                                          "the 8 segments hold a frame (2 frame(s) stood still, and a stop is one "
                                          "place)"] and r.kept is not None and r.kept <= 6
        else:
            assert r.notes == summary == [] and r.kept is not None and 1 <= r.kept <= 2


def _killer(*args: object) -> object:
    """A scoring job whose worker process dies (out of memory, say) the first time a job ends:
    exactly one worker wins the marker's unlink, so no other job sees the marker vanish under it.
    (It runs on a spawned worker, whose ``score_chunk`` is memlog's: the test's patch is the driver's.)"""
    from memlog.steps.score import score_chunk
    from tests.worker_kill import die_once

    return die_once(os.environ["MEMLOG_TEST_MARKER"], score_chunk, *args)


def test_a_broken_pool_is_replaced_for_the_logs_after_it(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """With several logs at once, a worker killed while one log runs fails that log (and the
    logs sharing the pool at that moment); every log started later runs on a new pool."""
    import memlog.steps.score as score_mod

    use_stand_in(monkeypatch)
    marker = tmp_path / "kill-once"
    marker.write_text("")
    monkeypatch.setenv("MEMLOG_TEST_MARKER", str(marker))
    monkeypatch.setattr(score_mod, "score_chunk", _killer)  # the driver hands its workers _killer
    logs = []
    for k in range(4):
        logs.append(tmp_path / f"log{k}.mcap")
        logs[-1].write_bytes((FIXTURES / "ros1.mcap").read_bytes())
    res = batch(logs, tmp_path / "out", BatchConfig(workers=2, logs_at_once=2, chunk_frames=1))
    status = [r.status for r in res.logs]
    assert not marker.exists() and "failed" in status
    assert status[-1] == "ok" and status.count("ok") >= 2, status  # the logs after the break ran
    assert sum(r.worker_failures for r in res.logs) >= 1


def test_no_log_starts_on_a_pool_that_already_lost_a_worker() -> None:
    """The pool can break while another log runs, before that log sees it (the CI run of stop 28:
    a log failing on its own left the broken pool to the next log): the next log gets a new pool."""
    from concurrent.futures.process import BrokenProcessPool

    from memlog.steps.batch import _Executors
    from tests.test_workers import _finish_late
    from tests.worker_kill import die_now

    executors = _Executors(BatchConfig(workers=2))
    try:
        first = executors.get()
        with pytest.raises(BrokenProcessPool):
            list(first.map_ordered(die_now, [(1,)]))
        second = executors.get()  # nobody called broken(): the pool says so itself
        assert second is not first
        assert [i for i, _ in second.map_ordered(_finish_late, [(0, 0.0), (1, 0.0)])] == [0, 1]
        assert executors.get() is second  # a working pool is kept
    finally:
        executors.close()


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
    # score_kept: the map step's ResMem also runs on the workers (by default one candidate per segment needs none)
    # (every 4th frame: each format keeps at least one frame per topic, and exact ResMem, 5 s a frame, runs on fewer)
    cfg = BatchConfig(map=MapConfig(stride=4, score_kept=True), workers=2, chunk_frames=1)
    (tmp_path / "ref").mkdir()
    want = {log.name: reference(log, tmp_path / "ref", cfg, stand_in=False) for log in logs}
    res = batch(logs, tmp_path / "out", cfg)
    assert [r.status for r in res.logs] == ["ok"] * len(logs) and res.exit_code == 0
    assert res.executor["kind"] == "processes" and res.executor["workers"] == 2
    real = recorded_sha256(resmem_onnx_path())
    assert real
    for log, r in zip(logs, res.logs):
        assert_same_outputs(r.outputs, want[log.name])
        with open_log(log) as reader:  # every 4th frame of each camera topic
            per_topic = Counter(f.topic for f in reader.frames())
        assert r.frames == sum((n + 3) // 4 for n in per_topic.values()), log.name
        with open(r.outputs["scored"], "rb") as fh:
            run = {m.name: m.metadata for m in make_reader(fh).iter_metadata()}["memlog_run"]
        assert _json.loads(run["models"])["resmem"] == real, log.name  # the real ResMem, not the stand-in
        with open(r.outputs["map"], "rb") as fh:
            made = {m.name: m.metadata for m in make_reader(fh).iter_metadata()}["memlog_map"]
        assert _json.loads(made["resmem_crops_run"]) > 0, log.name  # ResMem really ran on each log

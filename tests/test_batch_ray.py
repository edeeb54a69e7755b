"""``memlog batch --ray`` on a local Ray instance with 2 CPUs, started once for this module.

* three fixture logs of different formats (ROS 2 MCAP bag, ROS 1 bag, ROS 2 sqlite bag) give the
  outputs of local one-process ``score`` + ``make_map`` runs, timing fields aside, two logs at a time
  sharing the actors (``--logs-at-once 2``); a rerun skips them;
* the actors are planned from the Ray instance's nodes (``ray.nodes()``: one node, 2 CPUs) and
  pinned to it (a cluster of several nodes: ``tests/test_ray_nodes.py``);
* a worker process killed once mid-task (from the test side: ``tests/worker_kill.py``) costs a
  retry, not the run, and changes no output;
* a manifest with a truncated log, a file that is no log and a missing path: the good log's
  outputs as before, the damaged one finished and reported, exit 1 at the end;
* the shared EuRoC logs (four formats) and a Nordland drive: the local outputs;
* the real ResMem through Ray (one log, every 2nd frame): the same outputs as on one process.

Every test but the last scores with the stand-in ResMem (``tests/stand_in.py``), switched on in
the Ray workers by a file (their setup hook looks for it), so the tests stay affordable on 2 cores.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import pytest
import ray  # in the test extra: the Ray tests always run (no skip)

from memlog.cli.app import main
from memlog.steps.batch import BatchConfig, batch
from memlog.steps.map import MapConfig
from memlog.steps.ray_pool import Node, cluster_nodes
from tests.same_outputs import assert_same_outputs, reference
from tests.conftest import FIXTURES, ROOT, shared
from tests.stand_in import SWITCH_ENV
from tests.worker_kill import kill_one_worker


LOGS = [FIXTURES / "ros2_mcap", FIXTURES / "ros1.bag", FIXTURES / "ros2_sqlite"]
CFG = BatchConfig(ray=True, workers=2, chunk_frames=1)  # one frame per job: every log spreads over both actors


@pytest.fixture(scope="module")
def ray_dir(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """A local Ray instance (2 CPUs) whose workers know the stand-in switch and import this checkout."""
    d = tmp_path_factory.mktemp("ray")
    ray.init(num_cpus=2, include_dashboard=False, logging_level=logging.WARNING,
             runtime_env={"env_vars": {SWITCH_ENV: str(d / "stand-in.on"),
                                       "PYTHONPATH": str(ROOT)},  # this checkout's memlog and tests/
                          "worker_process_setup_hook": "tests.stand_in.install"})
    try:
        yield d
    finally:
        ray.shutdown()


@pytest.fixture()
def stand_in(ray_dir: Path) -> Iterator[None]:
    switch = ray_dir / "stand-in.on"
    switch.touch()
    try:
        yield
    finally:
        switch.unlink()


@pytest.fixture(scope="module")
def want(tmp_path_factory: pytest.TempPathFactory) -> dict[str, dict[str, Path]]:
    """The local one-process outputs of the three logs (stand-in ResMem)."""
    from tests.stand_in import use_stand_in

    d = tmp_path_factory.mktemp("reference")
    with pytest.MonkeyPatch.context() as mp:
        use_stand_in(mp)
        return {log.name: reference(log, d, CFG, stand_in=True) for log in LOGS}


def test_three_formats_on_ray_give_the_local_outputs_and_resume(
        tmp_path: Path, stand_in: None, want: dict[str, dict[str, Path]]) -> None:
    """Two logs at a time share the actors (``--logs-at-once 2``): each log's outputs are its own
    one-process ones, reported in the order given whatever order they ended; a rerun skips them."""
    res = batch(LOGS, tmp_path, replace(CFG, logs_at_once=2))
    assert [r.status for r in res.logs] == ["ok", "ok", "ok"] and res.exit_code == 0
    assert [Path(r.log).name for r in res.logs] == [log.name for log in LOGS]
    assert res.executor["kind"] == "ray" and res.executor["actors"] == 2 and res.executor["threads"] == 1
    assert res.executor["devices"] == ["cpu"]
    node = ray.get_runtime_context().get_node_id()  # the plan is the nodes Ray reports, per node
    assert cluster_nodes() == [Node(2.0, 0.0, node)]
    assert res.executor["nodes"] == [{"node": node, "actors": 2, "gpus": 0.0}]
    assert (res.executor["cluster_cpus"], res.executor["cluster_gpus"]) == (2.0, 0.0)
    for r in res.logs:
        assert_same_outputs(r.outputs, want[Path(r.log).name])
        assert r.worker_failures == 0
    assert [r.frames for r in res.logs] == [4, 8, 4]
    again = batch(LOGS, tmp_path, CFG)
    assert [r.status for r in again.logs] == ["skipped"] * 3 and again.executor.get("started") is False


@pytest.mark.shared
def test_shared_logs_on_ray_give_the_local_outputs(tmp_path: Path, stand_in: None,
                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    """The shared EuRoC logs (four formats, every 16th frame) and a Nordland drive (every 100th)."""
    from tests.stand_in import use_stand_in

    logs = [shared(n) for n in ("euroc_micro_ros2.mcap", "euroc_micro_ros1.bag", "euroc_micro_ros2_db3",
                                "euroc_micro_foxglove.mcap")]
    cfg = BatchConfig(map=MapConfig(stride=16), ray=True, workers=2)
    res = batch(logs, tmp_path / "out", cfg)
    assert [r.status for r in res.logs] == ["ok"] * 4
    assert [r.frames for r in res.logs] == [12, 6, 6, 6]  # 95 frames per topic; the ROS 2 MCAP has two
    use_stand_in(monkeypatch)
    (tmp_path / "ref").mkdir()
    for log, r in zip(logs, res.logs):
        assert_same_outputs(r.outputs, reference(log, tmp_path / "ref", cfg, stand_in=True))
    nordland = shared("nordland_dev_summer.mcap")
    cfg = BatchConfig(map=MapConfig(stride=100), ray=True, workers=2, chunk_frames=2)
    r = batch([nordland], tmp_path / "out", cfg).logs[0]
    assert r.status == "ok" and r.frames == 8
    assert_same_outputs(r.outputs, reference(nordland, tmp_path / "ref", cfg, stand_in=True))


def test_a_worker_killed_mid_task_is_retried(tmp_path: Path, stand_in: None, ray_dir: Path,
                                             want: dict[str, dict[str, Path]],
                                             monkeypatch: pytest.MonkeyPatch) -> None:
    armed = ray_dir / "kill.armed"
    armed.touch()  # the first worker to finish a job removes it and dies before returning the result
    kill_one_worker(monkeypatch, armed)
    res = batch([FIXTURES / "ros1.bag"], tmp_path, CFG)
    assert not armed.exists()  # a worker did die
    r = res.logs[0]
    assert r.status == "ok" and r.worker_failures == 1
    assert_same_outputs(r.outputs, want["ros1.bag"])
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(  # no partial or duplicate outputs
        ["batch.json", "ros1.scored.mcap", "ros1.map.mcap", "ros1.map.parquet"])


def test_damaged_logs_in_the_manifest_do_not_stop_the_others(
        tmp_path: Path, stand_in: None, want: dict[str, dict[str, Path]],
        capsys: pytest.CaptureFixture[str]) -> None:
    logs = tmp_path / "logs"
    logs.mkdir()
    data = (FIXTURES / "ros1.bag").read_bytes()
    (logs / "cut.bag").write_bytes(data[: len(data) * 2 // 3])  # truncated: read up to the damage
    (logs / "junk.mcap").write_bytes(b"no log here\n" * 50)  # cannot be read at all
    manifest = logs / "fleet.txt"
    manifest.write_text(f"junk.mcap\ncut.bag\nmissing.bag\n{FIXTURES / 'ros2_sqlite'}\n")  # relative and absolute
    out = tmp_path / "out"
    code = main(["batch", "--manifest", str(manifest), "-o", str(out), "--ray", "--workers", "2"])
    cap = capsys.readouterr()
    assert code == 1  # a log failed (after the others ran)
    summary = json.loads((out / "batch.json").read_text())
    status = {d["name"]: d["status"] for d in summary["logs"]}
    assert status == {"junk": "failed", "cut": "damaged", "missing": "failed", "ros2_sqlite": "ok"}
    assert summary["exit_code"] == 1
    cut = next(d for d in summary["logs"] if d["name"] == "cut")
    assert any("truncated" in x for x in cut["damage"]) and 0 < cut["frames"] < 8
    assert "finished with damaged input" in cap.err and "not a log memlog can read" in cap.out
    assert sorted(p.name for p in out.iterdir()) == sorted(
        ["batch.json"] + [f"{n}{s}" for n in ("cut", "ros2_sqlite") for s in (".scored.mcap", ".map.mcap",
                                                                              ".map.parquet")])
    good = next(d for d in summary["logs"] if d["name"] == "ros2_sqlite")
    assert_same_outputs(good["outputs"], want["ros2_sqlite"])


def _cap_and_say(text: str) -> int:
    """A job: says ``text`` on the ``memlog`` logger, returns the pixel cap in force on its worker."""
    from memlog.io.image import max_pixels
    from memlog.progress import warning

    warning(text)
    return max_pixels()


def test_the_drivers_settings_reach_the_actors_and_their_records_come_back(
        ray_dir: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture) -> None:
    """An actor is started by Ray, not by this process: the pixel cap (--max-pixels) set here after
    Ray started is given to it, and what its jobs log is handled by this process's loggers."""
    from memlog.io.image import max_pixels, set_max_pixels
    from memlog.steps.ray_pool import Placement, RayActors

    from memlog.runtime import current, use

    caplog.set_level(logging.INFO, logger="memlog")
    with use(current()):  # the runtime context in force now is put back after the test
        set_max_pixels(54321)
        ex = RayActors(Placement(1, 1, 0.0))
        try:
            assert list(ex.map_ordered(_cap_and_say, [("said on a Ray worker",)])) == [54321]
        finally:
            ex.close()
    assert max_pixels() != 54321
    assert [r.getMessage() for r in caplog.records if r.name == "memlog"] == ["said on a Ray worker"]


def test_real_resmem_on_ray_gives_the_one_process_outputs(tmp_path: Path, ray_dir: Path) -> None:
    assert not (ray_dir / "stand-in.on").exists()
    cfg = BatchConfig(map=MapConfig(stride=2), ray=True, workers=2, chunk_frames=1)
    log = FIXTURES / "ros2_sqlite"
    (tmp_path / "ref").mkdir()
    ref = reference(log, tmp_path / "ref", cfg, stand_in=False)
    res = batch([log], tmp_path / "out", cfg)
    r = res.logs[0]
    assert r.status == "ok" and r.frames == 2
    assert_same_outputs(r.outputs, ref)
    meta = json.loads(json.dumps(r.to_dict()))
    assert meta["identity"]["path"] == str(log.resolve())

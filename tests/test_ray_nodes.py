"""Ray actors planned per node, on a Ray cluster of two nodes started on this machine
(``ray.cluster_utils.Cluster``): a CPU-only head node with 1 CPU and a node with 1 CPU and one
(logical) GPU. Planned from the cluster's totals (2 CPUs, 1 GPU), two actors of 1 CPU + 0.5 GPU
were asked for; the head has no GPU, so the second never started and Ray waited for resources
that would never appear. Planned per node (``ray.nodes()``), each node holds one actor (the GPU
node's actor holds its GPU), each actor starts on its node and ``memlog batch`` runs.

The actors score with the stand-in ResMem (``tests/stand_in.py``), switched on for the whole module.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from pathlib import Path

import pytest
import ray  # in the test extra: the Ray tests always run (no skip)
from ray.cluster_utils import Cluster

from memlog.steps.batch import BatchConfig, batch
from memlog.steps.ray_pool import Node, RayActors, cluster_nodes, plan_placement
from tests.conftest import FIXTURES, ROOT
from tests.same_outputs import assert_same_outputs, reference
from tests.stand_in import SWITCH_ENV


@pytest.fixture(scope="module")
def nodes(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, str]]:
    """The Ray node ids of the head (1 CPU) and of the GPU node (1 CPU, 1 GPU), this process connected."""
    d = tmp_path_factory.mktemp("ray-nodes")
    (d / "stand-in.on").touch()
    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 1, "include_dashboard": False})
    try:
        gpu = cluster.add_node(num_cpus=1, num_gpus=1)
        cluster.wait_for_nodes()
        ray.init(address=cluster.address, logging_level=logging.WARNING,
                 runtime_env={"env_vars": {SWITCH_ENV: str(d / "stand-in.on"),
                                           "PYTHONPATH": str(ROOT)},  # this checkout's memlog and tests/
                              "worker_process_setup_hook": "tests.stand_in.install"})
        try:
            yield cluster.head_node.node_id, gpu.node_id
        finally:
            ray.shutdown()
    finally:
        cluster.shutdown()


def test_a_cpu_head_and_a_small_gpu_node_each_hold_their_actor(nodes: tuple[str, str], tmp_path: Path,
                                                                monkeypatch: pytest.MonkeyPatch) -> None:
    head, gpu = nodes
    assert sorted(cluster_nodes()) == sorted([Node(1.0, 0.0, head), Node(1.0, 1.0, gpu)])
    placement = plan_placement(cluster_nodes())
    assert sorted((p.node, p.actors, p.gpus) for p in placement.nodes) == sorted([(head, 1, 0.0), (gpu, 1, 1.0)])
    ex = RayActors(placement, start_timeout_s=120)  # totals planned actors that never started (600 s)
    try:
        assert [i["node"] for i in ex.info] == [p.node for p in placement.nodes for _ in range(p.actors)]
        assert {i["node"]: i["gpus"] for i in ex.info}[gpu] == "0"  # the GPU node's actor holds its GPU
    finally:
        ex.close()

    from tests.stand_in import use_stand_in

    log = FIXTURES / "ros1.bag"
    cfg = BatchConfig(ray=True, chunk_frames=1)
    res = batch([log], tmp_path / "out", cfg)
    assert [r.status for r in res.logs] == ["ok"]
    assert (res.executor["cluster_cpus"], res.executor["cluster_gpus"], res.executor["actors"]) == (2.0, 1.0, 2)
    assert sorted((p["node"], p["actors"], p["gpus"]) for p in res.executor["nodes"]) == \
        sorted([(head, 1, 0.0), (gpu, 1, 1.0)])
    use_stand_in(monkeypatch)
    (tmp_path / "ref").mkdir()
    assert_same_outputs(res.logs[0].outputs, reference(log, tmp_path / "ref", cfg, stand_in=True))

"""Scale-out on Ray: a local two-node cluster (``ray.cluster_utils.Cluster``, one CPU per node, no dashboard) runs a
small datagen (through the CLI, connecting with ``RAY_ADDRESS`` as on a real cluster) and a small trials campaign
with ``--workers ray``; both give the process pool's bytes. The driver alone writes: tasks return their results."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from helpers import run_cli
from test_datagen import file_hashes
from test_workers import TINY_TOML

from posegrasp.datagen.config import load_datagen_config
from posegrasp.datagen.generate import SceneJob, generate_dataset
from posegrasp.grasping.config import TrialConfig
from posegrasp.grasping.runfolder import EPISODES
from posegrasp.grasping.trials import Display, run_trials

pytestmark = pytest.mark.slow  # a local Ray cluster

ray = pytest.importorskip("ray", reason="Ray is the optional 'ray' extra; `make test` installs it")


@pytest.fixture(scope="module")
def cluster():
    from ray.cluster_utils import Cluster

    store = 100 * 1024 * 1024
    c = Cluster(initialize_head=True, head_node_args={"num_cpus": 1, "include_dashboard": False,
                                                       "object_store_memory": store})
    c.add_node(num_cpus=1, object_store_memory=store)
    c.wait_for_nodes()
    ray.init(address=c.address, log_to_driver=False)
    assert sum(n["Alive"] for n in ray.nodes()) == 2
    yield c
    ray.shutdown()
    c.shutdown()


def test_datagen_on_ray_gives_the_pools_bytes(cluster, tmp_path):
    cfg_file = tmp_path / "tiny.toml"
    cfg_file.write_text(TINY_TOML)
    assert "root" not in SceneJob.__dataclass_fields__  # a task gets no path: it never writes into --out
    out = tmp_path / "ray"
    r = run_cli("datagen", "--out", str(out), "--scenes", "3", "--views", "2", "--seed", "7", "--workers", "ray",
                "--config", str(cfg_file), "--no-progress", env={**os.environ, "RAY_ADDRESS": cluster.address})
    assert r.returncode == 0, r.stderr
    pool = tmp_path / "pool"
    generate_dataset(pool, 3, 2, 7, load_datagen_config(cfg_file), workers=2)
    assert file_hashes(out) == file_hashes(pool)


def test_trials_on_ray_give_the_pools_records(cluster, tmp_path: Path):
    on_ray = run_trials(tmp_path / "ray", 2, seed=2, perception="oracle", workers="ray", cfg=TrialConfig(),
                        display=Display(progress=False))
    run_trials(tmp_path / "pool", 2, seed=2, perception="oracle", workers=2, cfg=TrialConfig(),
               display=Display(progress=False))
    assert on_ray["workers"] == "ray"
    assert (tmp_path / "ray" / EPISODES).read_bytes() == (tmp_path / "pool" / EPISODES).read_bytes()

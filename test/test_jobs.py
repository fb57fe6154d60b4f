"""Route sets, timing examples and route evaluations as independent jobs: the same files from
one process, from local processes and from a Ray cluster (a local Ray instance, started here)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from deepsync.bag import read_envelope
from deepsync.cli import main
from deepsync.eval.route_set import REPORT, evaluate_route_set, report_dir
from deepsync.jobs import JobRunner, check_ray_address
from deepsync.recording import record_route_set, route_set_bag
from deepsync.training.dataset import DatasetConfig, generate, load_split

REPO = Path(__file__).resolve().parents[1]
CAMPUS = REPO / "config" / "scenarios" / "campus.yaml"
WALK = REPO / "config" / "scenarios" / "campus_route.yaml"
TOWERS = REPO / "config" / "towers" / "campus.yaml"
TINY = DatasetConfig(examples_per_shard=3, max_frames=2, max_coarse_error=2, window_margin=3)


@pytest.fixture(scope="module")
def ray_cluster():
    """A Ray instance on this machine for the module's tests, as a user's cluster would be."""
    ray = pytest.importorskip("ray", reason="ray is not installed (the optional extra deepsync[ray])")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, configure_logging=False)
    yield "auto"  # jobs join the running instance, as they would join a cluster
    ray.shutdown()


def envelope_bytes(bag: Path) -> bytes:
    return b"".join(chunk.samples.tobytes() for chunk in read_envelope(bag))


def test_a_route_set_is_the_same_from_one_process_and_from_a_pool(tmp_path):
    scenarios, seeds = [CAMPUS, WALK], [3, 4]
    alone = list(record_route_set(scenarios, seeds, 0.03, tmp_path / "alone", JobRunner(1)))
    pooled = list(record_route_set(scenarios, seeds, 0.03, tmp_path / "pool", JobRunner(2)))
    assert len(alone) == len(pooled) == 4
    for scenario in scenarios:
        for seed in seeds:
            a, b = route_set_bag(tmp_path / "alone", scenario, seed), route_set_bag(tmp_path / "pool", scenario, seed)
            assert envelope_bytes(a) == envelope_bytes(b)
    assert envelope_bytes(route_set_bag(tmp_path / "alone", CAMPUS, 3)) != envelope_bytes(
        route_set_bag(tmp_path / "alone", CAMPUS, 4))  # the seed is the recording's
    # a rerun keeps what is there and makes nothing
    assert list(record_route_set(scenarios, seeds, 0.03, tmp_path / "alone", JobRunner(2))) == []


def test_a_route_set_on_ray_is_the_one_made_locally(tmp_path, ray_cluster, capsys):
    args = ["simulate-set", "--scenario", str(CAMPUS), "--seeds", "5-6", "--seconds", "0.03"]
    assert main([*args, "--out", str(tmp_path / "ray"), "--ray", ray_cluster]) == 0
    assert "Ray cluster auto" in capsys.readouterr().out
    assert main([*args, "--out", str(tmp_path / "local"), "--workers", "1"]) == 0
    for seed in (5, 6):
        ray_bag, local_bag = route_set_bag(tmp_path / "ray", CAMPUS, seed), route_set_bag(tmp_path / "local", CAMPUS, seed)
        assert envelope_bytes(ray_bag) == envelope_bytes(local_bag)


def test_timing_examples_on_ray_are_the_ones_made_locally(tmp_path, ray_cluster):
    shards = {"train": 2, "val": 1}
    assert generate(tmp_path / "local", shards, TINY, workers=1) == 9
    assert generate(tmp_path / "ray", shards, TINY, ray=ray_cluster) == 9
    for split in shards:
        local, remote = load_split(tmp_path / "local", split), load_split(tmp_path / "ray", split)
        assert local.keys() == remote.keys()
        for key in local:
            np.testing.assert_array_equal(local[key], remote[key])
    assert not list((tmp_path / "ray").rglob("*.tmp"))  # shards are renamed into place whole


def test_route_reports_on_ray_are_the_ones_made_locally(tmp_path, ray_cluster):
    bags = [str(b.out) for b in record_route_set([WALK], [1, 2], 2.0, tmp_path / "bags", JobRunner(1))]
    local = dict(evaluate_route_set(bags, TOWERS, tmp_path / "local", JobRunner(1)))
    remote = dict(evaluate_route_set(bags, TOWERS, tmp_path / "ray", JobRunner(ray=ray_cluster)))
    assert local.keys() == remote.keys() == set(bags)
    for bag in bags:
        assert (json.loads((report_dir(tmp_path / "local", bag) / REPORT).read_text())
                == json.loads((report_dir(tmp_path / "ray", bag) / REPORT).read_text()))
    assert dict(evaluate_route_set(bags, TOWERS, tmp_path / "ray", JobRunner(ray=ray_cluster))) == {}  # all there
    assert not [p for p in (tmp_path / "ray").iterdir() if p.name.startswith(".")]  # no partial report left


def test_each_bag_of_a_route_set_draws_its_own_aiding(tmp_path):
    """One plan for a set is not one set of draws: with a seed shared by every bag, each route's
    GNSS fixes (and odometry, and start offset) erred alike, and the set measured one draw."""
    import shutil

    from deepsync.eval.aiding import AidingPlan

    recorded = next(iter(record_route_set([WALK], [1], 1.0, tmp_path / "bags", JobRunner(1)))).out
    bags = [shutil.copytree(recorded, tmp_path / name) for name in ("walk_a", "walk_b")]
    plan = AidingPlan(0.0, 5.0)  # one fix, at the start

    def start_fixes(out: Path) -> list[list[float]]:
        assert len(dict(evaluate_route_set(bags, TOWERS, out, JobRunner(1), aiding=plan))) == 2
        return [json.loads((report_dir(out, bag) / REPORT).read_text())["anchors"][0]["enu"] for bag in bags]

    first = start_fixes(tmp_path / "one")
    assert first[0] != first[1]  # the same truth, two bags: two draws
    assert start_fixes(tmp_path / "two") == first  # and the same draws for the same bags


def test_a_ray_address_that_is_none_is_refused_in_one_line(capsys):
    with pytest.raises(ValueError, match="auto"):
        check_ray_address("cluster")
    assert main(["simulate-set", "--scenario", str(CAMPUS), "--seeds", "1", "--seconds", "0.02",
                 "--out", "/nonexistent/never", "--ray", "cluster"]) == 2
    assert "--ray 'cluster'" in capsys.readouterr().err

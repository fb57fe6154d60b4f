"""The core package installed without its checkout (``pip install src/deepsync``): what it ships
is found through ``importlib.resources``, and what it does not ship (the demo's 15 MB bag) is
an error that says where it looked and how to get one."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

from deepsync.eval import demo

REPO = Path(__file__).resolve().parents[1]
INSTALLED_CHECK = """
import sys
from pathlib import Path
import deepsync
from deepsync.bag import find_msg_dir
from deepsync.eval import demo
from deepsync.timing.network import DEFAULT_CHECKPOINT
from deepsync.towers import load_tower_database
site = Path(sys.argv[1]).resolve()
assert Path(deepsync.__file__).resolve().is_relative_to(site), deepsync.__file__
assert demo._checkout() is None
with demo.packaged(demo.TOWERS) as towers:
    assert towers.resolve().is_relative_to(site) and load_tower_database(towers).pcis
with demo.packaged(demo.SCENARIO) as scenario:
    assert scenario.resolve().is_relative_to(site) and scenario.read_text().startswith("#")
assert find_msg_dir().resolve().is_relative_to(site), find_msg_dir()
assert DEFAULT_CHECKPOINT.is_file()
"""


@pytest.fixture(scope="module")
def installed(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The core package as a wheel makes it (its package data only), unpacked outside the
    checkout: what ``pip install src/deepsync`` puts into site-packages."""
    scratch = tmp_path_factory.mktemp("installed")
    source = scratch / "source"  # built from a copy: the checkout gets no build/ or egg-info
    shutil.copytree(REPO / "src" / "deepsync", source, symlinks=False,
                    ignore=shutil.ignore_patterns("__pycache__", "build", "*.egg-info"))
    built = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "--no-index",
                            "-q", "-w", str(scratch / "wheel"), str(source)], capture_output=True, text=True,
                           timeout=300, check=False)
    if built.returncode != 0:
        pytest.skip(f"pip cannot build the core's wheel here (setuptools >= 70.1 or wheel needed): "
                    f"{built.stderr.strip()[-300:]}")
    site = scratch / "site"
    (wheel,) = (scratch / "wheel").glob("deepsync-*.whl")
    with zipfile.ZipFile(wheel) as archive:
        archive.extractall(site)
    return site


def _run(site: Path, cwd: Path, *args: str) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "DEEPSYNC_MSGS_DIR", "AMENT_PREFIX_PATH")}
    env["PYTHONPATH"] = str(site)
    return subprocess.run([sys.executable, *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=300,
                          check=False)


def test_installed_package_finds_what_it_ships(installed: Path, tmp_path: Path) -> None:
    done = _run(installed, tmp_path, "-c", INSTALLED_CHECK, str(installed))
    assert done.returncode == 0, done.stderr


def test_installed_demo_without_the_bag_says_where_it_looked_and_how_to_get_one(installed: Path,
                                                                               tmp_path: Path) -> None:
    done = _run(installed, tmp_path, "-m", "deepsync.cli", "demo", "--out", str(tmp_path / "out"))
    assert done.returncode == 2
    message = done.stderr
    assert message.startswith("deepsync demo: error: the demo's recording bags/campus_route is not here")
    assert str(tmp_path / "bags" / "campus_route") in message  # where it looked
    assert "--bag BAG" in message and "--simulate SECONDS" in message  # how to get one
    assert not (tmp_path / "out").exists()


def test_installed_demo_simulates_its_scenario_and_runs_the_chain(installed: Path, tmp_path: Path) -> None:
    """The scenario, the tower database and the message definitions all from the package."""
    done = _run(installed, tmp_path, "-m", "deepsync.cli", "demo", "--simulate", "1", "--workers", "1", "--quiet",
                "--out", "out")
    assert done.returncode == 0, done.stderr
    assert "recorded 1.000 s of ADC stream" in done.stdout
    assert "  heard       no cell; sites per stack: 0: 1\n" in done.stdout  # one stack, not yet confirmed
    for written in ("recording/metadata.yaml", "replay/metadata.yaml", "route.json"):
        assert (tmp_path / "out" / written).is_file(), written


def test_demo_looks_in_the_checkout_first_then_the_working_directory(tmp_path: Path,
                                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    assert demo.bag_places() == [REPO / demo.BAG, tmp_path / demo.BAG]
    assert demo.find_bag() == REPO / demo.BAG
    monkeypatch.setattr(demo, "_checkout", lambda: None)  # installed
    with pytest.raises(ValueError, match="not here") as refused:
        demo.find_bag()
    assert str(tmp_path / demo.BAG) in str(refused.value)
    (tmp_path / demo.BAG).mkdir(parents=True)
    assert demo.find_bag() == tmp_path / demo.BAG
    assert demo.find_bag("my/walk") == Path("my/walk")  # given: taken as it is


def test_one_copy_of_the_demo_files() -> None:
    """The tower database and scenario the demo ships are the files config/ and deepsync_ros
    hold (links), so the docs' paths, the launch default and the package read the same bytes."""
    with demo.packaged(demo.TOWERS) as towers, demo.packaged(demo.SCENARIO) as scenario:
        assert (REPO / "config" / "towers" / "campus.yaml").resolve() == towers.resolve()
        assert (REPO / "src" / "deepsync_ros" / "config" / "towers" / "campus.yaml").resolve() == towers.resolve()
        assert (REPO / "config" / "scenarios" / "campus_route.yaml").resolve() == scenario.resolve()

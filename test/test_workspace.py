"""The colcon workspace is what a ROS 2 user's ``colcon build`` will see.

Checked with Debian's colcon + colcon-ros (package discovery and build types) and catkin_pkg
(package.xml validation), the same libraries a Jazzy install uses; ROS itself is not needed.
"""

from __future__ import annotations

import configparser
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from system_python import missing, run_python

REPO = Path(__file__).resolve().parents[1]
EXPECTED = {
    "deepsync": ("src/deepsync", "ros.ament_python"),
    "deepsync_msgs": ("src/deepsync_msgs", "ros.ament_cmake"),
    "deepsync_ros": ("src/deepsync_ros", "ros.ament_python"),
}
PYTHON_PACKAGES = ("deepsync", "deepsync_ros")


def _colcon_skip_reason() -> str | None:
    if shutil.which("colcon") is None:
        return "colcon not on PATH (apt install colcon python3-colcon-ros)"
    return missing("import colcon_ros", "python3-colcon-ros")


_CATKIN_SKIP = missing("import catkin_pkg.package", "python3-catkin-pkg")


needs_colcon = pytest.mark.skipif(
    _colcon_skip_reason() is not None, reason=_colcon_skip_reason() or ""
)
needs_catkin = pytest.mark.skipif(_CATKIN_SKIP is not None, reason=_CATKIN_SKIP or "")


def run_colcon(tmp_path: Path, *args: str) -> str:
    """``colcon list ...`` from the repo root, isolated from user config, writing no log files;
    its standard output."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("COLCON_")}
    env["COLCON_HOME"] = str(tmp_path / "colcon_home")  # no user defaults / mixins
    had_log = (REPO / "log").exists()
    proc = subprocess.run(
        ["colcon", "--log-base", os.devnull, "list", *args],
        cwd=REPO,
        env=env,
        check=False,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    assert had_log or not (REPO / "log").exists(), "colcon list wrote a log/ directory"
    return proc.stdout


def colcon_list(tmp_path: Path, *args: str) -> dict[str, tuple[str, str]]:
    """Packages ``colcon list`` finds: name -> (path, build type)."""
    packages = {}
    for line in run_colcon(tmp_path, *args).splitlines():
        name, path, kind = line.split("\t")
        packages[name] = (path, kind.strip("()"))
    return packages


@needs_colcon
def test_colcon_finds_exactly_our_packages_under_src(tmp_path: Path) -> None:
    assert colcon_list(tmp_path, "--base-paths", "src") == EXPECTED


@needs_colcon
def test_colcon_from_root_finds_nothing_else(tmp_path: Path) -> None:
    """From the root (colcon's default base path) too: the root, test/, bags/, config/ and the
    hidden .venv are not packages."""
    found = colcon_list(tmp_path)
    assert found == EXPECTED
    assert all(path.startswith("src/") for path, _ in found.values())


@needs_colcon
def test_colcon_build_order(tmp_path: Path) -> None:
    """``deepsync_ros`` comes after the packages it depends on."""
    order = run_colcon(tmp_path, "--base-paths", "src", "--topological-order", "--names-only").split()
    assert order.index("deepsync_ros") > order.index("deepsync_msgs")
    assert order.index("deepsync_ros") > order.index("deepsync")


CATKIN_SCRIPT = r"""
import json, sys
from catkin_pkg.package import parse_package
warnings = []
pkg = parse_package(sys.argv[1], warnings=warnings)
pkg.validate(warnings=warnings)
print(json.dumps({
    "name": pkg.name,
    "format": pkg.package_format,
    "build_type": pkg.get_build_type(),
    "groups": [g.name for g in pkg.member_of_groups],
    "exec_depends": [d.name for d in pkg.exec_depends],
    "test_depends": [d.name for d in pkg.test_depends],
    "warnings": warnings,
}))
"""


def catkin_parse(pkg_dir: Path) -> dict:
    proc = run_python(CATKIN_SCRIPT, str(pkg_dir), timeout=60)
    assert proc.returncode == 0, f"{pkg_dir}/package.xml is invalid:\n{proc.stderr}"
    return json.loads(proc.stdout)


@needs_catkin
@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_package_xml_validates(name: str) -> None:
    info = catkin_parse(REPO / EXPECTED[name][0])
    assert info["name"] == name
    assert info["format"] == 3
    assert info["warnings"] == [], f"catkin_pkg warnings for {name}: {info['warnings']}"
    assert "ros." + info["build_type"] == EXPECTED[name][1]


@needs_catkin
def test_msgs_package_is_an_interface_package() -> None:
    info = catkin_parse(REPO / "src" / "deepsync_msgs")
    assert "rosidl_interface_packages" in info["groups"]
    assert "rosidl_default_runtime" in info["exec_depends"]


@needs_catkin
def test_ros_package_depends_on_core_and_msgs() -> None:
    info = catkin_parse(REPO / "src" / "deepsync_ros")
    assert {"rclpy", "deepsync", "deepsync_msgs"} <= set(info["exec_depends"])


@needs_catkin
def test_ros_package_declares_what_nodes_and_launch_use() -> None:
    """Messages, diagnostic_updater, /clock, parameter descriptors, the launch file, its test."""
    info = catkin_parse(REPO / "src" / "deepsync_ros")
    assert {"std_msgs", "geometry_msgs", "sensor_msgs", "nav_msgs", "diagnostic_msgs", "diagnostic_updater",
            "rosgraph_msgs", "rcl_interfaces", "launch", "launch_ros", "ament_index_python"} <= set(info["exec_depends"])
    assert {"launch_testing", "launch_testing_ros", "python3-pytest"} <= set(info["test_depends"])


@needs_catkin
def test_core_python_dependencies_are_rosdep_keys() -> None:
    """The core's dependencies that have rosdep keys (ros/rosdistro rosdep/python.yaml) are declared;
    rosbags, mcap, sigmf and threadpoolctl have none and come from pip (docs/ros.md)."""
    info = catkin_parse(REPO / "src" / "deepsync")
    assert {"python3-numpy", "python3-scipy", "python3-yaml", "python3-pyproj", "python3-tqdm",
            "python3-matplotlib"} <= set(info["exec_depends"])


@pytest.mark.parametrize("name", PYTHON_PACKAGES)
def test_setup_cfg_installs_scripts_into_lib_pkg(name: str) -> None:
    """``ros2 run <pkg> <node>`` looks in lib/<pkg>, not bin/."""
    cfg = configparser.ConfigParser(interpolation=None)
    cfg.read(REPO / "src" / name / "setup.cfg")
    assert cfg["develop"]["script_dir"] == f"$base/lib/{name}"
    assert cfg["install"]["install_scripts"] == f"$base/lib/{name}"


@pytest.mark.parametrize("name", PYTHON_PACKAGES)
def test_ament_resource_marker(name: str) -> None:
    """ament_index registration: the marker file exists and setup.py installs it."""
    pkg = REPO / "src" / name
    assert (pkg / "resource" / name).is_file()
    setup_py = (pkg / "setup.py").read_text()
    assert "share/ament_index/resource_index/packages" in setup_py


def test_colcon_meta_is_valid_json() -> None:
    meta = json.loads((REPO / "colcon.meta").read_text())
    assert isinstance(meta.get("names"), dict)
    assert set(meta["names"]) <= set(EXPECTED)
    assert all(isinstance(v, dict) for v in meta["names"].values())


def test_deepsync_ros_imports_without_rclpy() -> None:
    """The package itself must import on a machine without ROS (no module-level rclpy)."""
    code = (
        "import sys; sys.path.insert(0, sys.argv[1]); import deepsync_ros; "
        "assert 'rclpy' not in sys.modules, 'rclpy imported'"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code, str(REPO / "src" / "deepsync_ros")],
        check=False,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 0, proc.stderr


def _build_alone(tmp_path: Path, name: str, *options: str) -> Path:
    """``colcon build`` in a workspace that holds only the package ``name`` (copied, symlinks
    resolved as a tarball or a git checkout of the folder would give them); its install prefix."""
    workspace = tmp_path / "ws"
    shutil.copytree(REPO / EXPECTED[name][0], workspace / "src" / name, symlinks=False,
                    ignore=shutil.ignore_patterns("__pycache__", "*.egg-info", "build", "install", "log"))
    env = {k: v for k, v in os.environ.items() if not k.startswith(("COLCON_", "PYTHON", "VIRTUAL_ENV"))}
    env["COLCON_HOME"] = str(tmp_path / "colcon_home")
    env["PATH"] = os.pathsep.join(p for p in env.get("PATH", "").split(os.pathsep) if ".venv" not in p)
    done = subprocess.run(["colcon", "build", "--event-handlers", "console_direct-", *options],
                          cwd=workspace, env=env, capture_output=True, text=True, timeout=300, check=False)
    assert done.returncode == 0, f"{name} does not build alone:\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}"
    return workspace / "install" / name


@needs_colcon
@pytest.mark.parametrize("options", [(), ("--symlink-install",)], ids=["copy", "symlink"])
def test_ros_package_builds_alone_with_everything_its_launch_needs(tmp_path: Path, options: tuple) -> None:
    """A workspace holding the deepsync_ros folder alone builds (issue #49: setup.py copied
    ../../config), and installs the launch file's defaults: params, tower database, the bag."""
    share = _build_alone(tmp_path, "deepsync_ros", *options) / "share" / "deepsync_ros"
    for path in ("launch/deepsync.launch.py", "launch/dual_ekf.launch.py", "config/deepsync_nodes.yaml",
                 "config/deepsync_ekf_poses.yaml", "config/towers/campus.yaml",
                 "config/robot_localization_dual_ekf.yaml", "bags/campus/metadata.yaml", "bags/campus/campus.mcap",
                 "package.xml"):
        assert (share / path).is_file(), f"share/deepsync_ros/{path} is not installed"
    assert (share / "bags" / "campus" / "campus.mcap").stat().st_size == \
        (REPO / "src" / "deepsync_ros" / "bags" / "campus" / "campus.mcap").stat().st_size


@needs_colcon
def test_core_package_builds_alone(tmp_path: Path) -> None:
    prefix = _build_alone(tmp_path, "deepsync")
    assert (prefix / "share" / "deepsync" / "package.xml").is_file()
    assert (prefix / "lib" / "deepsync" / "deepsync").is_file()  # ros2 run deepsync deepsync
    for data in ("deepsync/data/towers/campus.yaml", "deepsync/data/scenarios/campus_route.yaml",
                 "deepsync/bag/msg/EnvelopeSamples.msg", "deepsync/timing/timing_net.pt"):  # the package data
        assert list(prefix.glob(f"lib/python*/site-packages/{data}")), f"{data} is not installed"


def test_bundled_files_at_the_root_are_the_packages() -> None:
    """The repository root's campus bag is a link into deepsync_ros; the demo's tower database and
    scenario are the core package's data (``deepsync.eval.demo``), linked from the root and, for the
    launch file's default, from deepsync_ros: one copy each, where they always were."""
    core_data = (REPO / "src" / "deepsync" / "deepsync" / "data").resolve()
    for path, owner in (("bags/campus", REPO / "src" / "deepsync_ros"), ("config/towers/campus.yaml", core_data),
                        ("config/scenarios/campus_route.yaml", core_data),
                        ("src/deepsync_ros/config/towers/campus.yaml", core_data)):
        linked = REPO / path
        assert linked.is_symlink(), f"{path} should link into {owner.relative_to(REPO.resolve())}"
        assert linked.resolve().is_relative_to(owner.resolve())
        assert linked.exists()

"""The launch file: its arguments, the executables it starts, what it imports, its helpers.

Without ROS the launch file is read as source (``ast``) and its standard-library helpers are run
on their own; where ``launch``/``launch_ros`` import, ``generate_launch_description()`` is called;
where ROS 2 is sourced and deepsync_ros is built, the launch_testing check
``test/ros_launch/deepsync_pose_launch.py`` runs the real launch and waits for a pose.
"""

from __future__ import annotations

import ast
import importlib.util
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
LAUNCH_FILE = REPO / "src" / "deepsync_ros" / "launch" / "deepsync.launch.py"
SETUP_PY = REPO / "src" / "deepsync_ros" / "setup.py"
NODES_YAML = REPO / "src" / "deepsync_ros" / "config" / "deepsync_nodes.yaml"
POSE_LAUNCH_TEST = REPO / "test" / "ros_launch" / "deepsync_pose_launch.py"
SHARE = "$(find-pkg-share deepsync_ros)"

# The documented arguments (docs/ros.md) and their defaults.
DOCUMENTED = {
    "source": f"{SHARE}/bags/campus",
    "towers": f"{SHARE}/config/towers/campus.yaml",
    "bias_map": "",
    "params_file": f"{SHARE}/config/deepsync_nodes.yaml",
    "extra_params_file": "",
    "use_sim_time": "true",
    "namespace": "deepsync",
    "one_process": "false",
    "loop": "true",
    "realtime": "true",
    "motion": "",
    "antenna_tf": "true",
    "base_frame": "base_link",
    "antenna_x": "0.0",
    "antenna_y": "0.0",
    "antenna_z": "0.0",
}
NODE_NAMES = ("envelope_adc", "cell_sync", "cell_timing", "tdoa_fusion", "deepsync_pipeline")
# What may never be imported by the launch file: it runs on the interpreter of `ros2 launch`.
FORBIDDEN_IMPORTS = {"numpy", "scipy", "torch", "rosbags", "mcap", "deepsync", "deepsync_ros", "deepsync_msgs"}
ROS_IMPORTS = {"launch", "launch_ros", "ament_index_python", "yaml"}

TREE = ast.parse(LAUNCH_FILE.read_text(), filename=str(LAUNCH_FILE))


def _calls(tree: ast.AST, name: str) -> list[ast.Call]:
    return [node for node in ast.walk(tree) if isinstance(node, ast.Call)
            and getattr(node.func, "id", getattr(node.func, "attr", None)) == name]


def _keyword(call: ast.Call, name: str) -> ast.expr | None:
    return next((k.value for k in call.keywords if k.arg == name), None)


def _module_constant(name: str):
    for node in TREE.body:
        if isinstance(node, ast.Assign) and any(getattr(t, "id", None) == name for t in node.targets):
            return ast.literal_eval(node.value)
    raise AssertionError(f"{LAUNCH_FILE.name} has no module-level {name}")


def _render_default(node: ast.expr) -> str:
    """A DeclareLaunchArgument default as text: a string, or _share('a', 'b') -> $(find-pkg-share)/a/b."""
    if isinstance(node, ast.Constant) and isinstance(node.value, str):
        return node.value
    if isinstance(node, ast.Call) and getattr(node.func, "id", None) == "_share":
        return "/".join([SHARE, *(ast.literal_eval(arg) for arg in node.args)])
    raise AssertionError(f"unexpected default {ast.dump(node)}")


def declared_arguments() -> dict[str, str]:
    found = {}
    for call in _calls(TREE, "DeclareLaunchArgument"):
        name = ast.literal_eval(call.args[0])
        assert name not in found, f"argument {name} declared twice"
        default = _keyword(call, "default_value")
        assert default is not None, f"argument {name} has no default"
        description = _keyword(call, "description")
        assert description is not None and len(ast.literal_eval(description)) > 20, f"{name}: no description"
        found[name] = _render_default(default)
    return found


def test_declares_exactly_the_documented_arguments_and_defaults() -> None:
    assert declared_arguments() == DOCUMENTED


def test_share_defaults_point_into_this_package() -> None:
    (share,) = [node for node in TREE.body if isinstance(node, ast.FunctionDef) and node.name == "_share"]
    (find,) = _calls(share, "FindPackageShare")
    assert isinstance(find.args[0], ast.Name) and _module_constant(find.args[0].id) == "deepsync_ros"


def test_share_defaults_are_installed_by_setup_py() -> None:
    """Every default path under the package share is a data_files destination of setup.py."""
    installed = setup_py_data_files()
    for name, default in DOCUMENTED.items():
        if default.startswith(SHARE):
            relative = default[len(SHARE) + 1:]
            assert any(dest == f"share/deepsync_ros/{relative}" or dest.startswith(f"share/deepsync_ros/{relative}/")
                       for dest in installed.values()), f"{name} default {relative} is not installed"


def test_documented_arguments_are_in_docs() -> None:
    text = (REPO / "docs" / "ros.md").read_text()
    for name, default in DOCUMENTED.items():
        assert f"`{name}`" in text, f"docs/ros.md does not document {name}"
    assert "source:=topic" in text


# --- setup.py ---------------------------------------------------------------------------------


def setup_py_entry_points() -> dict[str, str]:
    tree = ast.parse(SETUP_PY.read_text())
    (setup,) = _calls(tree, "setup")
    entry_points = ast.literal_eval(_keyword(setup, "entry_points"))
    return dict(line.replace(" ", "").split("=", 1) for line in entry_points["console_scripts"])


def setup_py_data_files() -> dict[str, str]:
    """source (relative to the repo) -> destination, evaluated from setup.py as colcon does
    (run in the package directory), without running setup()."""
    code = (
        "import json, os, sys, setuptools\n"
        "captured = {}\n"
        "setuptools.setup = lambda **kw: captured.update(kw)\n"
        "sys.argv = ['setup.py']\n"
        "exec(compile(open('setup.py').read(), 'setup.py', 'exec'), {'__file__': os.path.abspath('setup.py'),"
        " '__name__': '__main__'})\n"
        "out = {}\n"
        "for dest, sources in captured['data_files']:\n"
        "    for s in sources:\n"
        "        out[os.path.relpath(os.path.abspath(s), os.path.abspath('../..'))] = os.path.join(dest, os.path.basename(s))\n"
        "print(json.dumps(out))\n"
    )
    done = subprocess.run([sys.executable, "-c", code], cwd=SETUP_PY.parent, capture_output=True, text=True,
                          timeout=60, check=False)
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)


def test_launch_starts_only_executables_setup_py_declares() -> None:
    entry_points = setup_py_entry_points()
    assert entry_points == {name: f"deepsync_ros.entry:{name}" for name in NODE_NAMES}
    started = set(_module_constant("FOUR_NODES")) | {_module_constant("ONE_PROCESS")}
    assert started == set(NODE_NAMES)
    # the dependency check reads the shebang of an executable setup.py installs
    (script,) = [node for node in TREE.body if isinstance(node, ast.FunctionDef) and node.name == "_node_script"]
    defaults = {a.arg: ast.literal_eval(d) for a, d in zip(script.args.args[-len(script.args.defaults):],
                                                          script.args.defaults) if isinstance(d, ast.Constant)}
    assert defaults["executable"] in entry_points
    # every Node() passes package=PACKAGE and the executable as its node name
    (node_call,) = [call for call in _calls(TREE, "Node") if ast.unparse(_keyword(call, "package")) == "PACKAGE"]
    assert ast.unparse(_keyword(node_call, "executable")) == ast.unparse(_keyword(node_call, "name"))
    assert ast.unparse(_keyword(node_call, "package")) == "PACKAGE"


def test_setup_py_data_files_exist_relative_to_where_colcon_runs_it() -> None:
    data_files = setup_py_data_files()
    for source in data_files:
        assert (REPO / source).is_file(), f"setup.py installs {source}, which does not exist"
        # a workspace may hold the package folder alone: nothing may come from outside it
        assert Path(source).parts[:2] == ("src", "deepsync_ros"), f"setup.py installs {source}, outside the package"
    destinations = set(data_files.values())
    for expected in ("share/deepsync_ros/launch/deepsync.launch.py",
                     "share/deepsync_ros/config/deepsync_nodes.yaml",
                     "share/deepsync_ros/config/robot_localization_dual_ekf.yaml",
                     "share/deepsync_ros/config/deepsync_ekf_poses.yaml",
                     "share/deepsync_ros/launch/dual_ekf.launch.py",
                     "share/deepsync_ros/config/foxglove_layout.json",
                     "share/deepsync_ros/config/towers/campus.yaml",
                     "share/deepsync_ros/bags/campus/metadata.yaml",
                     "share/deepsync_ros/bags/campus/campus.mcap",
                     "share/deepsync_ros/package.xml",
                     "share/ament_index/resource_index/packages/deepsync_ros"):
        assert expected in destinations, f"setup.py does not install {expected}"


# --- imports ----------------------------------------------------------------------------------


def _imported(tree: ast.AST) -> list[tuple[str, int]]:
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(alias.name.split(".")[0], node.col_offset) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            found.append(((node.module or "").split(".")[0], node.col_offset))
    return found


def test_launch_file_never_imports_numpy_or_deepsync() -> None:
    imported = _imported(TREE)
    assert not {name for name, _ in imported} & FORBIDDEN_IMPORTS
    module_level = {name for name, column in imported if column == 0}
    assert module_level <= set(sys.stdlib_module_names) | {"launch", "launch_ros"}, module_level
    assert {name for name, _ in imported} <= set(sys.stdlib_module_names) | ROS_IMPORTS


# --- the helpers, run without ROS -------------------------------------------------------------

HELPERS = ("_as_bool", "_number", "_interpreter_command", "_check_dependencies", "_params_key_matches",
           "_unmatched_nodes", "_is_bag", "_is_address", "_refusal", "_end_of_a_required_node", "_node_overrides")


def _load_helpers() -> dict:
    """The launch file's standard-library helpers, compiled on their own (launch not needed)."""
    body = [node for node in TREE.body
            if (isinstance(node, ast.Import) and all(a.name in sys.stdlib_module_names for a in node.names))
            or (isinstance(node, ast.Assign) and not any(isinstance(n, ast.Call) for n in ast.walk(node.value)))
            or (isinstance(node, ast.FunctionDef) and node.name in HELPERS)]
    namespace: dict = {}
    exec(compile(ast.Module(body=body, type_ignores=[]), str(LAUNCH_FILE), "exec"), namespace)
    assert all(name in namespace for name in HELPERS)
    return namespace


H = _load_helpers()


@pytest.mark.parametrize("text,value", [("true", True), ("True", True), ("1", True), ("false", False),
                                        ("FALSE", False), ("0", False)])
def test_as_bool(text: str, value: bool) -> None:
    assert H["_as_bool"]("loop", text) is value


@pytest.mark.parametrize("text", ["x", "nan", "inf", ""])
def test_number_refuses_what_is_not_a_finite_number(text: str) -> None:
    with pytest.raises(ValueError, match="antenna_x:="):
        H["_number"]("antenna_x", text)
    assert H["_number"]("antenna_x", " -0.25 ") == -0.25


def test_a_bias_map_reaches_the_fusing_nodes_and_an_empty_one_leaves_the_params_file() -> None:
    bag = str(REPO / "bags" / "campus")
    given = H["_node_overrides"](bag, "towers.yaml", "walk.npz", "vehicle", realtime=True, loop=False,
                                 use_sim_time=True)
    assert {name for name, values in given.items() if "bias_map" in values} == {"tdoa_fusion", "deepsync_pipeline"}
    assert given["tdoa_fusion"]["bias_map"] == given["deepsync_pipeline"]["bias_map"] == "walk.npz"
    assert given["cell_sync"] == {"towers": "towers.yaml", "frontend": bag, "motion": "vehicle"}
    unset = H["_node_overrides"](bag, "towers.yaml", "", "", realtime=True, loop=False, use_sim_time=True)
    assert not any("bias_map" in values or "motion" in values for values in unset.values())
    assert "frontend" not in H["_node_overrides"]("topic", "t.yaml", "", "", realtime=True, loop=False,
                                                  use_sim_time=True)["cell_sync"]


class _Exited:
    """What launch's OnProcessExit hands on_exit: a ProcessExited event's name and status."""

    def __init__(self, returncode: int) -> None:
        self.process_name = "cell_sync-2"
        self.returncode = returncode


class _Context:
    def __init__(self, shutting_down: bool) -> None:
        self.is_shutdown = shutting_down


def test_a_node_that_fails_ends_the_launch_with_its_name_and_status() -> None:
    """issue #49: cell_sync exiting 1 (n_frames: -3) left the launch running for ever."""
    with pytest.raises(RuntimeError, match="deepsync launch: cell_sync-2 exited with status 1"):
        H["_end_of_a_required_node"](_Exited(1), _Context(shutting_down=False))


def test_nodes_stopping_while_the_launch_shuts_down_are_no_failure() -> None:
    assert H["_end_of_a_required_node"](_Exited(-2), _Context(shutting_down=True)) is None


def test_every_deepsync_node_is_required() -> None:
    """Each Node() of our package ends the launch when it exits (on_exit)."""
    ours = [call for call in _calls(TREE, "Node") if ast.unparse(_keyword(call, "package")) == "PACKAGE"]
    assert ours and all(ast.unparse(_keyword(call, "on_exit")) == "_end_of_a_required_node" for call in ours)


def test_the_antenna_transform_is_tf2_ros_static_publisher_of_the_navsat_frame() -> None:
    (tf_node,) = [call for call in _calls(TREE, "Node") if ast.unparse(_keyword(call, "package")) == "'tf2_ros'"]
    assert ast.literal_eval(_keyword(tf_node, "executable")) == "static_transform_publisher"
    arguments = ast.unparse(_keyword(tf_node, "arguments"))
    assert "'--frame-id'" in arguments and "'--child-frame-id', ANTENNA_FRAME" in arguments
    from deepsync.bag.convert import ANTENNA_FRAME_ID
    assert _module_constant("ANTENNA_FRAME") == ANTENNA_FRAME_ID


def test_as_bool_refuses_anything_else() -> None:
    with pytest.raises(ValueError, match="loop:='yes' is not a boolean"):
        H["_as_bool"]("loop", "yes")


@pytest.mark.parametrize("head,command", [
    ("#!/usr/bin/python3\n", ["/usr/bin/python3"]),
    ("#!/home/me/ws/.venv/bin/python -E\n", ["/home/me/ws/.venv/bin/python", "-E"]),
    ("#!/usr/bin/env python3\n", ["/usr/bin/env", "python3"]),
    ('#!"/home/me/my ws/.venv/bin/python"\n', ["/home/me/my ws/.venv/bin/python"]),
    ("#!/bin/sh\n'''exec' \"/very/long path/bin/python3\" \"$0\" \"$@\"\n' '''\n", ["/very/long path/bin/python3"]),
])
def test_interpreter_from_shebang(tmp_path: Path, head: str, command: list[str]) -> None:
    script = tmp_path / "envelope_adc"
    script.write_text(head + "import sys\n")
    assert H["_interpreter_command"](str(script)) == command


def test_interpreter_without_shebang_is_an_error(tmp_path: Path) -> None:
    script = tmp_path / "envelope_adc"
    script.write_text("import sys\n")
    with pytest.raises(ValueError, match="no shebang"):
        H["_interpreter_command"](str(script))


def test_dependency_check_reports_what_is_missing(tmp_path: Path) -> None:
    """The real check, with ROS or without: a dependency made to fail to import (a package of that
    name first on the path that raises) is named, with how to get it, and the check fails."""
    shadow = tmp_path / "sigmf"
    shadow.mkdir()
    (shadow / "__init__.py").write_text("raise ImportError('made unimportable by the test')\n")
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(tmp_path), *filter(None, [env.get("PYTHONPATH")]), *sys.path])
    ok, said = H["_check_dependencies"]([sys.executable], env=env)
    assert not ok
    assert "sigmf does not import (ImportError: made unimportable by the test); pip install 'sigmf>=1.14'" in said
    if importlib.util.find_spec("deepsync_msgs") is None:  # no ROS here: that is missing too
        assert "deepsync_msgs.msg does not import" in said and "colcon build" in said
    else:
        assert "deepsync_msgs" not in said


def test_dependency_check_passes_when_the_module_exits_0() -> None:
    ok, said = H["_check_dependencies"]([sys.executable, "-c", "print('all there')"])
    assert ok and said == "all there"


def test_dependency_check_of_a_missing_interpreter() -> None:
    ok, said = H["_check_dependencies"](["/nonexistent/python3"])
    assert not ok and "could not run /nonexistent/python3" in said


@pytest.mark.parametrize("key,fqn,matches", [
    ("/**/envelope_adc", "/deepsync/envelope_adc", True),
    ("/**/envelope_adc", "/envelope_adc", True),
    ("/**/envelope_adc", "/robot1/deepsync/envelope_adc", True),
    ("/**/envelope_adc", "/deepsync/cell_sync", False),
    ("envelope_adc", "/envelope_adc", True),
    ("envelope_adc", "/deepsync/envelope_adc", False),  # rclpy prepends '/': root namespace only
    ("/deepsync/envelope_adc", "/deepsync/envelope_adc", True),
    ("/deepsync/envelope_adc", "/other/envelope_adc", False),
    ("/*/envelope_adc", "/deepsync/envelope_adc", True),
    ("/*/envelope_adc", "/a/b/envelope_adc", False),
    ("/deepsync/*", "/deepsync/tdoa_fusion", True),
    ("/**", "/deepsync/tdoa_fusion", True),
])
def test_params_key_matching(key: str, fqn: str, matches: bool) -> None:
    assert H["_params_key_matches"](key, fqn) is matches


def test_unmatched_nodes(tmp_path: Path) -> None:
    params = tmp_path / "p.yaml"
    params.write_text("/**/envelope_adc:\n  ros__parameters: {loop: true}\ncell_sync:\n  ros__parameters: {}\n")
    assert H["_unmatched_nodes"](str(params), ["/deepsync/envelope_adc", "/deepsync/cell_sync"]) == [
        "/deepsync/cell_sync"]


def test_the_nodes_yaml_reaches_every_node_in_any_namespace() -> None:
    """config/deepsync_nodes.yaml (the launch default) applies to each node under /deepsync and
    under another namespace (the launch's namespace argument)."""
    assert NODES_YAML.is_file(), f"{NODES_YAML} is missing"
    for namespace in ("/deepsync", "/robot1/deepsync", ""):
        names = [f"{namespace}/{name}" for name in NODE_NAMES]
        assert H["_unmatched_nodes"](str(NODES_YAML), names) == [], namespace


def test_a_live_address_is_not_checked_as_a_path() -> None:
    assert H["_is_address"]("rtl_tcp://192.168.1.5:1234?freq=1860e6")
    assert H["_is_address"]("tcp://localhost:5000")
    assert not H["_is_address"]("/dev/ttyUSB0")  # a device path exists, and is checked as one
    assert not H["_is_address"]("bags/campus")


def test_is_bag() -> None:
    assert H["_is_bag"](str(REPO / "bags" / "campus"))
    assert H["_is_bag"]("/anywhere/route.mcap")
    assert not H["_is_bag"](str(REPO / "config" / "scenarios" / "campus.yaml"))


# --- with ROS ---------------------------------------------------------------------------------


def _ros_missing(*modules: str) -> str | None:
    for module in modules:
        try:
            importlib.import_module(module)
        except Exception as error:  # ImportError, or a ROS install built for another Python
            return f"{module} does not import here ({type(error).__name__}: {error}); ROS 2 Jazzy not sourced"
    return None


@pytest.mark.skipif(_ros_missing("launch", "launch_ros") is not None,
                    reason=_ros_missing("launch", "launch_ros") or "")
def test_generate_launch_description_declares_the_arguments() -> None:
    from launch import LaunchContext
    from launch.actions import DeclareLaunchArgument, OpaqueFunction
    from launch.utilities import perform_substitutions

    spec = importlib.util.spec_from_file_location("deepsync_launch", LAUNCH_FILE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    description = module.generate_launch_description()
    arguments = {e.name: e for e in description.entities if isinstance(e, DeclareLaunchArgument)}
    assert set(arguments) == set(DOCUMENTED)
    for name, default in DOCUMENTED.items():
        if not default.startswith(SHARE):
            assert perform_substitutions(LaunchContext(), arguments[name].default_value) == default
    assert any(isinstance(e, OpaqueFunction) for e in description.entities)


def _launch_test_skip_reason() -> str | None:
    reason = _ros_missing("rclpy", "launch_testing", "launch_ros", "geometry_msgs.msg", "ament_index_python")
    if reason:
        return reason
    if shutil.which("launch_test") is None:
        return "launch_test is not on PATH (apt install ros-jazzy-launch-testing; source /opt/ros/jazzy/setup.bash)"
    from ament_index_python.packages import PackageNotFoundError, get_package_share_directory
    try:
        get_package_share_directory("deepsync_ros")
    except PackageNotFoundError:
        return "deepsync_ros is not built and sourced (colcon build; source install/setup.bash)"
    return None


@pytest.mark.slow
@pytest.mark.skipif(_launch_test_skip_reason() is not None, reason=_launch_test_skip_reason() or "")
def test_default_launch_publishes_a_pose_within_120_s() -> None:
    """In a DDS domain of its own: in a full run this process's own nodes (test_ros_nodes, in the
    same /deepsync namespace) and whatever else the machine runs must not meet the launch's."""
    env = dict(os.environ, ROS_DOMAIN_ID=str(50 + os.getpid() % 50), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    done = subprocess.run(["launch_test", str(POSE_LAUNCH_TEST)], capture_output=True, text=True,
                          timeout=400, check=False, env=env)
    assert done.returncode == 0, done.stdout[-6000:] + done.stderr[-6000:]


def _ros2_launch_skip_reason() -> str | None:
    if shutil.which("ros2") is None:
        return "ros2 is not on PATH (source /opt/ros/jazzy/setup.bash)"
    return _launch_test_skip_reason()


@pytest.mark.skipif(_ros2_launch_skip_reason() is not None, reason=_ros2_launch_skip_reason() or "")
def test_a_refused_launch_starts_nothing_says_why_and_exits_1() -> None:
    # a Shutdown action would end the launch with 0: scripts and CI must see the failure
    done = subprocess.run(["ros2", "launch", "deepsync_ros", "deepsync.launch.py", "towers:=/nonexistent/towers.yaml"],
                          capture_output=True, text=True, timeout=60, check=False)
    said = done.stdout + done.stderr
    assert done.returncode == 1, said
    assert "no such file or directory: towers:=/nonexistent/towers.yaml" in said
    assert "Traceback" not in said and "process started" not in said


# --- PROJ's data for the nodes (issue #49: every node warned "Valid PROJ data directory not found") ---


def _base_python_with_proj(tmp_path: Path) -> Path:
    data = tmp_path / "usr" / "share" / "proj"
    data.mkdir(parents=True)
    (data / "proj.db").write_bytes(b"")
    return tmp_path / "usr"


def test_a_venv_over_a_system_python_gets_the_systems_proj_data(tmp_path: Path, monkeypatch) -> None:
    from deepsync_ros import dependencies
    base = _base_python_with_proj(tmp_path)
    monkeypatch.setattr(dependencies.os, "environ", {})
    monkeypatch.setattr(dependencies.sys, "prefix", str(tmp_path / "venv"))
    monkeypatch.setattr(dependencies.sys, "base_prefix", str(base))
    dependencies.use_system_proj_data()
    assert dependencies.os.environ == {"PROJ_DATA": str(base / "share" / "proj")}


@pytest.mark.parametrize("situation", ["set by the user", "no venv", "no system data"])
def test_proj_data_is_left_alone_otherwise(tmp_path: Path, monkeypatch, situation: str) -> None:
    from deepsync_ros import dependencies
    base = _base_python_with_proj(tmp_path) if situation != "no system data" else tmp_path / "bare"
    environ = {"PROJ_LIB": "/opt/proj"} if situation == "set by the user" else {}
    monkeypatch.setattr(dependencies.os, "environ", dict(environ))
    monkeypatch.setattr(dependencies.sys, "prefix", str(base if situation == "no venv" else tmp_path / "venv"))
    monkeypatch.setattr(dependencies.sys, "base_prefix", str(base))
    dependencies.use_system_proj_data()
    assert dependencies.os.environ == environ


@pytest.mark.skipif(_ros2_launch_skip_reason() is not None, reason=_ros2_launch_skip_reason() or "")
def test_a_node_that_cannot_run_ends_the_launch_with_its_reason(tmp_path: Path) -> None:
    """issue #49: cell_sync refusing n_frames -3 left the launch running for ever."""
    broken = tmp_path / "broken.yaml"
    broken.write_text("/**/cell_sync:\n  ros__parameters:\n    n_frames: -3\n")
    env = dict(os.environ, ROS_DOMAIN_ID=str(50 + (os.getpid() + 1) % 50), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    done = subprocess.run(["ros2", "launch", "deepsync_ros", "deepsync.launch.py", f"extra_params_file:={broken}",
                           "antenna_tf:=false"], capture_output=True, text=True, timeout=180, check=False, env=env)
    said = done.stdout + done.stderr
    assert done.returncode == 1, said
    assert "n_frames" in said  # the node's own line
    assert "cell_sync" in said and "exited with status 1" in said

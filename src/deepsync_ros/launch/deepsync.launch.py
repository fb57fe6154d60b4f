"""The whole DeepSync pipeline: envelope ADC -> cell sync -> cell timing -> TDOA fusion.

    ros2 launch deepsync_ros deepsync.launch.py            # the bundled campus bag, looped
    ros2 launch deepsync_ros deepsync.launch.py --show-args

With no arguments the envelope_adc node plays the bag installed with the package, publishes
/clock from its stamps (use_sim_time:=true) and the nodes publish /deepsync/pose within seconds.
``source:=topic`` starts no envelope_adc node: the nodes are fed by ``ros2 bag play --clock``.
``one_process:=true`` runs the single deepsync_pipeline node instead of the four.
``antenna_tf`` (true) also starts tf2_ros' static_transform_publisher for base_link ->
deepsync_antenna (the frame of the NavSatFix on /deepsync/fix) at ``antenna_x/y/z``.

Every node is required: when one exits while the launch runs (a parameter it cannot run with,
a crash), the launch ends every other node and exits 1, naming it; its own error line is
above. (A node that ended with status 0 ends the launch normally.)

Before any node starts, the nodes' own interpreter (the shebang of the installed envelope_adc
script) runs ``-m deepsync_ros.dependencies``; when a dependency is missing the launch logs what
and how to get it, starts nothing and exits 1. This file runs on the interpreter of ``ros2
launch`` (the system Python): it imports only the standard library and launch itself, never
numpy or deepsync.
"""

import os
import re
import shlex
import subprocess

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction, Shutdown
from launch.logging import get_logger
from launch.substitutions import PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.substitutions import FindPackageShare

PACKAGE = "deepsync_ros"
FOUR_NODES = ("envelope_adc", "cell_sync", "cell_timing", "tdoa_fusion")
ONE_PROCESS = "deepsync_pipeline"
TOPIC_SOURCE = "topic"  # source:=topic -> no envelope_adc node; `ros2 bag play --clock` feeds the nodes
CHECK_TIMEOUT_S = 120.0
ANTENNA_FRAME = "deepsync_antenna"  # the NavSatFix's frame_id: tdoa_fusion's antenna_frame default


def _share(*parts):
    """A path in this package's share directory, resolved when the launch runs."""
    return PathJoinSubstitution([FindPackageShare(PACKAGE), *parts])


def generate_launch_description():
    return LaunchDescription([
        DeclareLaunchArgument(
            "source",
            default_value=_share("bags", "campus"),
            description="Envelope input of the envelope_adc node: a rosbag2 directory or .mcap, a SigMF "
                        "recording, a raw recording or a scenario YAML; or a live receiver's address "
                        "(rtl_tcp://HOST:PORT?freq=1860e6, tcp://HOST:PORT, a serial device, soapy://DRIVER?"
                        "freq=...; docs/live_receivers.md). 'topic': start no envelope_adc "
                        "node, the nodes read /<namespace>/envelope (ros2 bag play --clock).",
        ),
        DeclareLaunchArgument(
            "towers",
            default_value=_share("config", "towers", "campus.yaml"),
            description="Tower database YAML (sites, PCIs, positions, timing, map origin) for cell_sync "
                        "and tdoa_fusion. It must hold the PCIs the receiver hears. '' with "
                        "one_process:=true: a blind search, cell timings but no position.",
        ),
        DeclareLaunchArgument(
            "bias_map",
            default_value="",
            description="Site bias map (.npz, deepsync survey-map or trace-map) made with the towers database, for "
                        "tdoa_fusion (or the one-process node): each mapped site's range bias comes off "
                        "its ranges. '': the params file's (none).",
        ),
        DeclareLaunchArgument(
            "params_file",
            default_value=_share("config", "deepsync_nodes.yaml"),
            description="Node parameters (keys /**/<node name>: ros__parameters:). The launch "
                        "arguments are applied on top of it.",
        ),
        DeclareLaunchArgument(
            "extra_params_file",
            default_value="",
            description="A second parameters file applied on top of params_file, holding only what it "
                        "changes (e.g. config/deepsync_ekf_poses.yaml); '': none.",
        ),
        DeclareLaunchArgument(
            "use_sim_time",
            default_value="true",
            description="Every node uses /clock. With a file source the envelope_adc node publishes "
                        "/clock from the recording's stamps; with source:=topic, ros2 bag play --clock "
                        "does. false: wall-clock time, and envelope_adc publishes no /clock.",
        ),
        DeclareLaunchArgument(
            "namespace",
            default_value="deepsync",
            description="Namespace of the nodes and their topics (/deepsync/envelope, /deepsync/pose, ...).",
        ),
        DeclareLaunchArgument(
            "one_process",
            default_value="false",
            description="true: the single deepsync_pipeline node (one process, no intermediate "
                        "messages); false: the four nodes envelope_adc, cell_sync, cell_timing, tdoa_fusion.",
        ),
        DeclareLaunchArgument(
            "loop",
            default_value="true",
            description="Start the recording over when it ends (a file source only).",
        ),
        DeclareLaunchArgument(
            "realtime",
            default_value="true",
            description="Publish the recording at its own pace; false: as fast as the nodes take it.",
        ),
        DeclareLaunchArgument(
            "motion",
            default_value="",
            description="How the receiver moves: pedestrian, vehicle or static, for cell_sync (its "
                        "stacks) and tdoa_fusion (its motion model) alike; '': the params file's.",
        ),
        DeclareLaunchArgument(
            "antenna_tf",
            default_value="true",
            description="Publish the static transform base_frame -> deepsync_antenna (the frame of the "
                        "NavSatFix on fix) with tf2_ros' static_transform_publisher; false where the "
                        "robot's URDF (robot_state_publisher) already has the antenna.",
        ),
        DeclareLaunchArgument(
            "base_frame",
            default_value="base_link",
            description="The robot frame the antenna is mounted on (REP-105 base_link).",
        ),
        DeclareLaunchArgument("antenna_x", default_value="0.0",
                              description="Antenna position in base_frame, forward [m]."),
        DeclareLaunchArgument("antenna_y", default_value="0.0",
                              description="Antenna position in base_frame, left [m]."),
        DeclareLaunchArgument("antenna_z", default_value="0.0",
                              description="Antenna position in base_frame, up [m]."),
        OpaqueFunction(function=_launch_setup),
    ])


# ---------------------------------------------------------------------------------------------
# Everything below runs when the launch runs; standard library only (tested without ROS).


def _as_bool(name, text):
    """A launch argument as a bool, accepting what launch's own conditions accept."""
    value = str(text).strip().lower()
    if value in ("true", "1"):
        return True
    if value in ("false", "0"):
        return False
    raise ValueError(f"{name}:={text!r} is not a boolean (true or false)")


def _interpreter_command(script):
    """The command (a list) that runs Python the way the installed ``script`` does: from its
    shebang (``#!/abs/python``, ``#!/usr/bin/env python3``, a quoted path) or from the
    ``#!/bin/sh`` + ``'''exec' "python" "$0"`` form pip writes for long or spaced paths."""
    with open(script, "rb") as handle:
        head = handle.read(4096).decode("utf-8", "replace").splitlines()
    if not head or not head[0].startswith("#!"):
        raise ValueError(f"{script} has no shebang line")
    command = shlex.split(head[0][2:].strip())
    if not command:
        raise ValueError(f"{script} has an empty shebang line")
    if os.path.basename(command[0]) == "sh" and len(head) > 1 and head[1].startswith("'''exec'"):
        command = shlex.split(head[1][len("'''exec'"):])[:1]
    if not command:
        raise ValueError(f"cannot tell which Python {script} runs on")
    return command


def _check_dependencies(command, env=None, timeout=CHECK_TIMEOUT_S):
    """Run ``deepsync_ros.dependencies`` with the nodes' interpreter: (ok, what it said)."""
    try:
        done = subprocess.run(
            [*command, "-m", "deepsync_ros.dependencies"],
            env=env, capture_output=True, text=True, timeout=timeout, check=False,
        )
    except (OSError, subprocess.TimeoutExpired) as error:
        return False, f"could not run {' '.join(command)} -m deepsync_ros.dependencies: {error}"
    said = "\n".join(part.strip() for part in (done.stderr, done.stdout) if part.strip())
    return done.returncode == 0, said


def _node_script(package=PACKAGE, executable="envelope_adc"):
    """The installed console script of one of our nodes (ament index), or why there is none."""
    try:
        from ament_index_python.packages import PackageNotFoundError, get_package_prefix
    except ImportError as error:
        return None, f"ament_index_python does not import ({error}): source /opt/ros/jazzy/setup.bash"
    try:
        prefix = get_package_prefix(package)
    except PackageNotFoundError:
        return None, (f"package {package} is not on the ament index: build the workspace "
                      "(colcon build) and source install/setup.bash")
    script = os.path.join(prefix, "lib", package, executable)
    if not os.path.isfile(script):
        return None, (f"{script} does not exist: rebuild the workspace (colcon build "
                      f"--packages-select {package}) and source install/setup.bash")
    return script, ""


_WILDCARD_TOKEN = {"**": "(/[^/]+)*", "*": "/[^/]+"}


def _params_key_matches(key, fully_qualified_name):
    """Whether a params-file node key applies to a node, as rclpy/rclcpp match it: a key without
    a leading slash gets one, ``/**`` matches any number of namespace tokens, ``*`` one."""
    key = str(key)
    if not key.startswith("/"):
        key = "/" + key
    pattern = "".join(_WILDCARD_TOKEN.get(token, "/" + re.escape(token))
                      for token in key.strip("/").split("/"))
    return re.fullmatch(pattern or "/", fully_qualified_name) is not None


def _unmatched_nodes(params_file, fully_qualified_names):
    """The nodes for which ``params_file`` has no entry (empty when unknown: no PyYAML)."""
    try:
        import yaml  # python3-yaml: a dependency of launch_ros
    except ImportError:
        return []
    with open(params_file, encoding="utf-8") as handle:
        document = yaml.safe_load(handle) or {}
    if not isinstance(document, dict):
        return list(fully_qualified_names)
    return [name for name in fully_qualified_names
            if not any(_params_key_matches(key, name) for key in document)]


def _is_bag(path):
    return path.endswith(".mcap") or os.path.isfile(os.path.join(path, "metadata.yaml"))


def _is_address(source):
    """A live receiver's address (``scheme://...``), not a path: the node's opener checks it."""
    return "://" in source


def _number(name, text):
    """A launch argument as a float, or why not."""
    try:
        value = float(str(text).strip())
    except ValueError:
        raise ValueError(f"{name}:={text!r} is not a number") from None
    if value != value or value in (float("inf"), float("-inf")):
        raise ValueError(f"{name}:={text!r} is not a finite number")
    return value


def _node_overrides(source, towers, bias_map, motion, *, realtime, loop, use_sim_time):
    """Node name -> the parameters the launch arguments set on top of the params files; an
    argument left '' (motion, bias_map) leaves the files' value."""
    frontend = {"frontend": source} if (source != TOPIC_SOURCE and _is_bag(source)) else {}
    playback = {"source": source, "realtime": realtime, "loop": loop,
                # the recording's stamps become /clock when every node runs on sim time
                "publish_clock": use_sim_time}
    # one motion for the nodes that stack and the node that tracks: they must agree
    moving = {"motion": motion} if motion else {}
    corrected = {"bias_map": bias_map} if bias_map else {}
    return {
        "envelope_adc": playback,
        "cell_sync": {"towers": towers, **frontend, **moving},
        "cell_timing": dict(frontend),
        "tdoa_fusion": {"towers": towers, **corrected, **moving},
        ONE_PROCESS: {**playback, "towers": towers, **corrected, **moving},
    }


def _end_of_a_required_node(event, context):
    """``on_exit`` of every DeepSync node: the chain cannot run without any of them. Another
    status than 0 while the launch runs is a failure: raised, launch logs it as one error line,
    stops every other node and exits 1. Status 0 ends the launch normally. While the launch is
    shutting down (Ctrl-C), the nodes' exits are expected."""
    if context.is_shutdown:
        return None
    name = event.process_name
    if event.returncode != 0:
        raise _refusal(f"{name} exited with status {event.returncode} (its last lines above say why); "
                       "the other nodes cannot run without it and are stopped")
    return [Shutdown(reason=f"{name} ended (status 0); the other nodes are stopped")]


def _refusal(message):
    """What to raise to start nothing: launch logs it as one error line (no traceback) and
    exits 1, where a Shutdown action would end the launch normally, with 0."""
    return RuntimeError("deepsync launch: " + message)


def _launch_setup(context):
    logger = get_logger("deepsync.launch")
    arg = context.launch_configurations
    try:
        use_sim_time = _as_bool("use_sim_time", arg["use_sim_time"])
        one_process = _as_bool("one_process", arg["one_process"])
        loop = _as_bool("loop", arg["loop"])
        realtime = _as_bool("realtime", arg["realtime"])
        antenna_tf = _as_bool("antenna_tf", arg["antenna_tf"])
        antenna = [_number(f"antenna_{axis}", arg[f"antenna_{axis}"]) for axis in "xyz"]
    except ValueError as error:
        raise _refusal(str(error)) from None
    if antenna_tf and not arg["base_frame"].strip():
        raise _refusal("base_frame:='' names no frame for the antenna's transform (or antenna_tf:=false)")
    source = arg["source"].strip()
    towers = arg["towers"].strip()
    bias_map = arg["bias_map"].strip()
    params_file = arg["params_file"].strip()
    extra_params_file = arg["extra_params_file"].strip()
    namespace = arg["namespace"].strip().strip("/")
    from_topic = source == TOPIC_SOURCE

    if from_topic and one_process:
        raise _refusal("source:=topic needs the four nodes (one_process:=false): the "
                       "deepsync_pipeline node reads its source itself")
    blind = towers == ""  # no tower database: cell search and timing only, no position
    if blind and not one_process:
        raise _refusal("towers:='' (a blind search, no position) needs one_process:=true: the "
                       "tdoa_fusion node needs a tower database")
    if blind and bias_map:
        raise _refusal("bias_map:=... corrects fusion's site ranges, and towers:='' runs no fusion")
    missing = [f"{name}:={path}" for name, path in
               (("source", source), ("towers", towers), ("bias_map", bias_map), ("params_file", params_file),
                ("extra_params_file", extra_params_file))
               if not (name == "source" and (from_topic or _is_address(path))) and not (name == "towers" and blind)
               and not (name in ("bias_map", "extra_params_file") and not path) and not os.path.exists(path)]
    if missing:
        raise _refusal("no such file or directory: " + ", ".join(missing))

    script, why = _node_script()
    if script is None:
        raise _refusal(why)
    try:
        command = _interpreter_command(script)
    except (OSError, ValueError) as error:
        raise _refusal(str(error)) from None
    ok, said = _check_dependencies(command, env=dict(os.environ))
    if not ok:
        raise _refusal(f"the nodes cannot run with {' '.join(command)} (the interpreter of "
                       f"{script}); nothing was started.\n{said}")
    logger.info(said or "deepsync_ros dependencies import")

    executables = (ONE_PROCESS,) if one_process else tuple(
        name for name in FOUR_NODES if not (from_topic and name == "envelope_adc"))
    prefix = "/" + namespace if namespace else ""
    unmatched = _unmatched_nodes(params_file, [f"{prefix}/{name}" for name in executables])
    if unmatched:
        logger.warning(f"{params_file} has no entry for {', '.join(unmatched)}: they run on their "
                       "defaults (write the keys as /**/<node name> to match any namespace)")

    overrides = _node_overrides(source, towers, bias_map, arg["motion"].strip(), realtime=realtime, loop=loop,
                                use_sim_time=use_sim_time)
    nodes = []
    for name in executables:
        parameters = [params_file, *([extra_params_file] if extra_params_file else []),
                      {"use_sim_time": use_sim_time, **overrides[name]}]
        placement = {"namespace": namespace} if namespace else {}
        nodes.append(Node(package=PACKAGE, executable=name, name=name, parameters=parameters,
                          output="screen", emulate_tty=True, on_exit=_end_of_a_required_node, **placement))
    if antenna_tf:
        base_frame = arg["base_frame"].strip()
        # the NavSatFix's frame (tdoa_fusion's antenna_frame default); rotation: none, the antenna is a point
        offsets = [text for axis, value in zip("xyz", antenna) for text in (f"--{axis}", repr(value))]
        nodes.append(Node(package="tf2_ros", executable="static_transform_publisher", name="deepsync_antenna_tf",
                          arguments=[*offsets, "--frame-id", base_frame, "--child-frame-id", ANTENNA_FRAME],
                          parameters=[{"use_sim_time": use_sim_time}], output="screen"))
    if from_topic:
        logger.info(f"source:=topic: no envelope_adc node; play a bag into {prefix}/envelope, e.g. "
                    "ros2 bag play bags/campus --clock")
    return nodes

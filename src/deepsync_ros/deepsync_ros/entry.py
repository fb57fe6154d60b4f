"""Console entry points of the five nodes (``ros2 run deepsync_ros <name>``).

Each checks the Python dependencies first (:mod:`deepsync_ros.dependencies`) and, when one is
missing, exits 1 with what to install instead of a traceback from deep inside an import; the
same for the ROS packages the nodes import (rclpy, diagnostic_updater, the message packages),
which only a sourced ROS 2 installation provides. Only then is the node's module imported.
"""

from __future__ import annotations

import importlib
import sys

from deepsync_ros import dependencies

# ROS packages a node module imports, and where a Jazzy user gets them
_ROS_PACKAGES = {
    "rclpy": "source /opt/ros/jazzy/setup.bash",
    "rcl_interfaces": "source /opt/ros/jazzy/setup.bash",
    "builtin_interfaces": "source /opt/ros/jazzy/setup.bash",
    "std_msgs": "source /opt/ros/jazzy/setup.bash",
    "geometry_msgs": "source /opt/ros/jazzy/setup.bash",
    "sensor_msgs": "source /opt/ros/jazzy/setup.bash",
    "rosgraph_msgs": "source /opt/ros/jazzy/setup.bash",
    "diagnostic_msgs": "source /opt/ros/jazzy/setup.bash",
    "diagnostic_updater": "sudo apt install ros-jazzy-diagnostic-updater",
    "deepsync_msgs": "build the workspace (colcon build) and source install/setup.bash",
}


def _run(program: str, module: str) -> None:
    dependencies.use_system_proj_data()  # before anything imports pyproj
    if not dependencies.report(program):
        sys.exit(1)
    try:
        node = importlib.import_module(f"deepsync_ros.{module}")
    except ModuleNotFoundError as error:
        package = (error.name or "").split(".")[0]
        if package not in _ROS_PACKAGES:
            raise
        print(f"[{program}] missing ROS package {package}: {_ROS_PACKAGES[package]}", file=sys.stderr)
        sys.exit(1)
    sys.exit(node.main())


def envelope_adc() -> None:
    _run("envelope_adc", "envelope_adc_node")


def cell_sync() -> None:
    _run("cell_sync", "cell_sync_node")


def cell_timing() -> None:
    _run("cell_timing", "cell_timing_node")


def tdoa_fusion() -> None:
    _run("tdoa_fusion", "tdoa_fusion_node")


def deepsync_pipeline() -> None:
    _run("deepsync_pipeline", "pipeline_node")

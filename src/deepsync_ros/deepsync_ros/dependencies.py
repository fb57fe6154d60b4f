"""Are the nodes' Python dependencies importable? One clear line per missing piece.

ROS 2 Jazzy on Ubuntu 24.04 runs the nodes on the interpreter their entry points name, with
the packages apt installed (NumPy 1.26, SciPy, PyYAML) plus what rosdep or pip added (rosbags,
mcap, pyproj, tqdm, ...). When one is missing, the user should read which, and how to get it,
not a traceback from deep inside an import. Every entry point and the launch file run
:func:`missing_dependencies` first; ``python -m deepsync_ros.dependencies`` runs it by hand.
Only the standard library is imported here, so the check itself cannot fail to import.
"""

from __future__ import annotations

import importlib
import importlib.metadata
import os
import sys

# module -> how a Jazzy user gets it (docs/ros.md, "1. Install")
REQUIRED = {
    "numpy": "sudo apt install python3-numpy  (Ubuntu 24.04 ships 1.26; the nodes need numpy < 2)",
    "scipy": "sudo apt install python3-scipy",
    "yaml": "sudo apt install python3-yaml",
    "pyproj": "sudo apt install python3-pyproj",
    "tqdm": "sudo apt install python3-tqdm",
    "matplotlib": "sudo apt install python3-matplotlib",
    "rosbags": "pip install 'rosbags>=0.11,<0.12'  (no apt package; see docs/ros.md, 1. Install)",
    "mcap": "pip install 'mcap>=1.1'",
    "sigmf": "pip install 'sigmf>=1.14'",
    "threadpoolctl": "sudo apt install python3-threadpoolctl",
    "deepsync": "build the workspace: colcon build, then source install/setup.bash",
    "deepsync_msgs.msg": "build the workspace (colcon build) and source install/setup.bash",
}


def use_system_proj_data() -> None:
    """Point pyproj at the system's PROJ data where it would not find it: apt's pyproj (which
    carries no data of its own) looks in ``sys.prefix``/share/proj, and in a venv made with
    ``--system-site-packages`` that is the venv, so every node would warn "Valid PROJ data
    directory not found". Nothing changes when ``PROJ_DATA``/``PROJ_LIB`` is set, outside a
    venv, or when the base Python has no ``proj.db`` (a pip pyproj brings its own)."""
    if "PROJ_DATA" in os.environ or "PROJ_LIB" in os.environ or sys.prefix == sys.base_prefix:
        return
    system_data = os.path.join(sys.base_prefix, "share", "proj")
    if os.path.isfile(os.path.join(system_data, "proj.db")):
        os.environ["PROJ_DATA"] = system_data


def missing_dependencies() -> list[str]:
    """One line per dependency that does not import (or is the wrong version); empty: all good."""
    problems = []
    for module, remedy in REQUIRED.items():
        try:
            importlib.import_module(module)
        except Exception as error:  # an ImportError, or a broken install raising anything
            problems.append(f"{module} does not import ({type(error).__name__}: {error}); {remedy}")
    try:
        major = int(importlib.metadata.version("numpy").split(".")[0])
    except importlib.metadata.PackageNotFoundError:
        major = None
    if major is not None and major >= 2:
        problems.append(f"numpy {importlib.metadata.version('numpy')} is installed, but ROS 2 Jazzy's rclpy and "
                        "message packages are built against numpy 1.x: pip install 'numpy<2'")
    return problems


def report(program: str) -> bool:
    """Print what is missing for ``program`` to stderr; True when nothing is."""
    problems = missing_dependencies()
    for line in problems:
        print(f"[{program}] missing dependency: {line}", file=sys.stderr)
    if problems:
        print(f"[{program}] Python: {sys.executable}. docs/ros.md ('1. Install') says how the nodes find "
              "their dependencies.", file=sys.stderr)
    return not problems


def main() -> int:
    use_system_proj_data()
    ok = report("deepsync_ros")
    if ok:
        print(f"deepsync_ros: every dependency imports with {sys.executable}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())

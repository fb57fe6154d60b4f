"""Debian's system Python, where the ROS tooling (rosidl, colcon-ros, catkin_pkg) is installed
by ``scripts/setup.sh``: tests run those tools in it and skip, with the reason, without it."""

from __future__ import annotations

import subprocess
from pathlib import Path

SYSTEM_PYTHON = "/usr/bin/python3"


def run_python(code: str, *args: str, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    """Run ``code`` in the system Python, capturing its text output."""
    return subprocess.run([SYSTEM_PYTHON, "-c", code, *args], check=False, capture_output=True,
                          text=True, timeout=timeout)


def missing(imports: str, install: str) -> str | None:
    """None if the system Python can run ``imports``, else why not (naming the apt packages)."""
    if not Path(SYSTEM_PYTHON).exists():
        return f"{SYSTEM_PYTHON} not found (apt install {install})"
    probe = run_python(imports)
    if probe.returncode != 0:
        last = probe.stderr.strip().splitlines()[-1:]
        return f"{SYSTEM_PYTHON} cannot run {imports!r} (apt install {install}): {last}"
    return None

"""The install and build commands the README and docs/ros.md give agree, and work as written
(issue #49: on a real Jazzy the README's sequence failed where pip's torch had brought setuptools
80+ into the venv: ``colcon build --symlink-install`` -> ``option --editable not recognized``)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
GUIDES = ("README.md", "docs/ros.md")
SYMLINK_BUILD = "colcon build --symlink-install"
PIN = re.compile(r"pip install .*['\"]?setuptools<80['\"]?")
TORCH = re.compile(r"pip install .*\btorch\b")


def _command_lines(name: str) -> list[str]:
    """The lines inside the guide's fenced code blocks, in order (comments stripped)."""
    lines, inside = [], False
    for line in (REPO / name).read_text().splitlines():
        if line.lstrip().startswith("```"):
            inside = not inside
        elif inside:
            lines.append(line.split("  #")[0].strip())
    return lines


@pytest.mark.parametrize("name", GUIDES)
def test_symlink_builds_come_after_the_setuptools_pin(name: str) -> None:
    lines = _command_lines(name)
    builds = [i for i, line in enumerate(lines) if SYMLINK_BUILD in line]
    assert builds, f"{name} shows no {SYMLINK_BUILD}"
    for build in builds:
        pins = [i for i in range(build) if PIN.search(lines[i])]
        assert pins, f"{name}: {lines[build]!r} without `pip install 'setuptools<80'` before it"
        torches = [i for i in range(build) if TORCH.search(lines[i])]
        assert not torches or max(pins) > max(torches), \
            f"{name}: the setuptools pin must come after the torch install, which upgrades setuptools"


def test_guides_build_the_same_way() -> None:
    """The same colcon command, the same venv, robot_localization installed by both routes."""
    builds = {name: {line for line in _command_lines(name) if "colcon build" in line} for name in GUIDES}
    assert all(any(line.startswith("python -m colcon build --symlink-install") for line in found)
               for found in builds.values()), builds
    for name in GUIDES:
        commands = "\n".join(_command_lines(name))
        assert "python3 -m venv --system-site-packages" in commands, name
        assert "ros-jazzy-robot-localization" in commands, f"{name} does not install robot_localization"
        assert "rosdep install --from-paths src --ignore-src -y" in (REPO / name).read_text(), name

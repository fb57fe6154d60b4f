#!/usr/bin/env bash
# Set up a fresh machine for DeepSync (idempotent): Debian tools that check the ROS side, and a
# virtual environment with the pinned Python dependencies. Needs Python 3.10+ and pip.
set -euo pipefail
cd "$(dirname "$0")/.."

VENV=.venv
STAMP=$VENV/.installed

# ROS 2 itself is not installable here; these Debian packages carry the same .msg parser,
# package.xml validator and colcon that a ROS build runs, so the tests can check those files.
DEBIAN_PACKAGES="python3-rosidl rosidl-tools colcon python3-colcon-ros python3-catkin-pkg"
missing=""
if command -v dpkg-query >/dev/null; then
  for p in $DEBIAN_PACKAGES; do
    dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing="$missing $p"
  done
fi
if [ -n "$missing" ]; then
  SUDO=""; [ "$(id -u)" -ne 0 ] && command -v sudo >/dev/null && SUDO="sudo"
  if [ "$(id -u)" -eq 0 ] || [ -n "$SUDO" ]; then
    echo "setup: installing Debian packages:$missing"
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq $missing >/dev/null
  else
    echo "setup: cannot install$missing (no root); the ROS-tooling tests will skip"
  fi
fi

PYTHON=${PYTHON:-python3}
if [ ! -f "$STAMP" ] || [ constraints.txt -nt "$STAMP" ] || [ src/deepsync/setup.py -nt "$STAMP" ] || [ src/deepsync_ros/setup.py -nt "$STAMP" ]; then
  echo "setup: creating $VENV with pinned dependencies"
  "$PYTHON" -m venv "$VENV"
  "$VENV/bin/python" -m pip install --quiet --disable-pip-version-check -c constraints.txt -e "src/deepsync[network,onnx,ray]" -e src/deepsync_ros pytest hypothesis
  touch "$VENV/COLCON_IGNORE" "$STAMP"  # keep colcon out of the venv's packages
fi

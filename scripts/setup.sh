#!/usr/bin/env bash
# Set up a fresh machine for DeepSync (idempotent): Debian tools that check the ROS side, and a
# virtual environment with the pinned Python dependencies. Needs Python 3.10+ and pip.
set -euo pipefail
cd "$(dirname "$0")/.."

VENV=.venv
STAMP=$VENV/.installed

# the optional Debian packages of the ROS-tooling tests: said, and skipped with a line when
# they cannot be installed (no root, the package lock held, no network)
scripts/debian_packages.sh

PYTHON=${PYTHON:-python3}
if [ ! -f "$STAMP" ] || [ constraints.txt -nt "$STAMP" ] || [ src/deepsync/setup.py -nt "$STAMP" ] || [ src/deepsync_ros/setup.py -nt "$STAMP" ]; then
  echo "setup: 1/2 creating the virtual environment $VENV ($("$PYTHON" --version 2>&1))"
  "$PYTHON" -m venv "$VENV"
  echo "setup: 2/2 installing the pinned Python dependencies of constraints.txt into $VENV: numpy, scipy,"
  echo "setup:     rosbags, matplotlib, torch (CPU), onnx, onnxruntime, ray, sionna-rt, pytest and their own;"
  echo "setup:     a few minutes and about 2 GB on a first run (one line per package below)"
  # pip's lines that say where it is, one per package; the end of its output when it fails
  log=$(mktemp)
  set +e
  "$VENV/bin/python" -m pip install --disable-pip-version-check -c constraints.txt \
    -e "src/deepsync[network,onnx,ray,raytrace]" -e src/deepsync_ros pytest hypothesis 2>&1 | tee "$log" \
    | grep --line-buffered -E "^(Collecting|Installing collected|Successfully installed)" | sed -u 's/^/setup:     /'
  status=${PIPESTATUS[0]}
  set -e
  if [ "$status" -ne 0 ]; then
    echo "setup: pip failed (exit $status); the end of its output:"
    tail -n 40 "$log"
    rm -f "$log"
    exit 1
  fi
  rm -f "$log"
  touch "$VENV/COLCON_IGNORE" "$STAMP"  # keep colcon out of the venv's packages
  echo "setup: done"
fi

#!/usr/bin/env bash
# The test suite: set up, then pytest (ROS-only tests skip, with the reason, without rclpy).
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh
exec .venv/bin/python -m pytest -q "$@"

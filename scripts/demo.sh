#!/usr/bin/env bash
# The main job on the bundled data, no ROS needed: set up, then `deepsync demo`.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh
exec .venv/bin/deepsync demo "$@"

#!/usr/bin/env bash
# Regenerate the route bags (not in git: ~0.3 GB each, and they follow from the scenario files
# and the simulator exactly): bags/generated/route_urban and route_dense, one pass of each walk;
# route_dense_reference, a fixed rooftop receiver hearing route_dense's sites for 60 s (the
# reference station the route table calibrates the site clocks with); and route_drive, a car at
# 15 m/s among route_dense's sites (benchmarks/fusion/stack_length.py). Extra arguments go to
# `deepsync simulate` (e.g. --workers 4).
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh

SECONDS_PER_ROUTE=96.4   # one pass of the walk: 135.0 m at 1.4 m/s (the receiver then stands still)
OUT=bags/generated
mkdir -p "$OUT"

REFERENCE_SECONDS=60     # a reference station's recording: long enough to measure drifts
DRIVE_SECONDS=21         # the drive: 315 m at 15 m/s, before its power swing outgrows the fixed gain

for route in route_urban route_dense route_dense_reference route_drive; do
  seconds=$SECONDS_PER_ROUTE
  [ "$route" = route_dense_reference ] && seconds=$REFERENCE_SECONDS
  [ "$route" = route_drive ] && seconds=$DRIVE_SECONDS
  start=$(date +%s)
  .venv/bin/deepsync simulate --scenario "config/scenarios/$route.yaml" --seconds "$seconds" \
    --out "$OUT/$route" --overwrite --quiet "$@"
  echo "route_bags: $OUT/$route in $(( $(date +%s) - start )) s wall, $(du -sh "$OUT/$route" | cut -f1)"
done

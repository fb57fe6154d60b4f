#!/usr/bin/env bash
# Regenerate the two full-length route bags (not in git: ~0.3 GB each, and they follow from the
# scenario files and the simulator exactly): bags/generated/route_urban and route_dense, one pass
# of each walk. Extra arguments go to `deepsync simulate` (e.g. --workers 4).
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh

SECONDS_PER_ROUTE=96.4   # one pass of the walk: 135.0 m at 1.4 m/s (the receiver then stands still)
OUT=bags/generated
mkdir -p "$OUT"

for route in route_urban route_dense; do
  start=$(date +%s)
  .venv/bin/deepsync simulate --scenario "config/scenarios/$route.yaml" --seconds "$SECONDS_PER_ROUTE" \
    --out "$OUT/$route" --overwrite --quiet "$@"
  echo "route_bags: $OUT/$route in $(( $(date +%s) - start )) s wall, $(du -sh "$OUT/$route" | cut -f1)"
done

#!/usr/bin/env bash
# One learning-curve point: sc3 diagnose's headline measures on the first 6 held-out episodes (EPISODES=24: all). ./diag.sh MODEL NAME [COPY]
set -euo pipefail
cd ~/sc3-runs/so101
. /work/main/.venv/bin/activate
/usr/bin/time -f "DIAG_WALL %e s" sc3 diagnose --world-model "$1" --data ~/sc3-runs/so101/heldout --episodes "${EPISODES:-6}" \
    --cf-starts 1 --max-seconds 8 --benchmark so101 --no-progress --out curve/$2.json
[ -n "${3:-}" ] && cp curve/$2.json "$3"

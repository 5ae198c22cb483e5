#!/usr/bin/env bash
# One learning-curve point of the SO-101 trunk: anneal a branch of its latest state over N steps, export it, and
# compare it with the dense, paired probe against a reference model on all 24 held-out episodes (the trunk paused
# throughout). ./branch_probe.sh N NAME [AGAINST]   (AGAINST: exports/so101_v7_cpu)
# Writes ~/sc3-runs/so101/branches/NAME (the export), docs/so101_curve/NAME_vs_REF.json and .md, wall times on stdout.
set -euo pipefail
N=$1; NAME=$2; AGAINST=${3:-exports/so101_v7_cpu}
REPO="$(cd "$(dirname "$0")/../.." && pwd)"
cd "$REPO"
. .venv/bin/activate
OUT=~/sc3-runs/so101/branches/$NAME
mkdir -p ~/sc3-runs/so101/branches
t0=$(date +%s)
scripts/with_trunk_paused sc3 trunk branch --trunk ~/sc3-runs/so101/trunk --steps "$N" --out "$OUT" \
    --workdir ~/sc3-runs/so101/branches/${NAME}_run --no-progress
t1=$(date +%s)
echo "BRANCH_WALL $((t1 - t0)) s"
scripts/with_trunk_paused sc3 diagnose --world-model "$OUT" --against "$AGAINST" --data ~/sc3-runs/so101/heldout \
    --episodes 24 --benchmark so101 --stages open_loop dense --max-seconds 8 --no-progress \
    --out docs/so101_curve/${NAME}_vs_$(basename "$AGAINST").json | tee docs/so101_curve/${NAME}_vs_$(basename "$AGAINST").md
t2=$(date +%s)
echo "PROBE_WALL $((t2 - t1)) s"

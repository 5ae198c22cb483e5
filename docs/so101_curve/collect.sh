#!/usr/bin/env bash
# SO-101 data for the world-model campaign (deterministic: seed 0 reproduces it every session)
set -euo pipefail
cd ~/sc3-runs/so101
. /work/main/.venv/bin/activate
sc3 so101 collect --out data --episodes 200 --heldout 24 --max-steps 100 --workers 2 --no-progress
sc3 data import-lerobot --data data/train --out train
sc3 data import-lerobot --data data/heldout --out heldout
echo COLLECT_DONE

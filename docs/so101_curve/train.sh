#!/usr/bin/env bash
# Superseded by scripts/trunk.sh (one WSD run with its optimizer state; docs/world_model.md, "The trunk"); kept for
# the records of the v3 -> v7 stretches. The SO-101 world-model campaign: one run continued across sessions. ./train.sh FROM WORKDIR STEPS SEED [WARMUP [FLAG...]]
# FLAG...: more `sc3 train` options, for a lever's arm (e.g. --flow.moving-weight 4; docs/so101.md, what is left)
# SEED: a new one each stretch, so a stretch does not redraw the previous stretch's windows in the same order.
# FROM: the newest float32 export (exports/so101_vN_cpu, params only: the optimizer's moments are not exported, so
# each stretch re-warms up briefly and decays to lr 0 at STEPS); rerunning with the same WORKDIR resumes it exactly.
# Stretches so far: v3 -> v4 (wm, 1100 steps, seed 0, warm-up 50; first launched with 1500, shortened at step 341),
# v4 -> v5 (wm2, seed 1), v5 -> v6 (wm3, 260 steps, seed 2; launched for 350, shortened at step 81), v6 -> v7
# (lev/base_a, 400 steps, seed 3, run with PYTHONPATH=~/sc3-runs/code: a frozen copy of the code): docs/results.md.
set -euo pipefail
FROM=$1; WORKDIR=$2; STEPS=$3; SEED=$4; WARMUP=${5:-30}
shift $(( $# < 5 ? $# : 5 ))
cd ~/sc3-runs/so101
. /work/main/.venv/bin/activate
exec sc3 train --config so101_latent --model.tokenizer-path "$FROM/tokenizer" --model.action-sum pose \
    --data ~/sc3-runs/so101/train --batch 12 --train.init-from "$FROM" --train.workdir "$WORKDIR" \
    --train.steps "$STEPS" --train.ckpt-every 50 --train.log-every 10 --train.no-progress --train.warmup-steps "$WARMUP" \
    --train.seed "$SEED" "$@"

#!/usr/bin/env bash
# Issue 64: act.sh's ACT trained on from its last checkpoint to STEPS in all (constant lr, no scheduler: a resumed
# run is the same run, longer), a checkpoint every 1000 steps. [RUN=...] ./resume.sh STEPS; then eval.sh 00STEPS
set -uo pipefail
export HF_HUB_OFFLINE=1 WANDB_MODE=disabled MUJOCO_GL=egl
B=~/sc3-runs/venv312/bin
RUN=${RUN:-so101_act}; OUT=~/sc3-runs/act/$RUN
echo "act resume start $(date)"
/usr/bin/time -f "WALL %e s" nice -n ${NICE:-0} $B/lerobot-train \
  --config_path=$OUT/checkpoints/last/pretrained_model/train_config.json --resume=true \
  --steps=$1 --save_freq=1000 > ~/sc3-runs/act/${RUN}_resume.log 2>&1
echo "act resume done $(date)"

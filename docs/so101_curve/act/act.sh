#!/usr/bin/env bash
# Issue 64: an ACT trained with the real lerobot-train on the collected SO-101 data's successful episodes (two
# cameras + state), a checkpoint every SAVE steps (the budgets; each one's real rate: RUN=... eval.sh STEP).
# Env: STEPS (5000), SAVE (1000), NICE (5), RUN (the run's folder under ~/sc3-runs/act, so101_act), ACT_ARGS (the
# optimizer, batch and size flags; default LeRobot's 52M ACT at lr 1e-4, batch 8). The run of 2026-12-06 (results.md):
# RUN=act_b32 NICE=0 STEPS=20000 SAVE=500 ACT_ARGS="--policy.optimizer_lr=2e-4 --policy.optimizer_lr_backbone=2e-4
#   --batch_size=32 --policy.dim_model=256 --policy.dim_feedforward=1024 --policy.n_encoder_layers=2", stopped by hand.
set -uo pipefail
# the collection's successful episodes (collect.sh's data/collect.json)
mkdir -p ~/sc3-runs/act
python3 -c "import json; e = json.load(open('$HOME/sc3-runs/so101/data/collect.json'))['splits']['train']['episodes']; print(','.join(str(x['episode_index']) for x in e if x['succeeded']))" > ~/sc3-runs/act/successes.txt
export HF_HUB_OFFLINE=1 WANDB_MODE=disabled MUJOCO_GL=egl
B=~/sc3-runs/venv312/bin
OUT=~/sc3-runs/act/${RUN:-so101_act}
echo "act start $(date)"
/usr/bin/time -f "WALL %e s" nice -n ${NICE:-5} $B/lerobot-train \
  --dataset.repo_id=local/so101 --dataset.root=$HOME/sc3-runs/so101/data/train --dataset.video_backend=pyav \
  --dataset.episodes="[$(cat ~/sc3-runs/act/successes.txt)]" \
  --policy.type=act --policy.device=cpu --policy.push_to_hub=false --policy.pretrained_backbone_weights=null \
  --policy.input_features='{"observation.state": {"type": "STATE", "shape": [14]}, "observation.images.workspace": {"type": "VISUAL", "shape": [3, 80, 80]}, "observation.images.wrist": {"type": "VISUAL", "shape": [3, 80, 80]}}' \
  --policy.chunk_size=10 --policy.n_action_steps=10 ${ACT_ARGS:---policy.optimizer_lr=1e-4 --policy.optimizer_lr_backbone=1e-4 --batch_size=8} \
  --num_workers=1 --steps=${STEPS:-5000} --save_freq=${SAVE:-1000} --log_freq=100 --seed=0 \
  --output_dir=$OUT --job_name=act_so101 > ~/sc3-runs/act/${RUN:-so101_act}.log 2>&1
echo "act done $(date)"
echo ACT_TRAIN_DONE

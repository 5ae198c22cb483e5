#!/usr/bin/env bash
# One ACT checkpoint's real rate: the real lerobot-eval in the SO-101 simulator on the sweep's conditions 0..35.
# ./eval.sh STEP  (RUN=: act.sh's run under ~/sc3-runs/act, default so101_act; NICE=: its priority, default 5)
set -uo pipefail
export HF_HUB_OFFLINE=1 WANDB_MODE=disabled MUJOCO_GL=egl
RUN=${RUN:-so101_act}
/usr/bin/time -f "WALL %e s" nice -n ${NICE:-5} ~/sc3-runs/venv312/bin/lerobot-eval \
  --policy.path=$HOME/sc3-runs/act/$RUN/checkpoints/$1/pretrained_model \
  --env.type=sc3_so101 --eval.n_episodes=36 --eval.batch_size=4 --seed=0 --policy.device=cpu \
  --output_dir=$HOME/sc3-runs/act/eval_${RUN}_$1 > ~/sc3-runs/act/eval_${RUN}_$1.log 2>&1
echo "EVAL_DONE $RUN $1 $(date)"

#!/usr/bin/env bash
# The SO-101 world-model campaign: one run, resumed exactly each session (rerunning this resumes the workdir).
# Start: exports/so101_v3_cpu (int8 params, the old displacement-from-zero pose) re-conditioned on the measured end
# effector (action_space.fit_measured), model.action_sum pose; 1100 steps at batch 12 ending at lr 0 (first launched with 1500, shortened at step 341 to end inside the session).
set -euo pipefail
cd ~/sc3-runs/so101
. /work/main/.venv/bin/activate
EX=/work/main/exports/so101_v3_cpu
exec sc3 train --config so101_latent --model.tokenizer-path $EX/tokenizer --model.action-sum pose \
    --data ~/sc3-runs/so101/train --batch 12 --train.init-from $EX --train.workdir ~/sc3-runs/so101/wm \
    --train.steps 1100 --train.ckpt-every 50 --train.log-every 10 --train.no-progress --train.warmup-steps 50

#!/usr/bin/env bash
# Rebuild the latent world model of the simulated benchmark (configs/bussing_latent.py) from nothing. Resumable:
# every step skips or resumes what exists. Wall times measured on the 2-core CPU machine in docs/world_model.md.
#   bash scripts/world_model.sh [RUNS_DIR] [EXTRA sc3 train ARGS...]
set -euo pipefail
R=${1:-runs/bussing}
shift || true
D=$R/demos
H=$R/heldout
# world-model data: the scripted expert on *bussing* only, with failure knobs (350 episodes, 3 views at 64x64, 20 Hz).
# No --wrong-destination-prob: no object of this data is ever carried to the other class's container.
[ -f $D/.done ] || {
  sc3 sim demos --out $D --episodes 160 --seed 10
  sc3 sim demos --out $D --episodes 80 --seed 11 --grasp-noise 0.04
  sc3 sim demos --out $D --episodes 60 --seed 12 --action-noise 0.012
  sc3 sim demos --out $D --episodes 50 --seed 13 --release-noise 0.08
  touch $D/.done; }
# held-out episodes for the tokenizer's and the world model's diagnostics (other seeds)
[ -f $H/.done ] || {
  sc3 sim demos --out $H --episodes 20 --seed 19
  sc3 sim demos --out $H --episodes 10 --seed 18 --grasp-noise 0.04
  touch $H/.done; }
# the learned latent tokenizer: 64x64 -> 16x16x16, ~0.74M parameters
sc3 train-tokenizer --data $D --heldout $H --workdir $R/tokenizer --steps 2200 --ae.width 96 --ae.mid-width 48 \
  --ae.out-width 24 --ae.blocks 1 --ae.latent-channels 16 --no-progress
# the world model on cached latents (the cache is built on the first run, in $R/latent_train/latents)
sc3 train --config bussing_latent --model.tokenizer-path $R/tokenizer/tokenizer --data $D \
  --train.workdir $R/latent_train --train.no-progress "$@"
# gate it on the held-out episodes
sc3 diagnose --world-model $R/latent_train --data $H --benchmark bussing --out $R/latent_train/diagnose.json \
  --sample-steps 8 --inverse-steps 8

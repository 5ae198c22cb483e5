#!/usr/bin/env bash
# Rebuild the shipped world model and perception scorer of the simulated benchmark from nothing (resumable: every
# step skips what exists). On the 2-core CPU machine: demos ~6 min, world model ~80 min
# (the shipped one was stopped at step 2,177 of 2,600 for time), scorer ~20 min + ~40 min.
#   bash scripts/bussing_sim.sh [RUNS_DIR]        then: sc3 sweep bench --world-model RUNS_DIR/train ...
set -euo pipefail
R=${1:-runs/bussing}
D=$R/demos
# world-model data: scripted expert on *bussing* only, a mixture of failure knobs (400 episodes, 3 views at 64x64)
sc3 sim demos --out $D --episodes 160 --seed 10
sc3 sim demos --out $D --episodes 80 --seed 11 --grasp-noise 0.04
sc3 sim demos --out $D --episodes 60 --seed 12 --action-noise 0.012
sc3 sim demos --out $D --episodes 50 --seed 13 --release-noise 0.08
sc3 sim demos --out $D --episodes 50 --seed 14 --wrong-destination-prob 0.4
# the world model (configs/bussing_sim.py); resumes from its latest checkpoint
sc3 train --config bussing_sim --data $D --train.workdir $R/train --train.no-progress
# the perception scorer: the same demos + 300 expert episodes of both tasks + 140 zoo-policy episodes on training
# seeds (a measuring instrument may see reverse bussing and the policies' behaviours; never the evaluation seeds)
sc3 train-perception --data $D $R/scorer_data $R/scorer_zoo --generate 300 --generate-policies 140 \
    --steps 3000 --out $R/perception.npz
# fine-tuned on 208 episodes of the current 13-policy zoo (seeds 7,000,000+), augmented with colour drift and patch
# noise (the shipped weights: docs/sweep.md#scorers names the exact stores they were fine-tuned on)
sc3 train-perception --data $R/scorer_data $R/scorer_zoo $R/scorer_zoo2 --generate-policies 208 \
    --policy-seed 70 --init $R/perception.npz --steps 3000 --lr 5e-4 --out $R/perception_ft.npz
# small copies to commit (params as float16)
python -c "from sc3_jax.model import checkpoint; checkpoint.export('$R/train', 'sc3_jax/benchmarks/bussing/shipped/bussing_sim')"
cp $R/perception_ft.npz sc3_jax/benchmarks/bussing/perception.npz

#!/usr/bin/env bash
# The paper's training ablations at an equal budget on the CPU: the full recipe (configs/bussing_latent.py)
# and its four ablations, each trained from scratch for STEPS steps (the same schedule squeezed into STEPS: warm-up,
# then cosine decay to 0 at STEPS) on the demos, tokenizer and latent cache of scripts/world_model.sh, exported and
# gated by `sc3 diagnose` on its held-out episodes. Resumable: a finished variant is skipped, a stopped one resumes
# from its last checkpoint. Run scripts/world_model.sh RUNS_DIR first (it builds what this reads), or at least its
# demos and heldout steps, with the shipped tokenizer copied to RUNS_DIR/tokenizer/tokenizer (docs/results.md).
#   bash scripts/ablations.sh RUNS_DIR STEPS [VARIANT ...]
#     variants (default: all, in this order): full, forward_only, no_id, no_cvi, no_decouple, and full_seed1 = the
#     full recipe with another initialisation, noise and data-order seed: the run-to-run spread that a difference
#     between two variants has to exceed (each figure comes from one run, so the table has no intervals)
#   sc3 diagnose-table --world-model RUNS_DIR/ablations_STEPS/*/export --baseline full   the table (docs/results.md)
set -euo pipefail
R=$1 STEPS=$2
shift 2
variants=${*:-full forward_only no_id no_cvi no_decouple full_seed1}
A=$R/ablations_$STEPS
# the variants share one latent cache; the first variant encodes it when scripts/world_model.sh has not
mkdir -p $R/latent_train/latents
for v in $variants; do
  W=$A/$v
  case $v in
    full) config=bussing_latent extra="" ;;
    full_seed1) config=bussing_latent extra="--train.seed 1 --data.seed 1" ;;
    *) config=ablation_$v:bussing_latent extra="" ;;
  esac
  mkdir -p $W
  # the latents depend on the tokenizer and the demos only: share the main run's cache instead of encoding again
  [ -e $W/latents ] || ln -s "$(cd $R/latent_train && pwd)/latents" $W/latents
  [ -f $W/export/params.npz ] || {
    sc3 train --config $config --model.tokenizer-path $R/tokenizer/tokenizer --data $R/demos \
      --train.workdir $W --train.steps $STEPS --train.no-progress $extra
    # a trainer stopped by SIGTERM saves and exits cleanly: export only a run that reached its budget
    last=$(ls $W/checkpoints | grep -E '^[0-9]+$' | sort -n | tail -1)
    [ "$last" = "$STEPS" ] || { echo "$v stopped at step $last of $STEPS: rerun to resume" >&2; exit 1; }
    python -c "import numpy as np; from sc3_jax.model import checkpoint; checkpoint.export('$W', '$W/export', np.float16)"; }
  [ -f $W/export/diagnose.json ] || sc3 diagnose --world-model $W/export --data $R/heldout --episodes 4 --no-progress \
    --benchmark bussing --sample-steps 8 --inverse-steps 8 \
    --out $W/export/diagnose.json > $W/diagnose.md
done

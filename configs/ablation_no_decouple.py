"""Ablation: no horizon decoupling, the model predicts only the frames it keeps (l' = l = 16 at paper scale; for
another base, l' is set to that base's l). ``:BASE`` picks another base config.

Its measured form is ``:bussing_latent`` at the equal budget of ``scripts/ablations.sh`` (1,000 steps from scratch
on the demos, tokenizer and latent cache of ``scripts/world_model.sh``, exported and diagnosed):

    bash scripts/ablations.sh RUNS 1000 full no_decouple            # or by hand, per variant:
    sc3 train --config ablation_no_decouple:bussing_latent --model.tokenizer-path RUNS/tokenizer/tokenizer \
        --data RUNS/demos --train.workdir RUNS/ablations_1000/no_decouple --train.steps 1000
    sc3 diagnose-table --world-model RUNS/ablations_1000/*/export --baseline full

Measured (docs/results.md, "Training ablations at an equal budget"; 28 min of training on the 2 cores, 0.59 steps/s
against the full recipe's 0.47; the full recipe's two seeds differ by at most 0.14 dB): the one ablation that
clearly hurts: against the full recipe, teacher-forced moving pixels -0.33 dB over copy-last, wrist -0.46 dB,
true - shuffled actions -0.36 dB, open loop at 4 s -0.36 dB, the counterfactual direction 0.78 against 0.89; 4 gates
fail (+1). At equal steps it had ~20% less compute; whether equal wall time closes the gap is not measured. Closed
loop not measured (it needs an accelerator: ``CONFIG=ablation_no_decouple:bussing_latent_gpu TRAIN=no_decouple bash
scripts/gpu_world_model.sh train RUN``, docs/world_model.md)."""
from sc3_jax.core.config import load_config, replace


def get_config(arg: str | None = None):
    cfg = load_config(arg or "paper")
    keep = cfg.rollout.keep_frames
    return replace(cfg, name=f"{cfg.name}-no_decouple", data=dict(future_frames=keep))

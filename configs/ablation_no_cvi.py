"""Ablation: no cross-view inpainting (FD and ID keep the base's ratio, 8:1 for ``paper``). ``:BASE`` picks another
base config.

Its measured form is ``:bussing_latent`` at the equal budget of ``scripts/ablations.sh`` (1,000 steps from scratch
on the demos, tokenizer and latent cache of ``scripts/world_model.sh``, exported and diagnosed):

    bash scripts/ablations.sh RUNS 1000 full no_cvi            # or by hand, per variant:
    sc3 train --config ablation_no_cvi:bussing_latent --model.tokenizer-path RUNS/tokenizer/tokenizer \
        --data RUNS/demos --train.workdir RUNS/ablations_1000/no_cvi --train.steps 1000
    sc3 diagnose-table --world-model RUNS/ablations_1000/*/export --baseline full

Measured (docs/results.md, "Training ablations at an equal budget"; 36 min of training on the 2 cores; the full
recipe's two seeds differ by at most 0.14 dB): no effect seen: against the full recipe 4 of 5 video columns are
within the spread (-0.09 to +0.01 dB), open loop at 4 s +0.25 dB, inverse dynamics 0.23 of the floor's error (full:
0.24), outcome reproduction 0.25 (equal); 4 gates fail (+1). Every diagnostic conditions on all three real views, so
what inpainting buys (re-rendering a view from the others) cannot show there. Closed loop not measured (it needs an
accelerator: ``CONFIG=ablation_no_cvi:bussing_latent_gpu TRAIN=no_cvi bash scripts/gpu_world_model.sh train RUN``,
docs/world_model.md)."""
from sc3_jax.model import modes
from sc3_jax.core.config import load_config, replace


def get_config(arg: str | None = None):
    cfg = load_config(arg or "paper")
    return replace(cfg, name=f"{cfg.name}-no_cvi", modes=dict(probs=modes.without(cfg.modes.probs, modes.CVI)))

"""Baseline: forward dynamics only (the Cosmos-Predict-style action-conditioned model of the paper's ablations): no
cross-view inpainting, no inverse dynamics, so no U_chunk and no early termination (sweep it with ``--taus inf``).
``--config ablation_forward_only`` is paper scale; ``--config ablation_forward_only:NAME`` applies it to NAME.

Its measured form is ``:bussing_latent`` at the equal budget of ``scripts/ablations.sh`` (1,000 steps from scratch
on the demos, tokenizer and latent cache of ``scripts/world_model.sh``, exported and diagnosed):

    bash scripts/ablations.sh RUNS 1000 full forward_only            # or by hand, per variant:
    sc3 train --config ablation_forward_only:bussing_latent --model.tokenizer-path RUNS/tokenizer/tokenizer \
        --data RUNS/demos --train.workdir RUNS/ablations_1000/forward_only --train.steps 1000
    sc3 diagnose-table --world-model RUNS/ablations_1000/*/export --baseline full

Measured (docs/results.md, "Training ablations at an equal budget"; 44 min of training on the 2 cores; the full
recipe's two seeds differ by at most 0.14 dB): ahead of the full recipe on every video diagnostic at this budget:
teacher-forced moving pixels +0.24 dB over copy-last and +0.39 dB over the temporal median, wrist +0.34 dB,
true - shuffled actions +0.31 dB, open loop at 4 s +0.59 dB; the same counterfactual direction (0.88) and outcome
reproduction (0.25); no inverse dynamics trained; 3 gates fail, as the full recipe's. The lead comes from dropping
inverse dynamics, not inpainting (``ablation_no_id`` is within 0.07 dB of it). Closed loop not measured (it needs an
accelerator: ``CONFIG=ablation_forward_only:bussing_latent_gpu TRAIN=forward_only bash scripts/gpu_world_model.sh
train RUN``, docs/world_model.md)."""
from sc3_jax.model import modes
from sc3_jax.core.config import load_config, replace


def get_config(arg: str | None = None):
    cfg = load_config(arg or "paper")
    probs = modes.without(cfg.modes.probs, modes.CVI, modes.ID)
    return replace(cfg, name=f"{cfg.name}-forward_only", modes=dict(probs=probs))

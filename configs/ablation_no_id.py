"""Ablation: no inverse dynamics (FD and CVI keep the base's ratio, 8:1 for ``paper``). ``--config ablation_no_id``
is paper scale; ``--config ablation_no_id:tiny`` applies it to another named config.

Its measured form is ``:bussing_latent`` at the equal budget of ``scripts/ablations.sh`` (1,000 steps from scratch
on the demos, tokenizer and latent cache of ``scripts/world_model.sh``, exported and diagnosed):

    bash scripts/ablations.sh RUNS 1000 full no_id            # or by hand, per variant:
    sc3 train --config ablation_no_id:bussing_latent --model.tokenizer-path RUNS/tokenizer/tokenizer \
        --data RUNS/demos --train.workdir RUNS/ablations_1000/no_id --train.steps 1000
    sc3 diagnose-table --world-model RUNS/ablations_1000/*/export --baseline full

Measured (docs/results.md, "Training ablations at an equal budget"; 35 min of training on the 2 cores; the full
recipe's two seeds differ by at most 0.14 dB): against the full recipe, teacher-forced moving pixels +0.23 dB over
copy-last and +0.32 dB over the temporal median, true - shuffled actions +0.23 dB, open loop at 4 s +0.54 dB: better
frames, within 0.07 dB of forward only on every column; but no inverse dynamics, so no U_chunk and no early stop;
outcome reproduction 0.17 (-0.08, the seeds' spread); 3 gates fail, as the full recipe's. Closed loop not measured
(it needs an accelerator: ``CONFIG=ablation_no_id:bussing_latent_gpu TRAIN=no_id bash scripts/gpu_world_model.sh
train RUN``, docs/world_model.md)."""
from sc3_jax.model import modes
from sc3_jax.core.config import load_config, replace


def get_config(arg: str | None = None):
    cfg = load_config(arg or "paper")
    return replace(cfg, name=f"{cfg.name}-no_id", modes=dict(probs=modes.without(cfg.modes.probs, modes.ID)))

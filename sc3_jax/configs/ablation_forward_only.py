"""Baseline: forward dynamics only (the Cosmos-Predict-style action-conditioned model of the paper's ablations): no
cross-view inpainting, no inverse dynamics, so no U_chunk and no early termination (sweep it with ``--taus inf``).
``--config ablation_forward_only`` is paper scale; ``--config ablation_forward_only:NAME`` applies it to NAME."""
from sc3_jax import modes
from sc3_jax.config import load_config, replace


def get_config(arg: str | None = None):
    cfg = load_config(arg or "paper")
    probs = modes.without(cfg.modes.probs, modes.CVI, modes.ID)
    return replace(cfg, name=f"{cfg.name}-forward_only", modes=dict(probs=probs))

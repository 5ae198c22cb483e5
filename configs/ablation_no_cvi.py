"""Ablation: no cross-view inpainting (FD and ID keep their 8:1 ratio). ``:BASE`` picks another base config."""
from sc3_jax.config import load_config, replace


def get_config(arg: str | None = None):
    cfg = load_config(arg or "paper")
    return replace(cfg, name=f"{cfg.name}-no_cvi", modes=dict(probs=(8 / 9, 0.0, 1 / 9)))

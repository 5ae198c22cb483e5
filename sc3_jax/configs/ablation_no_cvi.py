"""Ablation: no cross-view inpainting (FD and ID keep the base's ratio, 8:1 for ``paper``). ``:BASE`` picks another
base config."""
from sc3_jax import modes
from sc3_jax.config import load_config, replace


def get_config(arg: str | None = None):
    cfg = load_config(arg or "paper")
    return replace(cfg, name=f"{cfg.name}-no_cvi", modes=dict(probs=modes.without(cfg.modes.probs, modes.CVI)))

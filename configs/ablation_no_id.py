"""Ablation: no inverse dynamics (FD and CVI keep their 8:1 ratio). ``--config ablation_no_id`` is paper scale;
``--config ablation_no_id:tiny`` applies it to another named config."""
from sc3_jax.config import load_config, replace


def get_config(arg: str | None = None):
    cfg = load_config(arg or "paper")
    return replace(cfg, name=f"{cfg.name}-no_id", modes=dict(probs=(8 / 9, 1 / 9, 0.0)))

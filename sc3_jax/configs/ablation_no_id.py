"""Ablation: no inverse dynamics (FD and CVI keep the base's ratio, 8:1 for ``paper``). ``--config ablation_no_id``
is paper scale; ``--config ablation_no_id:tiny`` applies it to another named config."""
from sc3_jax import modes
from sc3_jax.config import load_config, replace


def get_config(arg: str | None = None):
    cfg = load_config(arg or "paper")
    return replace(cfg, name=f"{cfg.name}-no_id", modes=dict(probs=modes.without(cfg.modes.probs, modes.ID)))

"""Ablation: no horizon decoupling, the model predicts only the frames it keeps (l' = l = 16 at paper scale; for
another base, l' is set to that base's l). ``:BASE`` picks another base config."""
from sc3_jax.config import load_config, replace


def get_config(arg: str | None = None):
    cfg = load_config(arg or "paper")
    keep = cfg.rollout.keep_frames
    return replace(cfg, name=f"{cfg.name}-no_decouple", data=dict(future_frames=keep))

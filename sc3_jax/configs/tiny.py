"""Tiny CPU config: trains on the synthetic environment in minutes (tests, `sc3 demo`). Uses the small-model
shortcuts (ModelConfig.anchor_conditioning / action_to_frames / action_reads_frames), residual prediction, noise
levels biased to high t and balanced video/action losses: what made a 1.4M-parameter model learn in CPU-minutes."""
from sc3_jax.config import Config, DataConfig, FlowConfig, ModeConfig, ModelConfig, RolloutConfig, TrainConfig

SHORTCUTS = dict(anchor_conditioning=True, action_to_frames=True, action_reads_frames=True)


def get_config(arg: str | None = None) -> Config:
    return Config(name="tiny",
                  # 12 tokens a frame: 8-px patches on the synthetic data's three 16x16 views; on a lab's two
                  # 96x128 cameras the patch grows to 32 (24 tokens a frame), not the tokens to 384 (sizing.py)
                  model=ModelConfig(patch_size=8, frame_tokens=12, **SHORTCUTS),
                  data=DataConfig(batch_size=32),
                  # ID gets a larger share than the paper's 0.1 so every mode learns within a CPU-minutes budget
                  # (inverse dynamics sees 0.8 samples per step at batch 8 otherwise); `paper` keeps 0.8/0.1/0.1.
                  modes=ModeConfig(probs=(0.6, 0.1, 0.3)),
                  flow=FlowConfig(t_logit_mean=1.0, video_loss_weight=10.0),
                  train=TrainConfig(lr=3e-3, warmup_steps=50, steps=1500),
                  rollout=RolloutConfig(keep_frames=3))

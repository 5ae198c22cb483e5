"""CPU-medium (~16M params, 3 x 32x32 views, 8x8 patches): a model whose dense layers dominate its FLOPs, the regime
a train step should run near matmul speed in (bench/train_step.py)."""
from sc3_jax.config import Config, DataConfig, ModelConfig, TrainConfig


def get_config(arg: str | None = None) -> Config:
    return Config(
        name="cpu_medium",
        model=ModelConfig(dim=512, depth=4, num_heads=8, num_kv_heads=4, head_dim=64, mlp_dim=1536,
                          rope_axes_dim=(12, 10, 10), patch_size=8,
                          anchor_conditioning=True, action_to_frames=True, action_reads_frames=True),
        data=DataConfig(image_size=(32, 32), context_frames=2, future_frames=4, batch_size=8),
        train=TrainConfig(workdir="runs/cpu_medium"),
    )

"""A CPU-medium model (~12M params, 32x32 views): big enough that matmuls dominate, for benchmarks."""
from sc3_jax.config import Config, DataConfig, ModelConfig, TrainConfig


def get_config(arg: str | None = None) -> Config:
    return Config(
        name="cpu_medium",
        model=ModelConfig(dim=384, depth=6, num_heads=6, num_kv_heads=2, head_dim=64, mlp_dim=1152,
                          rope_axes_dim=(12, 10, 10), patch_size=4,
                          anchor_conditioning=True, action_to_frames=True, action_reads_frames=True),
        data=DataConfig(image_size=(32, 32), context_frames=2, future_frames=4, batch_size=8),
        train=TrainConfig(workdir="runs/cpu_medium"),
    )

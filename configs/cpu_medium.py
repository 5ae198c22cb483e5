"""CPU-medium (~16M params, 3 x 32x32 views, 8x8 patches): a model whose dense layers dominate its FLOPs, the regime
a train step should run near matmul speed in (bench/train_step.py).

    python bench/train_step.py --configs tiny cpu_medium      # a train step's FLOP/s against a matmul's
    sc3 demo --out runs/demo                                  # synthetic episodes in runs/demo/episodes, then:
    sc3 train --config cpu_medium --data runs/demo/episodes --train.workdir runs/cpu_medium

Measured (docs/results.md, "Component measurements"; 292 tokens a sample at batch 8, 16M parameters in its table,
18.8M by `sc3 configs`): a train step at 0.47 of a matmul's FLOP/s, 1,713 tokens/s on the 2-core machine;
`sc3 plan`'s lowered FLOP count is within 0.25% of XLA's compiled one here (docs/plan.md). Expected: a benchmark
config, never trained to a measured quality; check a run of it as any: `sc3 diagnose --world-model RUN --data HELDOUT` should read
the moving pixels above copy-last and true actions above shuffled ones."""
from sc3_jax.core.config import Config, DataConfig, ModelConfig, TrainConfig


def get_config(arg: str | None = None) -> Config:
    return Config(
        name="cpu_medium",
        model=ModelConfig(dim=512, depth=4, num_heads=8, num_kv_heads=4, head_dim=64, mlp_dim=1536,
                          rope_axes_dim=(12, 10, 10), patch_size=8,
                          anchor_conditioning=True, action_to_frames=True, action_reads_frames=True),
        data=DataConfig(image_size=(32, 32), context_frames=2, future_frames=4, batch_size=8),
        train=TrainConfig(workdir="runs/cpu_medium"),
    )

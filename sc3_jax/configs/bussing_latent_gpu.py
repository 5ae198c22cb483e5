"""``bussing_latent`` at accelerator scale: the same recipe (latent tokenizer, pose conditioning, context noise,
l' = 10 / l = 8, multi-FPS windows, pseudo-actions) in a 5x larger model (dim 384, 8 layers: 23.8M parameters,
21.5 MB as an int8 export, the form the repository ships) with bfloat16 matmuls and 64-window batches.

``train.steps`` 15,000 x 64 = ~10^6 windows (against ~3.5 x 10^4 for the CPU run of ``bussing_latent``), ~45 minutes
at the 5-6 steps/s measured on one H100 (``scripts/gpu_world_model.sh``: demos from 16 MuJoCo processes, then
training; a checkpoint every 1,000 steps, so a run cut short by the device's time still exports). It also runs on a
CPU, slowly."""
from sc3_jax.config import load_config, replace


def get_config(arg: str | None = None):
    cfg = load_config("bussing_latent")
    return replace(
        cfg, name="bussing_latent_gpu",
        model=dict(dim=384, depth=8, num_heads=6, num_kv_heads=2, head_dim=64, mlp_dim=1536, rope_axes_dim=(12, 10, 10),
                   dtype="bfloat16"),
        data=dict(batch_size=64, read_threads=12),
        train=dict(workdir="runs/bussing_latent_gpu/train", lr=1e-3, warmup_steps=300, steps=15000, ckpt_every=1000,
                   keep_checkpoints=2, progress=False))

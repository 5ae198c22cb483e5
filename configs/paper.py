"""Paper scale (SC3-Eval on a Cosmos3-Nano-sized backbone, ~2B parameters): 3 views at 480x640, 20 Hz with a 10 Hz
subsample, l' = 24 predicted / l = 16 kept frames, policy chunk 25, AdamW 1e-4 / wd 0.05 / betas (0.9, 0.99),
2,000 warm-up steps then cosine to 24,000 steps, global batch 512, modes (0.8, 0.1, 0.1), pseudo-actions p = 0.5.

It uses 32x32 pixel patches (15 x 20 tokens per frame), not the Wan VAE (``model.tokenizer='wan2.2'``, see
docs/wan_vae.md); `sc3 plan` / `jax.eval_shape` report its size without allocating it.

    sc3 plan --config paper --mesh data=4,fsdp=8 --device gb200 --no-chunk       # anywhere: nothing is allocated
    sc3 train --config paper --mesh.data 1 --mesh.fsdp 8 --data STORE --train.workdir CKPT    # one 8-GPU node
    python launch/multihost.py ... -- train --config paper --data STORE ...      # several hosts: launch/README.md

Expected, from `sc3 plan` (its output: docs/plan.md, "Paper scale ... next to the paper"): 2,030,756,871 parameters,
25,224 tokens a sample, 5.4e17 FLOPs a step: 16.9 s a step at MFU 0.4, 4.69 days for the 24,000 steps on 32 GB200 (the
paper: 7.9 s and 2.2 days, on Wan latents); as configured it does not fit (1,736 GB of activations a device,
estimated), and fits with `--model.attention-impl fused --model.remat none --train.grad-accum 16` (117 GB of 186). One
closed-loop chunk at 4 of its 32 layers: 4.05 s on one H200, 32.4 s scaled to full depth against the paper's 2.3 s on
one GB200 (docs/results.md, "Accelerator"). Never trained here: no faithfulness measured; `sc3 plan`'s verdict line is
the check."""
from sc3_jax.core.config import Config, DataConfig, MeshConfig, ModelConfig, RolloutConfig, TrainConfig


def get_config(arg: str | None = None) -> Config:
    return Config(
        name="paper",
        model=ModelConfig(dim=2048, depth=32, num_heads=16, num_kv_heads=8, head_dim=128, mlp_dim=8192,
                          rope_axes_dim=(24, 20, 20), patch_size=32, dtype="bfloat16", remat=True,
                          prediction="velocity", context_attention="causal"),
        data=DataConfig(image_size=(480, 640), context_frames=4, future_frames=24, batch_size=512),
        train=TrainConfig(workdir="runs/paper", steps=24_000, warmup_steps=2_000, lr=1e-4, ckpt_every=1000),
        mesh=MeshConfig(data=-1, fsdp=8, tensor=1),
        rollout=RolloutConfig(policy_chunk=25, keep_frames=16, tau=0.02),
    )

"""A bimanual ALOHA-like robot on Wan VAE latents, at the paper's scale: 4 cameras (cam_high, cam_low,
cam_left_wrist, cam_right_wrist) at 480x640, 14-D absolute joint-target actions (6 joints + gripper per arm; the
imagined state a policy observes in a rollout is the last target, 14-D too), 50 Hz data.

Tokens: the Wan2.2 VAE (16x space, 4x time, 48 latent channels) with 2x2 latent patches as Cosmos3 does: 15 x 20 =
300 tokens per token frame. A window of 5 context + 24 future frames is 2 + 6 token frames per view: 4 x 8 x 300
video tokens + 24 actions = 9,624 tokens per sample. ``aloha_wan:wan2.1`` takes the Wan2.1 VAE instead (8x space, 16
channels, same 2x2 patches: 1,200 tokens per token frame, 4x the sequence). Time-compressed tokens carry 4 actions per
token frame, which needs the Cosmos3 layout; a learned per-view embedding tells the 4 views apart (the layout's
positions do not). Backbone, optimiser and budget as ``paper`` (~2B parameters, 24,000 steps at global batch 512),
with the memory settings `sc3 plan` finds for 16 H100 (docs/plan.md, "A bimanual robot on Wan latents"): the fused
(cuDNN) attention kernel, no remat, 32 micro-batches (one sample per device at a time).

``model.tokenizer_path`` is where the pretrained VAE is expected (a diffusers AutoencoderKLWan directory: the ``vae/``
folder of Wan-AI/Wan2.2-TI2V-5B-Diffusers, or of a Wan2.1 pipeline for ``:wan2.1``): a real run needs it (random VAE
weights make meaningless latents); `sc3 plan` plans the preset's architecture where it is absent and never reads the
weights. `--data STORE` (a `sc3 data import-lerobot` output) makes `sc3 train` / `sc3 plan` read views, image
size and action dimension from its dataset.json; absolute actions have no pseudo-actions (data.pseudo_action_prob
0).

    sc3 plan --config aloha_wan --mesh data=2,fsdp=8 --device h100                 # anywhere: nothing is allocated
    sc3 train --config aloha_wan --data STORE --model.tokenizer-path VAE --train.workdir CKPT   # on the pod

Expected, from `sc3 plan` at MFU 0.4 (its output: docs/plan.md, "A bimanual robot on Wan latents"): 2,018,988,238
parameters, 9,624 tokens a sample; fits 16 H100 at 47.96 GB a device; 9.7e16 FLOPs a step plus 6.4e16 for the VAE
encode inside it: 15.4 s a step (at least 10.1 s more for the VAE), 4.27 days for 24,000 steps; one rollout chunk
1.2e15 FLOPs, 3.1 s on one H100. ``:wan2.1``: 38,424 tokens, fits only with remat dots (45.6 days). Never trained:
no quality measured; `sc3 plan`'s verdict line is the check."""
from sc3_jax.core.config import Config, DataConfig, MeshConfig, ModelConfig, RolloutConfig, TrainConfig

VIEWS = ("cam_high", "cam_low", "cam_left_wrist", "cam_right_wrist")


def get_config(arg: str | None = None) -> Config:
    vae = arg or "wan2.2"
    if vae not in ("wan2.1", "wan2.2"):
        raise ValueError(f"aloha_wan:{arg}: the argument names the VAE, wan2.1 or wan2.2")
    return Config(
        name="aloha_wan" if vae == "wan2.2" else f"aloha_wan:{vae}",
        model=ModelConfig(dim=2048, depth=32, num_heads=16, num_kv_heads=8, head_dim=128, mlp_dim=8192,
                          rope_axes_dim=(24, 20, 20), tokenizer=vae, tokenizer_path=f"runs/aloha/{vae}_vae",
                          patch_size=2, layout="cosmos3", num_views=len(VIEWS), action_dim=14, fps=50.0,
                          prediction="velocity",
                          context_attention="causal", dtype="bfloat16", attention_impl="fused", remat="none"),
        data=DataConfig(path="runs/aloha/episodes", views=VIEWS, image_size=(480, 640), context_frames=5,
                        future_frames=24, strides=(2, 5), pseudo_action_prob=0.0, batch_size=512),
        train=TrainConfig(workdir="runs/aloha_wan", steps=24_000, warmup_steps=2_000, lr=1e-4, ckpt_every=1000,
                          grad_accum=32),
        mesh=MeshConfig(data=-1, fsdp=8, tensor=1),
        # rollout.tau left to its default: a threshold in the raw units of 14 joint targets is calibrated on
        # held-out conditions, not borrowed from the benchmark's end-effector deltas
        rollout=RolloutConfig(policy_chunk=25, keep_frames=16),
    )

"""``bussing_latent`` at accelerator scale: the same recipe (latent tokenizer, pose conditioning, context noise,
l' = 10 / l = 8, multi-FPS windows, pseudo-actions) in a 5x larger model (dim 384, 8 layers: 23.8M parameters,
21.5 MB as an int8 export, the form the repository ships) with bfloat16 matmuls and 64-window batches.

``train.steps`` 15,000 x 64 = ~10^6 windows (against ~3.5 x 10^4 for the CPU run of ``bussing_latent``), ~45 minutes
at the 5-6 steps/s measured on one H100 (``scripts/gpu_world_model.sh``: demos from 16 MuJoCo processes, then
training; a checkpoint every 1,000 steps, so a run cut short by the device's time still exports). It also runs on a
CPU, slowly.

On one GPU machine (docs/world_model.md, "Accelerator run"; the shipped tokenizer is the default):

    bash scripts/gpu_world_model.sh data /tmp/wm 120     # demos from 16 MuJoCo processes for 120 s
    bash scripts/gpu_world_model.sh train /tmp/wm        # sc3 train --config bussing_latent_gpu --data /tmp/wm/demos
    bash scripts/gpu_world_model.sh export /tmp/wm OUT int8
    sc3 diagnose --world-model EXPORT --data HELDOUT --benchmark bussing --sample-steps 8 --out DIAG.json
    sc3 sweep bench --world-model EXPORT

Expected (docs/results.md, "The first accelerator run"): step 2,000 (128k windows) in about 9 min on one H100; its
diagnose reads moving pixels +6.76 dB over copy-last, +4.21 dB over the temporal median, true - shuffled actions +4.75
dB, inverse dynamics 0.045 against the floor's 1.47, offline outcome reproduction 0.67 with the shipped scorer (gate
0.75: fails by one object of 12). Online on the full protocol (docs/results.md, "Faithfulness against training
compute"): in distribution r 0.849 [0.759, 0.892], MMRV 0.208 [0.156, 0.320] against the policy-blind floor's 0.701 /
0.410. The shipped model, fine-tuned 1,500 more steps on failure-rich data, reads r 0.916 [0.873, 0.937], MMRV 0.153
[0.100, 0.192] in distribution at 72 conditions a policy (docs/results.md, "The shipped world model at 72
conditions")."""
from sc3_jax.core.config import load_config, replace


def get_config(arg: str | None = None):
    cfg = load_config("bussing_latent")
    return replace(
        cfg, name="bussing_latent_gpu",
        model=dict(dim=384, depth=8, num_heads=6, num_kv_heads=2, head_dim=64, mlp_dim=1536, rope_axes_dim=(12, 10, 10),
                   dtype="bfloat16"),
        data=dict(batch_size=64, read_threads=12),
        train=dict(workdir="runs/bussing_latent_gpu/train", lr=1e-3, warmup_steps=300, steps=15000, ckpt_every=1000,
                   keep_checkpoints=2, progress=False))

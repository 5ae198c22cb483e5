"""The world model of the simulated table-bussing benchmark on learned latents (the recipe of docs/world_model.md).

Against ``bussing_sim`` (16-px pixel patches, linear read-out): frames are encoded by the convolutional autoencoder
of ``sc3 train-tokenizer`` (64x64 -> 16x16x16 latents, 4x4 latent patches: still 16 tokens per view and frame) and
decoded by its CNN decoder, so thin arms stay drawable; every frame is conditioned on the absolute end-effector
pose integrated from the commanded actions (``model.pose_conditioning``); the context is noised in training with
its level given to the model (``model.context_noise``, anti-drift) and lightly at inference; the model predicts
l' = 10 frames and a rollout keeps l = 8 (the paper's horizon decoupling), from multi-FPS windows (strides 1-3 of
the 20 Hz data; rollouts run at stride 2 = 10 Hz) with pseudo-actions half of the time.

``--model.tokenizer-path`` names the trained tokenizer; the default is the one shipped with the exported model
(``sc3_jax/benchmarks/bussing/shipped/bussing_latent_gpu/tokenizer``; ``configs/bussing_latent_gpu.py`` is this recipe
at accelerator scale), and scripts/world_model.sh passes the one it trains.

From nothing on the 2-core machine (``bash scripts/world_model.sh RUNS`` makes the demos, the held-out episodes and
the tokenizer, then runs these; resumable):

    sc3 train --config bussing_latent --model.tokenizer-path RUNS/tokenizer/tokenizer --data RUNS/demos \
        --train.workdir RUNS/latent_train
    sc3 diagnose --world-model RUNS/latent_train --data RUNS/heldout --benchmark bussing --sample-steps 8 \
        --out RUNS/latent_train/diagnose.json
    sc3 sweep bench --world-model EXPORT          # an export of the run (docs/results.md has the commands)

Expected (docs/results.md, "The CPU latent run, checkpoint by checkpoint"): 4.9M parameters, the latent cache ~4 min,
then 0.43-0.5 steps/s on the 2 cores; at step 4,906 (3.8 training hours, 59k windows) diagnose reads moving pixels
+5.74 dB over copy-last, +2.76 dB over the temporal median (gate 3), true - shuffled actions +3.40 dB, offline outcome
reproduction 0.33 (gate 0.75): 2 of 5 gates fail. Online on the full protocol (docs/results.md, "Faithfulness against
training compute"): in distribution r 0.726 [0.631, 0.801], MMRV 0.317 [0.270, 0.413] against the policy-blind floor's
0.701 / 0.410. Expected: at a CPU budget it does not rank policies clearly better than a guess; its accelerator twin
``bussing_latent_gpu`` does."""
from pathlib import Path

import sc3_jax
from sc3_jax.benchmarks.bussing.hooks import BENCHMARK_TAU
from sc3_jax.core.config import (Config, DataConfig, FlowConfig, ModeConfig, ModelConfig, RolloutConfig, SampleConfig,
                            TrainConfig)

SHIPPED_TOKENIZER = Path(sc3_jax.__file__).parent / "benchmarks/bussing/shipped/bussing_latent_gpu/tokenizer"


def get_config(arg: str | None = None) -> Config:
    return Config(
        name="bussing_latent",
        model=ModelConfig(dim=192, depth=4, num_heads=4, num_kv_heads=2, head_dim=48, mlp_dim=576,
                          rope_axes_dim=(8, 8, 8), tokenizer="conv_ae", tokenizer_path=str(SHIPPED_TOKENIZER),
                          patch_size=4, anchor_conditioning=True, action_to_frames=True, action_reads_frames=True,
                          pose_conditioning=True, context_noise=True),
        data=DataConfig(path="runs/bussing/demos", image_size=(64, 64), context_frames=2, future_frames=10,
                        strides=(1, 2, 2, 3), batch_size=12, fps=20.0),
        modes=ModeConfig(probs=(0.7, 0.1, 0.2)),
        flow=FlowConfig(t_logit_mean=1.0, video_loss_weight=10.0, context_noise_max=0.3),
        train=TrainConfig(workdir="runs/bussing_latent/train", lr=1.5e-3, warmup_steps=150, steps=6000,
                          ckpt_every=250, log_every=25),
        sample=SampleConfig(steps=8, context_noise=0.02),
        rollout=RolloutConfig(policy_chunk=25, keep_frames=8, episode_seconds=20.0, control_hz=10.0, policy_hz=20.0,
                              tau=BENCHMARK_TAU),
    )

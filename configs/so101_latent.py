"""The SO-101 benchmark's world model (sc3_jax/benchmarks/so101, docs/so101.md): ``bussing_latent``'s recipe on the
two cameras a lab mounts (``workspace`` from the side, ``wrist`` on the gripper; 80 x 80) at the arm's 10 Hz, trained
from the collected LeRobot data like any lab's.

80 x 80 frames -> a conv autoencoder's 20 x 20 x 16 latents -> 4 x 4 patches: 25 tokens a view, 50 a frame, as many
as the one 96 x 128 room view had (``model.frame_tokens`` 48: sizing.py picks the patch). The model predicts l' = 12
frames and a rollout keeps l = 10, as the simulator executes the zoo's 10-action chunks; the 2 frames past a chunk
are predicted with its last action held and discarded (``rollout.fill_chunk``). Rollouts last the task's 10 s. The
store records the 14-D joint state, so ``sc3 train`` trains the learned state after the world model
(``state_head.py``): policies inside the model read the robot's own state.

From nothing, on the 2-core machine (each step resumes what exists but the collection; the tokenizer trains on the
store's two cameras):

    sc3 so101 collect --out ~/sc3-runs/so101/data --episodes 150 --heldout 24 --max-steps 100 --workers 2
    sc3 data import-lerobot --data ~/sc3-runs/so101/data/train --out ~/sc3-runs/so101/train
    sc3 data import-lerobot --data ~/sc3-runs/so101/data/heldout --out ~/sc3-runs/so101/heldout
    sc3 train-tokenizer --data ~/sc3-runs/so101/train --heldout ~/sc3-runs/so101/heldout \
        --workdir ~/sc3-runs/so101/tokenizer --steps 1500 --batch 16 --ae.width 96 --ae.mid-width 48 \
        --ae.out-width 24 --ae.blocks 1 --ae.latent-channels 16
    sc3 train --config so101_latent --model.tokenizer-path ~/sc3-runs/so101/tokenizer/tokenizer \
        --data ~/sc3-runs/so101/train --train.workdir ~/sc3-runs/so101/world_model
    sc3 diagnose --world-model ~/sc3-runs/so101/world_model --data ~/sc3-runs/so101/heldout --benchmark so101 --out DIAG.json
    sc3 sweep so101 --world-model ~/sc3-runs/so101/world_model \
        --scorer sc3_jax.benchmarks.so101.scorer:block_at_goal --out ~/sc3-runs/so101/sweep

Expected (docs/results.md, "SO-101: data, zoo and scorer on a lab's cameras"): collection 15 min (2 workers beside
other work), the tokenizer 18 min (held-out moving pixels 29.3 dB workspace, 33.4 dB wrist, against 8.3 / 10.9 for the
static frame); a world-model step ~2.5 s on the 2 cores alone (155 GFLOP). At the CPU's few thousand steps the
imagined world still fades (the first camera's model kept 0.35 of the objects at 4 s after 2,200 steps); the GPU
playbook's SO-101 phase trains it on.
"""
from sc3_jax.core.config import load_config, replace


def get_config(arg: str | None = None):
    cfg = load_config("bussing_latent")
    return replace(
        cfg, name="so101_latent",
        # 48 tokens a frame wanted over the views (the bussing model's budget): 4x4 latent patches on two 80x80
        # cameras give 50
        # action_sum "pose": the shortcut adds where the commands moved the gripper (metres, from the measured
        # state), not a running sum of normalised velocities that drifts by the mean every frame
        model=dict(tokenizer_path="runs/so101/tokenizer/tokenizer", num_views=2, frame_tokens=48, action_sum="pose"),
        data=dict(path="runs/so101/train", views=("workspace", "wrist"), image_size=(80, 80), context_frames=2,
                  future_frames=12, strides=(1, 1, 2)),
        train=dict(workdir="runs/so101/world_model", steps=6000),
        # the task's horizon: 90% of the collection's successes end by 9 s, plus a chunk (`sc3 so101 collect` prints it)
        rollout=dict(policy_chunk=10, keep_frames=10, episode_seconds=10.0, control_hz=10.0, policy_hz=10.0))

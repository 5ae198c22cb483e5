"""LeRobot 0.6.1 for real (marked ``lerobot``; skipped where lerobot >= 0.6.1 is not importable: it needs Python >=
3.12, .ci/run's last section makes that environment): a LeRobot ACT trained here for a few steps on the tiny bimanual
robot's own episodes (test_any_robot.py), then the real ``lerobot-eval`` command through plugins/lerobot_env_sc3
inside the world model trained on the same data. Its eval_info.json holds the episodes and videos, and the same
conditions through ``sc3 sweep episodes`` (the ACT loaded in-process with LeRobot's own processors) give the same
outcomes."""
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from lerobot_required import require

pytestmark = pytest.mark.lerobot
require()

from sc3_jax.cli import main  # noqa: E402
from test_any_robot import A, CAMS, bimanual  # noqa: E402, F401  (the fixture: imported store + trained tiny model)
from test_ic_sweep import _conditions  # noqa: E402

TESTS = Path(__file__).resolve().parent
STEPS = 3  # the fixture model's rollout.keep_frames: the ACT's n_action_steps, one world-model call per inference
ACT_DIR: list[Path] = []  # the trained pretrained_model, for the in-process sweep policy below


def _train_act(store, out: Path, steps: int = 3) -> Path:
    """A tiny LeRobot ACT, ``steps`` AdamW steps on the store's frames, states and next actions; saved as
    lerobot-train saves one (config, weights, pre/post processors with the data's statistics)."""
    import torch
    from lerobot.configs.types import FeatureType, NormalizationMode, PolicyFeature
    from lerobot.policies.act.configuration_act import ACTConfig
    from lerobot.policies.act.modeling_act import ACTPolicy
    from lerobot.policies.factory import make_pre_post_processors

    torch.manual_seed(0)
    eps = [store.load(e) for e in store.episode_ids()]
    images = {c: np.concatenate([np.asarray(ep.frames[c]) for ep in eps]) for c in CAMS}  # [T, H, W, 3]
    state = np.concatenate([ep.state for ep in eps]).astype(np.float32)
    action = np.concatenate([ep.actions for ep in eps]).astype(np.float32)
    H, W = images[CAMS[0]].shape[1:3]
    keys = [f"observation.images.{c}" for c in CAMS]
    cfg = ACTConfig(input_features={"observation.state": PolicyFeature(FeatureType.STATE, (A,)),
                                    **{k: PolicyFeature(FeatureType.VISUAL, (3, H, W)) for k in keys}},
                    output_features={"action": PolicyFeature(FeatureType.ACTION, (A,))},
                    chunk_size=STEPS, n_action_steps=STEPS, dim_model=32, dim_feedforward=64, n_heads=2,
                    n_encoder_layers=1, n_decoder_layers=1, n_vae_encoder_layers=1, latent_dim=8,
                    pretrained_backbone_weights=None, device="cpu",  # no hub download at run time
                    normalization_mapping={"VISUAL": NormalizationMode.MEAN_STD, "STATE": NormalizationMode.MEAN_STD,
                                           "ACTION": NormalizationMode.MEAN_STD})
    unit = {c: images[c].reshape(-1, 3) / 255.0 for c in CAMS}
    stats = {"observation.state": {"mean": state.mean(0), "std": state.std(0) + 1e-3},
             "action": {"mean": action.mean(0), "std": action.std(0) + 1e-3},
             **{f"observation.images.{c}": {"mean": unit[c].mean(0).reshape(3, 1, 1).astype(np.float32),
                                            "std": unit[c].std(0).reshape(3, 1, 1).astype(np.float32) + 1e-3}
                for c in CAMS}}
    policy = ACTPolicy(cfg)
    pre, post = make_pre_post_processors(cfg, dataset_stats=stats)
    opt = torch.optim.AdamW(policy.parameters(), lr=1e-3)
    rng = np.random.default_rng(0)
    T = len(state)
    for _ in range(steps):
        t = rng.integers(0, T - STEPS, 4)
        idx = t[:, None] + np.arange(STEPS)
        batch = {"observation.state": torch.from_numpy(state[t]),
                 "action": torch.from_numpy(action[idx]), "action_is_pad": torch.zeros(4, STEPS, dtype=torch.bool),
                 **{f"observation.images.{c}": torch.from_numpy(images[c][t]).permute(0, 3, 1, 2).float() / 255
                    for c in CAMS}}
        loss, _ = policy.forward(pre(batch))
        opt.zero_grad()
        loss.backward()
        opt.step()
    for part in (policy, pre, post):
        part.save_pretrained(out)
    return out


class InProcessACT:
    """The trained ACT as a HostPolicy for ``sc3 sweep episodes``, loaded in this process (torch on CPU beside JAX)
    and fed exactly as lerobot-eval feeds it: LeRobot's preprocess_observation, its saved processors, select_action
    popping n_action_steps actions from one inference."""

    def __init__(self, path: Path):
        import torch
        from lerobot.configs.policies import PreTrainedConfig
        from lerobot.policies.act.modeling_act import ACTPolicy
        from lerobot.policies.factory import make_pre_post_processors

        cfg = PreTrainedConfig.from_pretrained(path)
        cfg.pretrained_path = path
        self.policy = ACTPolicy.from_pretrained(path, config=cfg).eval()
        self.pre, self.post = make_pre_post_processors(cfg, pretrained_path=str(path))
        self.torch, self.chunk, self.action_dim = torch, STEPS, A

    def infer(self, obs):
        from lerobot.envs.utils import preprocess_observation

        raw = {"pixels": {c: np.asarray(obs["images"])[j][None] for j, c in enumerate(CAMS)},
               "agent_pos": np.asarray(obs["state"], np.float32)[None]}
        batch = self.pre({**preprocess_observation(raw), "task": ["fold the towel"]})
        self.policy.reset()
        out = []
        with self.torch.inference_mode():
            for _ in range(STEPS):
                out.append(self.post(self.policy.select_action(batch)).cpu().numpy()[0])
        return np.stack(out).astype(np.float32)


def act():
    return InProcessACT(ACT_DIR[0])


def score(view):
    """Moved up on average; each imagined state trajectory is also kept (SC3_SCORED=DIR, in lerobot-eval's process)
    so the test compares trajectories, not only a bit."""
    if os.environ.get("SC3_SCORED"):
        np.save(Path(os.environ["SC3_SCORED"]) / f"{view.id}.npy", view.state)
    moved = float(np.mean(view.state[-1] - view.state[0]))
    return {"success": moved > 0.0}


def test_lerobot_eval_runs_an_act_inside_the_world_model_as_the_sweep_does(bimanual, tmp_path):  # noqa: F811
    store, cfg = bimanual[4], bimanual[5]
    run = cfg.train.workdir
    ic = _conditions(store, tmp_path / "heldout")
    ACT_DIR[:] = [_train_act(store, tmp_path / "act" / "pretrained_model")]
    out = tmp_path / "eval"
    exe = Path(sys.executable).with_name("lerobot-eval")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(TESTS), os.environ.get("PYTHONPATH", "")]),
           "HF_HUB_OFFLINE": "1", "SC3_SCORED": str(tmp_path)}
    cmd = [str(exe), "--env.type=sc3", f"--env.world_model={run}", f"--env.initial_conditions={ic}",
           "--env.scorer=test_lerobot_eval:score", "--env.episode_seconds=0.6", f"--env.action_steps={STEPS}",
           f"--policy.path={ACT_DIR[0]}", "--policy.device=cpu", "--eval.n_episodes=2", "--eval.batch_size=2",
           "--seed=0", f"--output_dir={out}"]
    done = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stderr[-3000:]
    info = json.loads((out / "eval_info.json").read_text())
    task = info["per_task"][0]
    assert (task["task_group"], task["task_id"]) == ("sc3", 0) and info["overall"]["n_episodes"] == 2
    successes = task["metrics"]["successes"]
    assert len(successes) == 2 and all(isinstance(s, bool) for s in successes)
    videos = info["overall"]["video_paths"]
    assert len(videos) == 2 and all(Path(v).stat().st_size > 0 for v in videos)

    sweep = tmp_path / "sweep"
    assert main(["sweep", "episodes", "--data", str(ic), "--world-model", str(run), "--policies",
                 "act=test_lerobot_eval:act", "--scorer", "test_lerobot_eval:score", "--episodes", "2",
                 "--calibration-episodes", "0", "--batch", "2", "--episode-seconds", "0.6", "--taus", "inf",
                 "--out", str(sweep), "--no-progress"]) == 0
    from sc3_jax.evaluation.results import ResultsStore

    store = ResultsStore(sweep)
    recs = {r["seed"]: r for r in store.records()}
    assert [recs[i]["outcomes"]["success"] for i in range(2)] == successes
    for i in range(2):  # the imagined robot state, step by step (torch batch 2 there, 1 here: float noise only)
        seen = np.load(tmp_path / f"{recs[i]['episode']}.npy")
        np.testing.assert_allclose(seen[1:], store.load_arrays(recs[i]["id"])["states"], atol=1e-4)

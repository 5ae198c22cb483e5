"""`lerobot:PATH`: a LeRobot policy (its pretrained_model directory) acts in a world model, run by lerobot in-process
where lerobot 0.6 sits beside sc3_jax (.ci/run's Python 3.12 environment), else in its own environment through
`policies/lerobot_child.py` (SC3_LEROBOT_PYTHON=VENV/bin/python). The test that trains a tiny ACT with lerobot and
rolls it out needs one of the two; without either it is skipped, and the one-line errors are still checked."""
import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from sc3_jax.cli import main
from sc3_jax.core.errors import UserError
from sc3_jax.policies.lerobot_policy import PYTHON_ENV, LeRobotPolicy
from sc3_jax.policies.resolve import resolve
from test_any_robot import CAMS, A, H, W, bimanual  # noqa: F401  (the fixture: imported store + trained tiny model)

TINY_ACT = Path(__file__).parent / "tiny_act_lerobot.py"  # run by the lerobot environment's python
CHUNK = 8  # the bimanual fixture model's rollout.policy_chunk


def _lerobot_python() -> str | None:
    """The Python that has lerobot: SC3_LEROBOT_PYTHON's (the child), else this one if it has it (in-process)."""
    py = os.environ.get(PYTHON_ENV)
    if not py:
        return sys.executable if importlib.util.find_spec("lerobot") is not None else None
    ok = subprocess.run([py, "-c", "import lerobot"], capture_output=True).returncode == 0
    return py if ok else None


def _config(path: Path, chunk: int = 5, action: int = 4, state: int = 14) -> Path:
    path.mkdir(parents=True, exist_ok=True)
    (path / "config.json").write_text(json.dumps({
        "type": "act", "n_action_steps": chunk, "output_features": {"action": {"type": "ACTION", "shape": [action]}},
        "input_features": {"observation.state": {"type": "STATE", "shape": [state]}}}))
    return path


def test_the_spelling_reads_chunk_and_dimensions_from_config_json_without_lerobot(tmp_path):
    r = resolve(f"act=lerobot:{_config(tmp_path / 'pm')}")
    assert r.name == "act" and isinstance(r.policy, LeRobotPolicy)
    assert (r.policy.chunk, r.policy.action_dim, r.policy.state_dim) == (5, 4, 14)


def test_a_directory_that_is_no_pretrained_model_is_one_line(tmp_path):
    with pytest.raises(UserError) as e:
        resolve(f"lerobot:{tmp_path}")
    assert "no config.json" in str(e.value) and "\n" not in str(e.value)
    (tmp_path / "config.json").write_text("{}")
    with pytest.raises(UserError) as e:
        resolve(f"lerobot:{tmp_path}")
    assert "not a LeRobot policy config" in str(e.value)


@pytest.mark.skipif(importlib.util.find_spec("lerobot") is not None, reason="lerobot is installed here")
def test_a_python_without_lerobot_is_one_line_naming_the_variable(tmp_path, monkeypatch):
    monkeypatch.setenv(PYTHON_ENV, sys.executable)  # ours: no lerobot
    p = LeRobotPolicy(_config(tmp_path / "pm"))
    with pytest.raises(UserError) as e:
        p.infer({"images": np.zeros((1, 8, 8, 3), np.uint8), "state": np.zeros(14, np.float32)})
    msg = str(e.value)
    assert "lerobot" in msg and PYTHON_ENV in msg and "\n" not in msg
    p.close()


@pytest.mark.lerobot
@pytest.mark.skipif(_lerobot_python() is None, reason=f"no lerobot here and no environment with it ({PYTHON_ENV})")
def test_a_lerobot_act_trained_here_acts_inside_a_world_model(bimanual, tmp_path, monkeypatch):  # noqa: F811
    """A tiny ACT (4 cameras, 14-D state and actions, chunk 8) trained 3 steps by lerobot, then `sc3 rollout
    --policy lerobot:DIR` on the bimanual world model: the rollout's first actions are (within what the observation
    differs: the context frame against the first imagined one) what lerobot's own inference answers, not the state
    a holding policy would send. In-process where this Python has lerobot 0.6 and SC3_LEROBOT_PYTHON is unset."""
    py = _lerobot_python()
    env = {**os.environ, "HF_HUB_OFFLINE": "1"}
    pm = tmp_path / "pretrained_model"
    subprocess.run([py, str(TINY_ACT), str(pm), "--views", str(len(CAMS)), "--image", str(H), str(W),
                    "--state-dim", str(A), "--action-dim", str(A), "--chunk", str(CHUNK), "--steps", "3"],
                   check=True, env=env, capture_output=True)
    if py != sys.executable:
        monkeypatch.setenv(PYTHON_ENV, py)
    assert LeRobotPolicy(pm).in_process == (py == sys.executable and not os.environ.get(PYTHON_ENV))
    tmp, store = bimanual[0], bimanual[4]
    out = tmp_path / "ro"
    assert main(["rollout", "--world-model", str(tmp / "run"), "--policy", f"act=lerobot:{pm}", "--data",
                 str(store.root), "--out", str(out), "--episodes", "2", "--batch", "2",
                 "--rollout.episode-seconds", "0.6", "--no-progress"]) == 0
    with np.load(out / "rollout.npz") as z:
        actions, frames, states = z["actions"], z["frames"], z["states"]
    assert actions.shape == (2, 6, A) and np.isfinite(actions).all()
    p = LeRobotPolicy(pm)
    try:  # near what the policy saw first: the first imagined frame of every view and state
        first = p.infer({"images": frames[0, :, 0], "state": states[0, 0]})
    finally:
        p.close()
    np.testing.assert_allclose(actions[0, :3], first[:3], atol=0.02)
    ep = store.load(store.episode_ids()[0])  # a holding policy would send the initial condition's recorded state
    assert min(np.abs(actions[0, 0] - st).max() for st in ep.state[:4]) > 0.05

"""An SO-101-like lab, end to end with documented flags only: a LeRobot v3.0 dataset of one camera, 4-D actions
(end-effector deltas dx, dy, dz in [-1, 1] and an absolute gripper command) and a 14-D ``observation.state`` (5 joint
positions, 5 joint velocities, the gripper, the end-effector xyz) is imported as velocity actions with a target
(training and held-out episodes of one dataset), trained on with no mode or shape flag (one view: no cross-view
inpainting; the state: the learned state head), and three 4-D policies that refuse anything but the robot's 14-D
state are ranked inside the world model from the held-out episodes, against real labels (r and MMRV)."""
import csv
import json

import numpy as np
import pytest

from sc3_jax.cli import main

pytestmark = pytest.mark.slow  # two minutes on 2 cores: a world model and its learned state trained, a sweep

FPS, H, W, LENGTH, SCALE = 10, 24, 32, 24, 0.02  # SCALE: metres per unit of a commanded delta
GOAL = np.array([0.08, -0.06, 0.02])
NAMES = [f"joint{i}.pos" for i in range(5)] + [f"joint{i}.vel" for i in range(5)] + ["gripper", "x", "y", "z"]


def _joints(p):
    """A smooth, non-linear stand-in for the arm's inverse kinematics: 5 joint angles of the hand at ``p``."""
    x, y, z = p
    return np.array([np.arctan2(y, x + 0.3), np.sin(3 * x) + z, np.cos(4 * y) * (0.2 + z), 5 * x * y, np.tanh(z - x)])


def _frame(p, grip) -> np.ndarray:
    img = np.full((H, W, 3), 40, np.uint8)
    r, c = int(np.clip(12 + 60 * p[1], 1, H - 2)), int(np.clip(16 + 60 * p[0], 1, W - 2))
    img[r - 1:r + 2, c - 1:c + 2] = (255, int(120 + 2000 * p[2]) % 256, int(255 * grip))
    return img


def _episode(rng, gain: float):
    """A controller moving the hand toward GOAL at ``gain``, with noise; the robot follows its commands."""
    from sc3_jax.data.lerobot_write import RawEpisode

    p, grip, q_prev = rng.uniform(-0.05, 0.05, 3), 1.0, None
    frames, actions, states = [], [], []
    for t in range(LENGTH):
        q = _joints(p)
        states.append(np.concatenate([q, np.zeros(5) if q_prev is None else (q - q_prev) * FPS, [grip], p]))
        frames.append(_frame(p, grip))
        d = np.clip(gain * (GOAL - p) / SCALE / 4 + rng.normal(0, 0.15, 3), -1, 1)
        cmd = 0.0 if np.linalg.norm(GOAL - p) < 0.03 else 1.0
        actions.append([*d, cmd])
        p, q_prev, grip = p + SCALE * d, q, grip + 0.5 * (cmd - grip)
    return RawEpisode({"observation.images.front": np.stack(frames)}, np.asarray(actions, np.float32), "pick",
                      np.asarray(states, np.float32))


# -- the policies and the scorer the sweep names as test_so101_workflow:ATTR ----------------------------------------
class Reach:
    chunk, action_dim, state_dim = 8, 4, 14  # the robot's state, as every LeRobot policy reads observation.state

    def __init__(self, gain: float):
        self.gain = gain

    def infer(self, obs):
        s = np.asarray(obs["state"], np.float32)
        if s.shape != (14,):
            raise ValueError(f"this policy reads the robot's 14-D observation.state, got {list(s.shape)}")
        d = np.clip(self.gain * (GOAL - s[11:14]) / SCALE / 4, -1, 1)
        return np.repeat(np.array([[*d, 1.0]], np.float32), self.chunk, 0)


def still():
    return Reach(0.0)


def slow():
    return Reach(0.4)


def fast():
    return Reach(1.5)


def near_goal(view):
    """Success: the hand (the state's last three entries) ends nearer the goal than half its start distance."""
    assert view.state.shape[1] == 14, view.state.shape
    start, end = (np.linalg.norm(GOAL - view.state[i, 11:14]) for i in (0, -1))
    return {"success": bool(end < 0.5 * start)}


REAL = {"still": 0.0, "slow": 0.5, "fast": 1.0}  # real success rates of the three, 4 labelled episodes each


@pytest.fixture(scope="module")
def lab(tmp_path_factory):
    pytest.importorskip("av", reason="LeRobot support needs the [lerobot] extra (PyAV)")
    from sc3_jax.data.lerobot_write import write_lerobot

    tmp = tmp_path_factory.mktemp("so101")
    rng = np.random.default_rng(0)
    eps = [_episode(rng, g) for g in (0.3, 0.8, 1.5) * 4]  # episodes 0-8 to train on, 9-11 held out
    write_lerobot(tmp / "lerobot", eps, FPS, version="v3.0", names={"action": ["dx", "dy", "dz", "gripper"],
                                                                   "observation.state": NAMES},
                  robot_type="so101_follower")
    importing = ["data", "import-lerobot", "--data", str(tmp / "lerobot"), "--action-space", "velocity",
                 "--action-targets", "3"]
    assert main(importing + ["--out", str(tmp / "train"), "--episodes", "0:9"]) == 0
    assert main(importing + ["--out", str(tmp / "heldout"), "--episodes", "9:"]) == 0
    small = ["--model.dim", "32", "--model.depth", "1", "--model.num-heads", "2", "--model.num-kv-heads", "1",
             "--model.mlp-dim", "64", "--batch", "8", "--train.steps", "2", "--train.no-progress",
             "--train.no-tensorboard", "--rollout.policy-chunk", "8"]  # widths and budget: not mode or shape flags
    assert main(["train", "--config", "tiny", "--data", str(tmp / "train"), "--train.workdir", str(tmp / "run"),
                 *small]) == 0
    with open(tmp / "real.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["policy", "success"])
        for policy, rate in REAL.items():
            w.writerows([policy, int(i < 4 * rate)] for i in range(4))
    return tmp


def _sweep(tmp, out, *extra, policies=("still", "slow", "fast")):
    return main(["sweep", "episodes", "--data", str(tmp / "heldout"), "--world-model", str(tmp / "run"),
                 "--policies", *[f"{p}=test_so101_workflow:{p}" for p in policies],
                 "--scorer", "test_so101_workflow:near_goal", "--real", str(tmp / "real.csv"), "--episodes", "3",
                 "--calibration-episodes", "0", "--batch", "3", "--episode-seconds", "1.8", "--out", str(out),
                 "--no-progress", *extra])


def test_an_so101_like_robot_goes_from_its_lerobot_data_to_a_report(lab, capsys):
    from sc3_jax.data.episodes import EpisodeStore

    store = EpisodeStore(lab / "train")
    assert store.views == ["front"] and store.state_dim == 14 and store.action_space.kind == "velocity"
    assert len(store.episode_ids()) == 9 and len(EpisodeStore(lab / "heldout").episode_ids()) == 3
    with np.load(lab / "run" / "state_head.npz") as z:  # the store records a state: the learned state was trained
        held = json.loads(str(z["meta"]))["heldout"]
    assert held["head"] < 0.5 * held["hold"], held  # on a held-out episode, unrolled from its first state
    assert _sweep(lab, lab / "sweep") == 0
    t = json.loads((lab / "sweep" / "report" / "report.json").read_text())
    f = t["real"]["faithfulness"]["online"]
    assert f["points"] == 3 and {"value", "lo", "hi"} <= set(f["pearson"]) and {"value", "lo", "hi"} <= set(f["mmrv"])
    z = np.load(lab / "sweep" / "rollouts" / "fast" / "0_online.npz")
    assert z["states"].shape[-1] == 14  # what the policy and the scorer read: the robot's own state


def test_without_the_learned_state_the_policies_are_refused_in_one_line(lab, capsys):
    """--no-learned-state hands the policies the integrated 4-D commands (the choice for absolute targets or
    velocities of the recorded state): these policies declare the robot's 14-D state and are refused up front."""
    assert _sweep(lab, lab / "sweep_commands", "--no-learned-state") == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "14-D states (state_dim)" in err and "4-D states" in err

"""``sc3 diagnose``'s action-following passes end to end on a robot that is not the bussing benchmark: 4-D velocity
commands with a gripper target (SO-101's kind) under a 5-D recorded state that holds the end effector's xy, a
benchmark's locators, and a learned state head beside the world model. The tiny untrained world model copies its
last context frame whatever the actions (residual prediction, zero output weights): an action-blind model, so its
counterfactual cosine and gain read exactly 0 through the state head and through the arm's pixels alike, and the
table prints every headline row with an interval over episodes."""
import numpy as np
import pytest

import sc3_jax.benchmarks.bussing  # noqa: F401  (picks the GL backend before mujoco is imported)
from sc3_jax.model import checkpoint
from sc3_jax.rollout import state_head
from sc3_jax.train import train
from sc3_jax.evaluation.benchmark import Locators
from sc3_jax.core.config import load_config, replace
from sc3_jax.data.action_space import ActionSpace
from sc3_jax.data.episodes import Episode, EpisodeStore
from sc3_jax.data.norm_stats import NormStats
from sc3_jax.evaluation import diagnose as dg
from sc3_jax.evaluation import diagnose_headline
from sc3_jax.measures import locate

pytestmark = pytest.mark.slow  # a tiny world model compiled for two passes: over a minute on 2 cores

SPACE = ActionSpace("velocity", 4, ("dx", "dy", "dz", "gripper"), targets=(3,))
NAMES = ("j0", "gripper", "ee_x", "ee_y", "ee_z")
S, T, FPS = 32, 50, 10.0


def _frames(xy):
    """[T, S, S, 3]: a yellow 4x4 arm at the state's xy, a purple block that rides with it from frame 20."""
    f = np.full((len(xy), S, S, 3), 40, np.uint8)
    for t, (x, y) in enumerate(xy):
        r, c = int(round(12 + 40 * y)), int(round(12 + 40 * x))
        f[t, r:r + 4, c:c + 4] = (220, 200, 30)
        b = (r + 5, c) if t >= 20 else (int(round(12 + 40 * xy[20][1])) + 5, int(round(12 + 40 * xy[20][0])))
        f[t, b[0]:b[0] + 3, b[1]:b[1] + 3] = (160, 60, 160)
    return f


def _store(root):
    st = EpisodeStore(root, views=["workspace", "wrist"], fps=FPS, image_size=(S, S), create=True,
                      action_space=SPACE, state_dim=len(NAMES), state_names=list(NAMES), has_pose=False)
    rng = np.random.default_rng(0)
    for e in range(3):
        a = np.zeros((T, 4), np.float32)
        a[:, :2] = rng.normal(0, 0.02, (T, 2)) + np.array([0.01, 0.005])
        a[:, 3] = np.sign(rng.normal(size=T))
        xy = 0.05 + np.r_[[[0.0, 0.0]], np.cumsum(a[:-1, :2] / FPS * 10, 0)]  # 10 state units per action unit
        state = np.zeros((T, 5), np.float32)
        state[:, 2:4], state[:, 1] = xy, a[:, 3]
        frames = _frames(np.clip(xy, 0, 0.4))
        wrist = rng.integers(0, 255, frames.shape, dtype=np.uint8)
        st.write(Episode(f"ep{e}", {"workspace": frames, "wrist": wrist}, a, None, "", {}, state))
    return st


def _arm(frames, views):
    from sc3_jax.benchmarks.so101.hooks import arm_mask
    return locate.masked_views(locate.centroid(arm_mask(frames)), views)


def _block(frames, views):
    from sc3_jax.benchmarks.so101.hooks import block_mask
    return locate.masked_views(locate.centroid(block_mask(frames)), views)


@pytest.fixture(scope="module")
def result(tmp_path_factory):
    root = tmp_path_factory.mktemp("follow")
    st = _store(root / "heldout")
    cfg = replace(load_config("bussing_sim"), model=dict(dim=32, depth=1, num_heads=2, num_kv_heads=1, head_dim=16,
                                                         mlp_dim=64, rope_axes_dim=(4, 2, 2), action_dim=4,
                                                         num_views=2, patch_size=8),
                  sample=dict(steps=2), data=dict(fps=FPS, state_dim=5, views=("workspace", "wrist"),
                                                  image_size=(S, S), future_frames=8))
    assert cfg.model.prediction == "residual"
    params = _params(cfg)
    stats = NormStats(np.zeros(4, np.float32), np.full(4, 0.02, np.float32), np.zeros(4, np.float32),
                      np.ones(4, np.float32), action_space=SPACE)
    wm = checkpoint.save(root / "wm", cfg, stats, params, np.float32)
    import jax
    head = state_head.init(jax.random.key(0), 5, 4, 2 * 8 * 8 * 3, 16)
    head = {k: np.asarray(v) for k, v in head.items()}
    head.update(state_mean=np.zeros(5, np.float32), state_std=np.ones(5, np.float32),
                action_mean=np.zeros(4, np.float32), action_std=np.ones(4, np.float32))
    state_head.save(head, wm, {})
    loc = Locators(arm=_arm, objects={"block": _block}, moves={"dx": "ee_x", "dy": "ee_y"})
    return dg.diagnose(wm, st.root, dg.DiagnoseConfig(stages=("counterfactual", "open_loop"), progress=False,
                                                      cf_starts=2), locators=loc)


def _params(cfg):
    import jax
    return jax.device_get(train.init_state(cfg)["params"])


def test_an_action_blind_model_reads_cosine_0_through_the_state_head_and_the_pixels(result):
    cf = result["counterfactual"]
    assert cf["axes"] == ["dx", "dy"]  # what the benchmark says the actions move; the gripper moves no position
    assert "benchmark" in cf["notes"][0] or "measured" in cf["notes"][0]
    names = list(cf["readouts"])
    assert names[0].startswith("end effector (state head): ee_x, ee_y") and cf["headline"] == names[0]
    assert "arm pixels: workspace" in names and not any("wrist" in n for n in names)
    for r in cf["readouts"].values():
        assert r["cosine"]["n"] == 3 * 2 * 2 * 2  # episodes x starts x axes x signs
        assert r["cosine"]["value"] == 0.0 and r["gain"]["value"] == 0.0
        assert r["cosine"]["lo"] == r["cosine"]["hi"] == 0.0  # an interval over the 3 episodes


def test_the_table_prints_the_headline_rows_with_intervals(result):
    rows = diagnose_headline.summary_rows(result)
    measures = [r["measure"] for r in rows]
    assert measures[:2] == ["counterfactual cosine", "counterfactual gain"]
    ee = [r for r in rows if r["measure"] == "end-effector error"]
    assert [r["time"] for r in ee] == ["1 s", "2 s", "4 s"]  # 5 s episodes: no 8 s point
    assert all(r["units"] == "robot units: ee_x, ee_y" and r["n"] == 3 and r["lo"] <= r["value"] <= r["hi"]
               for r in ee)
    assert {"head on real frames", "hold the start"} <= set(ee[0]["reference"])
    blk = [r for r in rows if r["measure"] == "object position error"]
    assert blk and all(r["readout"] == "block: workspace" and r["units"] == "px" for r in blk)
    carried = next(r for r in rows if r["measure"] == "carried in imagination")
    assert carried["value"] == 0.0 and carried["n"] > 0  # the copy-last model leaves the carried block behind
    text = dg.render_table(result)
    assert "### Where the imagined arm and objects go" in text
    assert "| counterfactual cosine | end effector (state head): ee_x, ee_y | - | 0.00 [0.00, 0.00] |" in text

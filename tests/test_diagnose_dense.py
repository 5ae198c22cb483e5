"""``sc3 diagnose``'s dense probe and paired comparison (``diagnose_dense.py``, ``diagnose_paired.py``) on a store
whose motion is known: a yellow arm sweeping right, a purple block it carries over known frames (and one it pushes
the other way, which is no carry). The windows chosen are exactly the carried ones; two world models see the same
sampler key per window, so a model against itself differs by exactly 0 while another model does not; the paired
interval resamples episodes, not windows."""
import math

import numpy as np
import pytest

from sc3_jax.core.config import load_config, replace
from sc3_jax.core.errors import UserError
from sc3_jax.data.action_space import ActionSpace
from sc3_jax.data.episodes import Episode, EpisodeStore
from sc3_jax.data.norm_stats import NormStats
from sc3_jax.evaluation import diagnose_dense, diagnose_paired
from sc3_jax.evaluation.benchmark import Locators
from sc3_jax.measures import locate

SPACE = ActionSpace("velocity", 4, ("dx", "dy", "dz", "gripper"), targets=(3,))
S, T, FPS, LP, CARRY = 32, 36, 10.0, 10, 3.0  # image side, frames, fps (= control_hz: stride 1), l', --carry-px
# episode id -> (first, last) frame the block rides with the arm; "push" moves it against the arm's way
CARRIES = {"carry_a": (10, 20), "carry_b": (4, 24), "push": (8, 18)}


def _arm_col(t):
    return 2 + min(t, 24)  # sweeps right one pixel a frame, then stays


def _block_col(eid, t):
    a, b = CARRIES[eid]
    moved = int(np.clip(t - a, 0, b - a))
    return 8 - moved if eid == "push" else 8 + moved


def _episode(eid, rng):
    f = np.full((T, S, S, 3), 40, np.uint8)
    for t in range(T):
        f[t, 4:8, _arm_col(t):_arm_col(t) + 4] = (220, 200, 30)
        f[t, 14:17, _block_col(eid, t):_block_col(eid, t) + 3] = (160, 60, 160)
    a = np.zeros((T, 4), np.float32)
    a[:, 0] = 0.1
    wrist = rng.integers(0, 255, f.shape, dtype=np.uint8)
    return Episode(eid, {"workspace": f, "wrist": wrist}, a, None, "", {}, np.zeros((T, 5), np.float32))


def _store(root, ids):
    st = EpisodeStore(root, views=["workspace", "wrist"], fps=FPS, image_size=(S, S), create=True,
                      action_space=SPACE, state_dim=5, state_names=["j0", "gripper", "ee_x", "ee_y", "ee_z"],
                      has_pose=False)
    rng = np.random.default_rng(0)
    for eid in ids:
        st.write(_episode(eid, rng))
    return st


def _arm(frames, views):
    from sc3_jax.benchmarks.so101.hooks import arm_mask
    return locate.masked_views(locate.centroid(arm_mask(frames)), views)


def _block(frames, views):
    from sc3_jax.benchmarks.so101.hooks import block_mask
    return locate.masked_views(locate.centroid(block_mask(frames)), views)


LOCATORS = Locators(arm=_arm, objects={"block": _block})


def _expected(eid, steps):
    """(f0, time label) of every carried window, from the known motion: windows f0 = K-1 .. T-1-l' (a whole chunk
    of real targets after f0); carried at k steps when the block moved >= CARRY px the arm's way by f0 + k."""
    out = set()
    for f0 in range(1, T - LP):
        for label, k in steps.items():
            d = _block_col(eid, f0 + k) - _block_col(eid, f0)
            if d >= CARRY and _arm_col(f0 + k) > _arm_col(f0):
                out.add((f0, label))
    return out


def test_the_windows_chosen_are_exactly_those_where_the_real_arm_carries_the_block(tmp_path):
    from sc3_jax.rollout.rollout import make_spec
    st = _store(tmp_path / "h", list(CARRIES))
    cfg = _config()
    spec = make_spec(replace(cfg, rollout=dict(keep_frames=LP, policy_chunk=25)), FPS, 1, action_space=SPACE)
    steps = diagnose_dense.steps_of(diagnose_dense.SECONDS, cfg.rollout.control_hz)
    assert steps == {"0.5 s": 5, "1 s": 10}  # seconds through the model's control rate, not a fixed 10 Hz
    assert diagnose_dense.steps_of((0.5, 1.0), 4.0) == {"0.5 s": 2, "1 s": 4}
    eps = [st.load(e) for e in CARRIES]
    windows, n = diagnose_dense.select(eps, ["workspace", "wrist"], spec, lambda e: _arm, {"block": _block}, CARRY,
                                       steps)
    assert n == 3 * (T - LP - 1)
    got = {(list(CARRIES)[w.episode], w.f0, label) for w in windows for _, _, label, _, _ in w.carried}
    want = {(e, f0, label) for e in CARRIES for f0, label in _expected(e, steps)}
    assert want and got == want
    assert not any(e == "push" for e, _, _ in got)  # moved 10 px, against the arm: pushed, not carried
    assert {v for w in windows for _, v, *_ in w.carried} == {0}  # the workspace view: the wrist's is no position


def test_a_paired_interval_resamples_episodes_not_windows():
    """100 windows of +1 in one episode, one window of -1 in each of two others: resampling episodes draws the
    two -1 episodes alone in (2/3)^3 of the draws (lower end -1) and the +1 one alone in (1/3)^3 (upper end +1);
    resampling windows would give an interval tight around the pooled 0.96."""
    cells = {"e0": [100.0, 0.0, 100], "e1": [0.0, 1.0, 1], "e2": [0.0, 1.0, 1], "e3": [5.0, 5.0, 0]}
    r = diagnose_paired.paired(cells, draws=2000, seed=0)
    assert r["a_minus_b"]["value"] == pytest.approx(98 / 102) and r["n"] == 102 and r["episodes"] == 3
    assert r["a_minus_b"]["lo"] == -1.0 and r["a_minus_b"]["hi"] == 1.0
    assert r["a"]["value"] - r["b"]["value"] == pytest.approx(r["a_minus_b"]["value"])
    one = diagnose_paired.paired({"e0": [3.0, 1.0, 2]})
    assert one["a_minus_b"]["value"] == 1.0 and math.isnan(one["a_minus_b"]["lo"])  # one episode: no interval


def _config():
    return replace(load_config("bussing_sim"), model=dict(dim=32, depth=1, num_heads=2, num_kv_heads=1, head_dim=16,
                                                          mlp_dim=64, rope_axes_dim=(4, 2, 2), action_dim=4,
                                                          num_views=2, patch_size=8),
                   sample=dict(steps=2), data=dict(fps=FPS, state_dim=5, views=("workspace", "wrist"),
                                                   image_size=(S, S), future_frames=LP))


def _model(root, name, scale, seed, views=("workspace", "wrist")):
    """A tiny world model whose zero-initialised output layer (a copy-last model) is perturbed by ``scale``: its
    frames then depend on the sampler's noise."""
    import jax

    from sc3_jax.model import checkpoint
    from sc3_jax.train import train
    cfg = replace(_config(), data=dict(views=views))
    params = jax.device_get(train.init_state(_config())["params"])
    rng = np.random.default_rng(seed)
    params = jax.tree.map(lambda x: (x + scale * rng.standard_normal(x.shape)).astype(x.dtype), params)
    stats = NormStats(np.zeros(4, np.float32), np.full(4, 0.1, np.float32), np.zeros(4, np.float32),
                      np.ones(4, np.float32), action_space=SPACE)
    return checkpoint.save(root / name, cfg, stats, params, np.float32)


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    from sc3_jax.evaluation import diagnose as dg
    root = tmp_path_factory.mktemp("dense")
    st = _store(root / "heldout", ["carry_a", "carry_b"])
    a, b = _model(root, "a", 0.02, 1), _model(root, "b", 0.02, 2)
    dc = dg.DiagnoseConfig(stages=("dense",), progress=False, batch=8)
    run = lambda wm, **kw: dg.diagnose(wm, st.root, dc, locators=LOCATORS, **kw)  # noqa: E731
    return root, st, a, {"a": run(a), "a again": run(a), "b": run(b), "a seed 1": run(a, seed=1)}


def test_two_models_see_the_same_noise_per_window_so_a_model_against_itself_differs_by_exactly_0(runs):
    _, st, _, r = runs
    da, db = r["a"]["dense"], r["b"]["dense"]
    assert [w["key"] for w in da["windows"]] == [w["key"] for w in db["windows"]]
    want = diagnose_dense.window_keys(0 + diagnose_dense.KEY_STREAM, [w["episode"] for w in da["windows"]],
                                      [w["from_frame"] for w in da["windows"]])
    assert [w["key"] for w in da["windows"]] == want.tolist()  # from (seed, episode, frame) alone
    assert len({tuple(k) for k in want.tolist()}) == len(want)  # one key per window
    steps = {"0.5 s": 5, "1 s": 10}
    assert {(w["episode"], w["from_frame"], c["time"]) for w in da["windows"] for c in w["carried"]} == \
        {(e, f0, t) for e in ("carry_a", "carry_b") for f0, t in _expected(e, steps)}
    self_cmp = diagnose_paired.compare(r["a"], r["a again"])
    rows = self_cmp["dense"]["rows"]
    assert rows and all(x["n"] > 0 and x["a_minus_b"]["value"] == 0.0 and x["a_minus_b"]["lo"] == 0.0 ==
                        x["a_minus_b"]["hi"] for x in rows)
    ab = diagnose_paired.compare(r["a"], r["b"])["dense"]["rows"]
    assert any(x["a_minus_b"]["value"] != 0.0 for x in ab)  # the models differ, and the comparison shows it
    # the noise reaches the frames: the same model under other keys puts the block elsewhere in some window
    wa = {(w["episode"], w["from_frame"]): w["carried"] for w in da["windows"]}
    assert any(c["imagined"] != d["imagined"] for w in r["a seed 1"]["dense"]["windows"]
               for c, d in zip(w["carried"], wa[(w["episode"], w["from_frame"])])
               if math.isfinite(c["imagined"]) or math.isfinite(d["imagined"]))
    with pytest.raises(UserError, match="other noise"):
        diagnose_paired.compare(r["a"], r["a seed 1"])
    text = "\n".join(diagnose_paired.lines(self_cmp))
    assert "| block: workspace | 0.5 s |" in text and "+0.00 [+0.00, +0.00]" in text


def test_a_store_where_nothing_is_carried_and_another_robot_are_one_line_errors(runs, tmp_path, capsys):
    from sc3_jax.cli import main as cli
    from sc3_jax.evaluation import diagnose as dg
    root, st, a, _ = runs
    still = _store(tmp_path / "still", ["push"])
    with pytest.raises(UserError, match="nothing to measure"):
        dg.diagnose(a, still.root, dg.DiagnoseConfig(stages=("dense",), progress=False), locators=LOCATORS)
    with pytest.raises(UserError, match="benchmark"):
        dg.diagnose(a, st.root, dg.DiagnoseConfig(stages=("dense",), progress=False))
    other = _model(root, "other_views", 0.0, 0, views=("wrist", "workspace"))
    rc = cli(["diagnose", "--world-model", str(a), "--against", str(other), "--data", str(st.root), "--no-progress"])
    err = capsys.readouterr().err.strip()
    assert rc != 0 and len(err.splitlines()) == 1 and "views ['workspace', 'wrist'] against ['wrist', 'workspace']" \
        in err

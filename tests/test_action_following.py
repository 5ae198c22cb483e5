"""The action-following measures of ``sc3 diagnose`` (measures/action_following.py, tracking.py, moved.py) on a
synthetic scene: a bright blob (the arm) drawn where the integrated velocity commands put it. A world model that
ignores its actions reads a counterfactual cosine and gain of 0; an oracle that renders the commanded pose reads 1,
through the arm's pixels and through a state head alike; replaying the real frames reads position error 0 and
keeps every real carry."""
import dataclasses

import numpy as np
import pytest

from sc3_jax.data.action_space import ActionSpace
from sc3_jax.measures import action_following as af
from sc3_jax.measures import moved as mv
from sc3_jax.measures import tracking

SPACE = ActionSpace("velocity", 3, ("vx", "vy", "grip"), targets=(2,))
DT, N, SIZE, SCALE = 0.1, 8, 48, 8.0  # s per model step, steps per chunk, image pixels, pixels per state unit
STD = np.array([1.0, 1.0, 0.5])


def render(xy: np.ndarray, block: np.ndarray | None = None) -> np.ndarray:
    """uint8 [2, n, H, W, 3]: a third-person view with a Gaussian blob at each state's xy (row = 24 + 8 y, col = 24
    + 8 x), a purple one at ``block``'s, and a wrist view (noise the locators must ignore)."""
    yy, xx = np.mgrid[:SIZE, :SIZE]
    out = np.zeros((2, len(xy), SIZE, SIZE, 3), np.float64)
    for t, (x, y) in enumerate(np.asarray(xy)[:, :2]):
        out[0, t, ..., 0] = out[0, t, ..., 1] = 250 * np.exp(-((yy - 24 - SCALE * y) ** 2 + (xx - 24 - SCALE * x) ** 2)
                                                             / 4.5)
        if block is not None:
            bx, by = block[t]
            out[0, t, ..., 2] = 250 * np.exp(-((yy - 24 - SCALE * by) ** 2 + (xx - 24 - SCALE * bx) ** 2) / 4.5)
    out[1] = np.random.default_rng(0).integers(0, 255, out[1].shape)
    return np.clip(out, 0, 255).astype(np.uint8)


def weighted(frames, channel):
    w = np.asarray(frames, np.float64)[..., channel]
    w = np.where(w > 20, w, 0.0)
    H, W = w.shape[-2:]
    n = w.sum((-2, -1))
    with np.errstate(invalid="ignore"):  # a blank frame: no blob, nan
            out = np.stack([(w.sum(-1) * np.arange(H)).sum(-1) / n, (w.sum(-2) * np.arange(W)).sum(-1) / n], -1)
    return np.where(n[..., None] > 0, out, np.nan)


def arm_locator(frames, views):  # the benchmark's: the yellow blob's intensity-weighted centroid, not the wrist
    out = weighted(frames, 0)
    out[1] = np.nan
    return out


def block_locator(frames, views):
    out = weighted(frames, 2)
    out[1] = np.nan
    return out


@dataclasses.dataclass
class Ep:
    state: np.ndarray  # [T, 3]
    actions: np.ndarray  # [T, 3] model rate
    frames: np.ndarray  # [2, T, H, W, 3]


def episodes(n=3, T=40, seed=0):
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        a = rng.normal(0, 1, (T, 3)) * STD
        a[:, 2] = np.sign(a[:, 2])
        s = SPACE.integrate(np.zeros(3, np.float32), a[:-1], DT)
        out.append(Ep(s, a.astype(np.float32), render(s)))
    return out


def starts(eps, every=10):
    out = []
    for e, ep in enumerate(eps):
        for t in range(0, len(ep.state) - N - 1, every):
            ic = (ep.frames[:, t:t + 1], ep.state[t], 0)
            out.append({"episode": e, "start": t, "ic": ic, "actions": ep.actions[None, t:t + N],
                        "robot": ep.state[t]})
    return out


def oracle(ics, actions, noise):  # renders the commanded pose: where the integrated commands put the arm
    return [render(SPACE.integrate(ic[1], a[0], DT)[1:]) for ic, a in zip(ics, actions)]


def blind(ics, actions, noise):  # the same frames whatever the actions: the arm held at the start
    return [render(np.repeat(ic[1][None], a.shape[1], 0)) for ic, a in zip(ics, actions)]


def head_read(robot0, actions, frames):  # a state head that reads the arm off the frames (the recorded actions ignored)
    rc = weighted(frames, 0)[0]  # [n, 2]
    s = np.zeros((len(rc), 3))
    s[:, 0], s[:, 1] = (rc[:, 1] - 24) / SCALE, (rc[:, 0] - 24) / SCALE
    return s


@dataclasses.dataclass
class Store:  # what moved.moved reads of an EpisodeStore
    state_names: tuple = ("x", "y", "grip")
    has_pose: bool = False
    state_dim: int = 3


def readouts(eps):
    chunks = [(s["episode"], s["actions"][0], eps[s["episode"]].frames[:, [s["start"], s["start"] + N]])
              for s in starts(eps, every=3)]
    maps = af.fit_image_map(chunks, lambda e: arm_locator, ["front", "wrist"], SPACE, DT)
    assert maps[1]["map"] is None and maps[0]["r2"][0] > 0.99 and maps[0]["r2"][1] > 0.99  # the wrist says nothing
    moved = mv.moved(SPACE, Store())
    fs = af.fit_state_map([(s["actions"][0], eps[s["episode"]].state[[s["start"], s["start"] + N]])
                           for s in starts(eps, every=3)], SPACE, DT, (0, 1), af.cols_of(moved, (0, 1)))
    return [af.HeadReadout(head_read, moved, Store.state_names, fs["map"], (0, 1)),
            af.PixelReadout(0, ["front", "wrist"], lambda e: arm_locator, maps[0]["map"])], moved


@pytest.mark.parametrize("model, cosine, gain", [(oracle, 1.0, 1.0), (blind, 0.0, 0.0)])
def test_an_oracle_reads_cosine_1_and_an_action_blind_model_0(model, cosine, gain):
    eps = episodes()
    ros, moved = readouts(eps)
    assert moved.axes == (0, 1, 2) and moved.pose == (0, 1)  # the gripper target is no position
    rows = af.run(starts(eps), model, ros, SPACE, (0, 1), STD, 0.5, DT)
    sec = af.section(rows, SPACE.names, draws=200)
    assert set(sec) == {ros[0].name, ros[1].name}
    for name, r in sec.items():
        assert r["cosine"]["n"] == 2 * 2 * len(starts(eps))  # every start, both axes, both signs
        assert r["cosine"]["value"] == pytest.approx(cosine, abs=0.02), name
        assert r["gain"]["value"] == pytest.approx(gain, abs=0.05), name
        assert r["cosine"]["lo"] <= r["cosine"]["value"] <= r["cosine"]["hi"]
        assert set(r["axes"]) == {"vx", "vy"}


def test_a_model_that_swaps_the_axes_reads_cosine_0_and_one_that_reverses_them_minus_1():
    eps = episodes()
    ros, _ = readouts(eps)

    def swapped(ics, actions, noise):
        return oracle(ics, [a[..., [1, 0, 2]] for a in actions], noise)

    def reversed_(ics, actions, noise):
        rec = {}
        for ic, a, k in zip(ics, actions, noise):
            rec.setdefault(k, a)  # the recorded chunk comes first: mirror each variant's shift about it
        return oracle(ics, [2 * rec[k] - a for a, k in zip(actions, noise)], noise)

    for model, want in ((swapped, 0.0), (reversed_, -1.0)):
        sec = af.section(af.run(starts(eps), model, ros, SPACE, (0, 1), STD, 0.5, DT), SPACE.names, draws=50)
        assert sec[ros[1].name]["cosine"]["value"] == pytest.approx(want, abs=0.05)


def test_shifts_are_a_fraction_of_each_axis_std_and_displace_as_the_action_space_integrates():
    a = np.zeros((1, N, 3), np.float32)
    v = af.shifted(a, (0, 2), STD, 0.5)
    assert [x[0] for x in v] == ["recorded", "+0", "-0", "+2", "-2"]
    assert v[1][2] == 0.5 and v[3][2] == 0.25 and np.all(v[4][3][..., 2] == -0.25) and np.all(v[1][3][..., 1] == 0)
    assert mv.shift_displacement(SPACE, 0, 0.5, N, DT) == pytest.approx(0.5 * DT * N)  # a velocity integrates
    assert mv.shift_displacement(SPACE, 2, 0.25, N, DT) == 0.25  # a target is moved itself
    delta = ActionSpace()
    assert mv.shift_displacement(delta, 0, 0.01, N, DT) == pytest.approx(0.08)  # each step's delta adds
    assert mv.shift_displacement(ActionSpace("absolute", 2), 1, 0.3, N, DT) == 0.3


def test_what_the_actions_move_comes_from_the_space_the_benchmark_or_the_state_dimension():
    so101 = ActionSpace("velocity", 4, ("dx", "dy", "dz", "gripper"), targets=(3,))
    names = tuple(f"j{i}" for i in range(10)) + ("gripper", "ee_x", "ee_y", "ee_z")
    store = Store(state_names=names, state_dim=14)
    assert mv.moved(so101, store).source is None  # 14-D state, 4-D actions, nothing declared
    m = mv.moved(so101, store, {"dx": "ee_x", "dy": "ee_y", "dz": "ee_z"})
    assert (m.axes, m.entries, m.names) == ((0, 1, 2), (11, 12, 13), ("ee_x", "ee_y", "ee_z"))
    if "measured" in {f.name for f in dataclasses.fields(ActionSpace)}:  # the space's own declaration wins
        declared = dataclasses.replace(so101, measured=(11, 12, 13, 10))
        m = mv.moved(declared, store, {"dx": "j0"})
        assert m.entries == (11, 12, 13, 10) and m.pose == (11, 12, 13)
    assert mv.moved(ActionSpace(), Store(has_pose=True)).source == "ee_pose"
    assert mv.moved(ActionSpace(), Store(has_pose=False)).source is None


def _open_loop(eps, model):
    """Each episode's open loop from frame 0 with its recorded actions, tracked."""
    tr = tracking.Tracks(hz=1 / DT, views=["front", "wrist"], carry_px=3.0)
    for e, ep in enumerate(eps):
        n = len(ep.state) - 1
        ic = (ep.frames[:, :1], ep.state[0], 0)
        pred = model([ic], [ep.actions[None, :n]], [e])[0]
        real = ep.frames[:, 1:]
        start = ep.frames[:, :1]
        with_start = lambda f: np.concatenate([start, f], 1)  # noqa: E731
        im_s, re_s = head_read(None, None, with_start(pred)), head_read(None, None, with_start(real))
        tr.add_state("ee", "state units", e, im_s[:, :2], re_s[:, :2], ep.state[:, :2])
        arm_im, arm_re = arm_locator(with_start(pred), None), arm_locator(with_start(real), None)
        tr.add_pixels("arm", "arm", e, arm_im, arm_re)
    return tr.section(draws=100)


def test_replaying_the_real_frames_reads_position_error_0_and_a_frozen_arm_the_hold_reference():
    eps = episodes(T=45)
    replay = _open_loop(eps, oracle)
    frozen = _open_loop(eps, blind)
    assert set(replay["end effector"]["ee"]["times"]) == {"1 s", "2 s", "4 s"}  # 4.4 s episodes: no 8 s point
    for t in ("1 s", "2 s", "4 s"):
        r = replay["end effector"]["ee"]["times"][t]
        # the replay reads what the read-out reads on the real frames (its own floor: a blob cut by the border)
        assert r["imagined"]["value"] == pytest.approx(r["head on real frames"]["value"], abs=1e-12)
        assert r["imagined"]["value"] < 0.01 and r["imagined"]["n"] == 3
        assert r["hold the start"]["value"] > 0.1
        f = frozen["end effector"]["ee"]["times"][t]
        assert f["imagined"]["value"] == pytest.approx(f["hold the start"]["value"], abs=1e-3)
        assert replay["arm"]["arm: front"]["times"][t]["imagined"]["value"] == pytest.approx(0.0, abs=1e-6)
    assert "arm: wrist" not in replay["arm"]  # the wrist view reads no position


def test_a_carried_block_is_kept_by_a_replay_and_lost_by_a_model_that_leaves_it():
    rng = np.random.default_rng(3)
    T = 30
    arm = np.cumsum(np.r_[[[0.0, 0.0]], np.tile([[0.15, 0.05]], (T - 1, 1))], 0) - 1.5  # the arm sweeps right
    block = arm.copy()
    block[:10] = arm[10]  # the block waits until the arm reaches it at step 10, then goes with it
    real = render(arm, block)
    left = render(arm, np.repeat(block[:1], T, 0))  # imagination that moves the arm and leaves the block behind
    tr = tracking.Tracks(hz=10.0, views=["front", "wrist"], carry_px=3.0)
    for e, im in enumerate((real, left, real[:, rng.permutation(T)] * 0)):
        tr.add_carried("block", e, block_locator(im, None), arm_locator(im, None), block_locator(real, None),
                       arm_locator(real, None))
        tr.add_pixels("objects", "block", e, block_locator(im, None), block_locator(real, None))
    sec = tr.section(draws=100)
    c = sec["carried"]["block: front"]
    assert c["episodes_carrying"] == 3 and c["real_steps"] > 3 * 10
    per = [tr.carried[("block", "front")]["hit"][e] for e in range(3)]
    assert np.mean(per[0]) == 1.0 and np.mean(per[1]) == 0.0 and per[2] == [0.0] * len(per[2])  # lost: not carried
    assert c["carried_in_imagination"]["value"] == pytest.approx(1 / 3)
    blk = sec["objects"]["block: front"]["times"]["2 s"]["imagined"]
    assert blk["n"] == 2 and blk["value"] > 0  # the blank episode's block is lost (counted apart), the left one off
    assert sec["objects"]["block: front"]["times"]["2 s"]["imagined"]["lost"] == 1


def test_the_state_map_gives_the_commanded_displacement_in_the_states_own_units():
    """A robot whose velocity unit moves its state 2 units a second (SO-101: dx 1 is 0.025 m/s): the fitted map
    reads 2 on the diagonal, so a gain of 1 means the state moved as far as the commands move the real robot."""
    eps = episodes()
    chunks = [(s["actions"][0], 2 * eps[s["episode"]].state[[s["start"], s["start"] + N]]) for s in starts(eps, 3)]
    fs = af.fit_state_map(chunks, SPACE, DT, (0, 1), [0, 1])
    np.testing.assert_allclose(fs["map"][:2], 2 * np.eye(2), atol=1e-6)
    assert fs["map"][2].tolist() == [0.0, 0.0] and min(fs["r2"]) > 0.999
    assert af.fit_state_map(chunks[:5], SPACE, DT, (0, 1), [0, 1])["map"] is None  # too few chunks to fit


def test_a_sweep_report_shows_the_world_model_s_headline_rows_beside_it(tmp_path):
    """The report of any sweep reads WM/diagnose.json's headline rows (diagnose_headline.beside_sweep): the
    counterfactual cosine with its interval, against what an action-blind model and an exact follower read."""
    import json

    from sc3_jax.evaluation import diagnose_headline as H
    from sc3_jax.evaluation.diagnose_report import beside_sweep

    assert beside_sweep(str(tmp_path)) is None and H.report_table(None) is None  # not diagnosed: no table
    cos = {"value": 0.59, "lo": 0.49, "hi": 0.66, "n": 36}
    res = {"episodes": [{}] * 6, "counterfactual": {"headline": "end effector", "fraction_of_std": 0.5,
                                                    "axes": ["dx", "dy"],
                                                    "readouts": {"end effector": {"cosine": cos, "gain": cos}}}}
    (tmp_path / "diagnose.json").write_text(json.dumps(res))
    title, header, rows = H.report_table(beside_sweep(str(tmp_path)))
    assert "6 held-out episodes" in title and header[3] == "value"
    assert rows[0][:4] == ["counterfactual cosine", "end effector", "-", "0.59 [0.49, 0.66]"]
    assert "action-blind 0" in rows[0][4] and "follows exactly 1" in rows[0][4]

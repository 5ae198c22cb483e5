"""Scorers: criteria from per-frame predicates (hand-built cases), perception labels from physics state, the state
reader, agreement."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sc3_jax.benchmarks.bussing import perception
from sc3_jax.benchmarks.bussing.scorers import PerceptionScorer, SimScorer, criteria_from_predicates
from sc3_jax.evaluation.scorers import RolloutView, agreement, first_run, held
from sc3_jax.benchmarks.bussing.criteria import evaluate_object

DEST = {"cup": "bin", "bag": "can"}


def probs_for(T, series: dict):
    """series: {(object, predicate): bool list} -> probs [T, 6, 3]."""
    p = np.zeros((T, 6, 3))
    for (obj, pred), v in series.items():
        p[:, perception.TYPES.index(obj), perception.PREDICATES.index(pred)] = np.asarray(v, float)
    return p


def test_held_needs_a_run():
    assert held([0, 1, 1, 0], 2) and not held([1, 0, 1, 0], 2) and held([1], 1) and not held([], 1)
    assert first_run([0, 1, 0, 1, 1, 1], 2) == 3 and first_run([1, 0, 1], 2) is None


@pytest.mark.parametrize("series, expected", [
    # untouched: passes language, fails lifting and placing
    ({}, ("cup", True, False, False, "lifting")),
    # lifted and dropped in the right container
    ({("cup", "lifted"): [1, 1, 1, 0, 0, 0], ("cup", "in_bin"): [0, 0, 0, 1, 1, 1]}, ("cup", True, True, True,
                                                                                     "no_failure")),
    # placing is read over the settled tail (the last 3 frames), not from one frame: 2 final frames are not enough
    ({("cup", "lifted"): [1, 1, 1, 0, 0, 0], ("cup", "in_bin"): [0, 0, 0, 0, 1, 1]}, ("cup", True, True, False,
                                                                                     "placing")),
    # two misread frames of "lifted" do not count
    ({("cup", "lifted"): [0, 1, 1, 0, 0, 0]}, ("cup", True, False, False, "lifting")),
    # lifted, then into the wrong container: language violated
    ({("cup", "lifted"): [1, 1, 1, 0, 0, 0], ("cup", "in_can"): [0, 0, 1, 1, 1, 1]}, ("cup", False, True, False,
                                                                                     "language")),
    # "in a container" without ever being lifted is a misreading: it counts for nothing
    ({("cup", "in_can"): [0, 0, 1, 1, 1, 1]}, ("cup", True, False, False, "lifting")),
    ({("cup", "in_bin"): [1, 1, 1, 1, 1, 1]}, ("cup", True, False, False, "lifting")),
    # container frames count only from the first lifted run on: "in the can" before the lift is a misreading
    ({("cup", "in_can"): [1, 1, 1, 0, 0, 0, 0, 0, 0], ("cup", "lifted"): [0, 0, 0, 1, 1, 1, 0, 0, 0],
      ("cup", "in_bin"): [0, 0, 0, 0, 0, 0, 1, 1, 1]}, ("cup", True, True, True, "no_failure")),
    # lifted but ends outside: placing failure
    ({("cup", "lifted"): [0, 1, 1, 1, 0, 0]}, ("cup", True, True, False, "placing")),
    # in the bin, but taken out again at the end
    ({("cup", "lifted"): [1, 1, 1, 0, 0, 0], ("cup", "in_bin"): [0, 1, 1, 1, 1, 0]}, ("cup", True, True, False,
                                                                                     "placing")),
])
def test_criteria_from_predicates(series, expected):
    T = max([len(v) for v in series.values()], default=6)
    (o,) = criteria_from_predicates(probs_for(T, series), ["cup"], DEST)
    assert (o["object"], o["language"], o["lifting"], o["placing"], o["outcome"]) == expected


def test_predicate_labels_match_the_physics_criteria():
    """Labels built from positions, aggregated the scorer's way, equal the physics criteria on the same trajectory."""
    bin_xy, can_xy = np.array([0.2, -0.135]), np.array([0.2, 0.135])
    rng = np.random.default_rng(0)
    for _ in range(20):
        start = np.array([-0.1, 0.0, 0.03])
        up = start + [0, 0, rng.uniform(0.0, 0.12)]
        spots = [bin_xy, can_xy, np.array([0.0, 0.1])]
        carry = np.r_[spots[rng.integers(3)], rng.uniform(0.1, 0.15)]  # carried above the walls
        stops = [start, up, up, up] if rng.random() < 0.3 else [start, up, carry,
                                                                np.r_[spots[rng.integers(3)], 0.03]]
        traj = np.concatenate([np.linspace(a, b, 8) for a, b in zip(stops[:-1], stops[1:])])
        lab, mask = perception.predicate_labels(traj[:, None], ["cup"], bin_xy, can_xy)
        assert mask.sum() == 1 and mask[perception.TYPES.index("cup")]
        (o,) = criteria_from_predicates(lab.astype(float), ["cup"], DEST, min_run=1)
        truth = evaluate_object("cup", traj, 0.03, "bin", {"bin": bin_xy, "can": can_xy})
        assert (o["language"], o["lifting"], o["placing"]) == (truth.language, truth.lifting, truth.placing)


def test_perception_shapes_state_reader_and_round_trip(tmp_path):
    params = perception.init(jax.random.key(0))
    frames = np.random.default_rng(0).integers(0, 255, (3, 5, 64, 64, 3), dtype=np.uint8)
    probs, width = perception.predict(params, frames)
    assert probs.shape == (5, 6, 3) and width.shape == (5,) and np.all((probs >= 0) & (probs <= 1))
    w = perception.read_width(params, frames[:, 0])
    assert w.shape == () and 0.0 <= float(w) <= 0.09
    perception.save(tmp_path / "p.npz", params, {"note": 1})
    back = perception.load(tmp_path / "p.npz")
    assert np.allclose(perception.predict(back, frames)[0], probs, atol=1e-6)
    assert perception.load_meta(tmp_path / "p.npz") == {"note": 1, "arch": perception.arch(params)}
    with pytest.raises(FileNotFoundError, match="perception weights"):
        perception.load(tmp_path / "missing.npz")


def test_perception_architecture_is_stored_and_weights_of_any_size_load(tmp_path):
    small = {"n_kp": 8, "widths": [8, 12, 16], "hidden": 24}
    params = perception.init(jax.random.key(1), **small)
    assert perception.arch(params) == small and params["d1"]["w"].shape == (3 * 3 * 8, 24)
    frames = np.random.default_rng(1).integers(0, 255, (3, 4, 64, 64, 3), dtype=np.uint8)
    perception.save(tmp_path / "small.npz", params)
    assert perception.load_meta(tmp_path / "small.npz")["arch"] == small
    back = perception.load(tmp_path / "small.npz")
    assert perception.arch(back) == small
    assert np.allclose(perception.predict(back, frames)[0], perception.predict(params, frames)[0], atol=1e-6)
    # weights saved before the architecture was stored (no meta['arch']) load with the default shapes
    old = perception.init(jax.random.key(2))
    flat = {f"{a}/{b}": np.asarray(v) for a in old for b, v in old[a].items()}
    np.savez_compressed(tmp_path / "old.npz", __meta__="{}", **flat)
    assert perception.arch(perception.load(tmp_path / "old.npz")) == {
        "n_kp": perception.N_KP, "widths": list(perception.WIDTHS), "hidden": perception.HIDDEN}
    # a stored architecture that contradicts the arrays is refused
    np.savez_compressed(tmp_path / "bad.npz", __meta__='{"arch": {"n_kp": 8, "widths": [8, 12, 16], "hidden": 32}}',
                        **{f"{a}/{b}": np.asarray(v) for a in params for b, v in params[a].items()})
    with pytest.raises(ValueError, match="meta\\['arch'\\]"):
        perception.load(tmp_path / "bad.npz")


def test_loss_weights_positive_labels_only():
    from sc3_jax.benchmarks.bussing.perception_train import loss_fn
    rng = np.random.default_rng(3)
    params = perception.init(jax.random.key(3))
    x = jnp.asarray(rng.integers(0, 255, (4, 3, 64, 64, 3)), jnp.uint8)
    masks = jnp.ones((4, 6), bool)
    widths = jnp.zeros(4)
    logits = perception.apply(params, x)[0]
    neg = jnp.zeros((4, 6, 3), bool)
    pos = neg.at[:, 2, 1].set(True)
    # all labels negative: the weight changes nothing
    assert np.isclose(loss_fn(params, x, neg, masks, widths, 3.0)[1][0], loss_fn(params, x, neg, masks, widths)[1][0])
    # positives: their cross-entropy terms (-log sigmoid) count pos_weight times
    pos_term = float(-jax.nn.log_sigmoid(logits[:, 2, 1]).sum()) / 3 / masks.sum()
    c1, c3 = loss_fn(params, x, pos, masks, widths)[1][0], loss_fn(params, x, pos, masks, widths, 3.0)[1][0]
    assert np.isclose(float(c3 - c1), 2 * pos_term, rtol=1e-4)


def test_scorers_share_one_interface_and_agreement():
    physics = [{"name": "cup", "destination": "bin", "language": True, "lifting": True, "placing": False}]
    view = RolloutView("r0", np.zeros((3, 4, 64, 64, 3), np.uint8), ("cup",), {"cup": "bin"}, physics)
    gt = SimScorer().score(view)
    assert gt[0]["outcome"] == "placing"
    with pytest.raises(ValueError, match="only for real"):
        SimScorer().score(RolloutView("r1", view.frames, ("cup",), {"cup": "bin"}))
    p = PerceptionScorer(perception.init(jax.random.key(0))).score(view)
    assert set(p[0]) == set(gt[0])
    a = agreement([gt, gt], [gt, [dict(gt[0], lifting=False, outcome="lifting")]])
    assert a["lifting"] == 0.5 and a["language"] == 1.0 and a["outcome"] == 0.5 and a["n_objects"] == 2


def test_augment_degrades_per_sample_and_depends_only_on_the_key():
    from sc3_jax.benchmarks.bussing.perception_train import augment
    imgs = jnp.asarray(np.random.default_rng(0).integers(60, 200, (16, 3, 64, 64, 3)), jnp.uint8)
    a, b = augment(jax.random.key(1), imgs), augment(jax.random.key(1), imgs)
    c = augment(jax.random.key(2), imgs)
    assert a.dtype == jnp.uint8 and a.shape == imgs.shape
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    diff = np.abs(np.asarray(a, np.float32) - np.asarray(imgs, np.float32)).mean(axis=(1, 2, 3, 4))
    # every sample gets at least the pixel noise; the degradations are drawn per sample, so their sizes differ
    assert diff.min() > 1.0 and diff.max() > 2 * diff.min()


def test_train_warm_starts_from_given_weights():
    from sc3_jax.benchmarks.bussing.perception_train import train
    rng = np.random.default_rng(0)
    n = 24
    data = (rng.integers(0, 255, (n, 3, 64, 64, 3), dtype=np.uint8), rng.random((n, 6, 3)) > 0.5,
            np.tile(np.array([1, 1, 1, 0, 0, 0], bool), (n, 1)), rng.uniform(0, 0.08, n).astype(np.float32),
            np.repeat(np.arange(4), n // 4))
    start = perception.init(jax.random.key(5))
    zero_lr, m = train(data, steps=2, batch=4, lr=0.0, init=start, holdout=0.25, progress=False)
    assert all(np.array_equal(zero_lr[a][b], start[a][b]) for a in start for b in start[a])  # lr 0: nothing moves
    moved, _ = train(data, steps=2, batch=4, lr=1e-2, init=start, holdout=0.25, progress=False)
    assert not np.array_equal(moved["out"]["w"], start["out"]["w"])
    assert set(m) >= {"heldout_acc/lifted", "heldout_acc/in_bin", "heldout_acc/in_can", "heldout_width_mae_m",
                      "heldout_recall/in_can", "heldout_precision/in_can"}
    small = {"n_kp": 4, "widths": [4, 8, 8], "hidden": 16}
    fresh, _ = train(data, steps=1, batch=4, arch=small, pos_weight=2.0, holdout=0.25, progress=False)
    assert perception.arch(fresh) == small  # fresh weights take the requested architecture


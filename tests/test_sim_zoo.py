"""The policy zoo: every policy inside lax.scan equals the host loop; control knobs act as documented; the demo
generator keeps reverse-bussing episodes out of world-model data."""
import json
import types

import numpy as np
import pytest

import sc3_jax.benchmarks.bussing  # noqa: F401  (picks the GL backend before MuJoCo is imported)

pytest.importorskip("mujoco")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402

from sc3_jax.policies.base import as_host  # noqa: E402
from sc3_jax.benchmarks.bussing import zoo  # noqa: E402
from sc3_jax.benchmarks.bussing.demos import store_contents  # noqa: E402
from sc3_jax.benchmarks.bussing.env import BussingEnv  # noqa: E402
from sc3_jax.benchmarks.bussing.expert import ExpertKnobs, ScriptedExpert  # noqa: E402
from sc3_jax.benchmarks.bussing.scene import OPEN_WIDTH  # noqa: E402
from sc3_jax.benchmarks.bussing.tasks import OBJECT_BY_NAME, destination, make_initial_condition  # noqa: E402

HAVE_WEIGHTS = all((zoo.ZOO_DIR / e.weights).exists() for e in zoo.ZOO.values())


def test_zoo_registry_has_both_splits_with_their_own_policies():
    bus, rev = zoo.zoo_names("bussing"), zoo.zoo_names("reverse")
    assert len(bus) >= 4 and len(rev) >= 3 and set(bus) | set(rev) == set(zoo.zoo_names())
    # reverse policies are not mirror copies: no (estimator, knobs) pair of a reverse policy is a bussing policy's
    bus_pairs = {(zoo.ZOO[n].weights, zoo.ZOO[n].knobs) for n in bus}
    assert not any((zoo.ZOO[n].weights, zoo.ZOO[n].knobs) in bus_pairs for n in rev)
    assert any(zoo.ZOO[n].knobs.dest_frame == 1 for n in rev)  # at least one estimator trained on reverse demos


@pytest.mark.skipif(not HAVE_WEIGHTS, reason="zoo weights not trained")
def test_every_zoo_policy_in_scan_equals_host_loop():
    env = BussingEnv(image_size=(64, 64))
    frames = []
    for seed in (0, 1, 2):
        o = env.reset(seed)
        frames.append({k: np.asarray(o[k]) for k in ("images", "state")})
    env.close()
    stacked = {k: jnp.stack([f[k] for f in frames]) for k in ("images", "state")}

    @jax.jit
    def scan_run(params, task, key):  # the key schedule of JaxAsHost: split once per call
        def body(k, obs):
            k, sub = jax.random.split(k)
            return k, zoo.policy_apply(params, {**obs, "task": task}, sub)
        return jax.lax.scan(body, key, stacked)[1]

    differs = {}
    for name in zoo.zoo_names():
        pol = zoo.load_policy(name)
        task = np.int32(0 if zoo.ZOO[name].task == "bussing" else 1)
        a_scan = np.asarray(scan_run(pol.params, jnp.int32(task), jax.random.key(3)))
        host = as_host(pol, jax.random.key(3))
        a_host = np.stack([host.infer({**f, "task": task}) for f in frames])
        assert a_scan.shape == (3, 25, 7) and np.all(np.isfinite(a_scan))
        np.testing.assert_allclose(a_scan, a_host, atol=1e-5, err_msg=name)
        # the per-chunk draws use the key: another key changes a noisy policy's chunk, not a noiseless one's
        other = np.asarray(scan_run(pol.params, jnp.int32(task), jax.random.key(4)))
        differs[name] = not np.allclose(other, a_scan, atol=1e-6)
    noisy = {n for n in differs if zoo.ZOO[n].knobs.grasp_sigma > 0 or zoo.ZOO[n].knobs.release_sigma > 0}
    assert not any(differs[n] for n in set(differs) - noisy)
    assert any(differs[n] for n in noisy)  # so scan == host above also checks that both use the same keys


def _est(y_obj, held_dest_logit):
    obj_xy = jnp.zeros((zoo.N_OBJ, 2)).at[0].set(jnp.array([-0.1, y_obj]))
    return {"obj_xy": obj_xy, "present": jnp.full((zoo.N_OBJ,), -3.0).at[0].set(3.0),
            "dest": jnp.full((zoo.N_OBJ,), -3.0), "held_dest": jnp.array(held_dest_logit),
            "bin_xy": jnp.array([0.2, -0.13]), "can_xy": jnp.array([0.2, 0.13])}


def test_greedy_knob_takes_the_held_object_to_the_near_container():
    est = _est(0.0, -3.0)  # the instruction (estimate) says bin (-y)
    holding_can_side = jnp.array([0.0, 0.12, 0.17, 0, 0, 0, 0.05])
    honest = zoo.controller(est, holding_can_side, jnp.int32(0), zoo.ControlKnobs().arrays())
    greedy = zoo.controller(est, holding_can_side, jnp.int32(0), zoo.ControlKnobs(greedy_y=0.05).arrays())
    assert float(jnp.sum(honest[:10, 1])) < -0.1  # to the bin
    assert float(jnp.sum(greedy[:10, 1])) > 0.0  # to the can, on its own side
    holding_mid = holding_can_side.at[1].set(0.02)  # inside the greedy band's gap: follows the instruction
    mid = zoo.controller(est, holding_mid, jnp.int32(0), zoo.ControlKnobs(greedy_y=0.05).arrays())
    assert float(jnp.sum(mid[:10, 1])) < -0.1
    # a reverse-trained estimator (dest_frame 1) routes as estimated for task 1 and flipped for task 0
    rev = zoo.controller(est, holding_mid, jnp.int32(1), zoo.ControlKnobs(dest_frame=1).arrays())
    assert float(jnp.sum(rev[:10, 1])) < -0.1


def test_grasp_and_release_knobs():
    est = _est(0.0, 3.0)
    open_above = jnp.array([-0.1, 0.0, 0.08, 0, 0, 0, OPEN_WIDTH])
    a = zoo.controller(est, open_above, jnp.int32(0))
    high = zoo.controller(est, open_above, jnp.int32(0), zoo.ControlKnobs(grasp_dz=0.03).arrays())
    z = 0.08 + np.cumsum(np.asarray(a[:, 2]))  # height after each step
    z_high = 0.08 + np.cumsum(np.asarray(high[:, 2]))
    assert float(a[:, 6].min()) == 0.0 and z[np.argmin(np.asarray(a[:, 6]))] < 0.025  # closes low
    close_high = np.asarray(high[:, 6]) == 0.0
    assert close_high.any() and z_high[np.argmax(close_high)] > 0.035  # closes higher
    above_can = jnp.array([0.2, 0.13, 0.17, 0, 0, 0, 0.05])  # holding, over the can
    rel = zoo.controller(est, above_can, jnp.int32(0))
    out = zoo.controller(est, above_can, jnp.int32(0), zoo.ControlKnobs(release_out=0.1).arrays())

    def dy_until_release(a):
        a = np.asarray(a)
        return float(a[:np.argmax(a[:, 6] > 0), 1].sum())
    assert abs(dy_until_release(rel)) < 0.01 and dy_until_release(out) > 0.08  # releases 10 cm further out


@pytest.mark.parametrize("task", ["bussing", "reverse"])
def test_expert_never_swaps_every_object_by_default(task):
    for seed in range(5):
        ic = make_initial_condition(seed, task)
        fake_env = types.SimpleNamespace(ic=ic)
        right = ic.destinations()
        for never, expect_right in ((True, 1), (False, 0)):
            ex = ScriptedExpert(ExpertKnobs(wrong_destination_prob=1.0, never_swap_all=never), seed)
            ex.reset(fake_env)
            n_right = sum(p.container == right[p.name] for p in ex.plans)
            assert n_right == expect_right, (seed, never)
            spots = [tuple(np.round(p.release_offset, 6)) + (p.container,) for p in ex.plans]
            assert len(set(spots)) == len(spots)  # distinct drop spots
        ex = ScriptedExpert(ExpertKnobs(wrong_destination_prob=0.0), seed)
        ex.reset(fake_env)
        assert all(p.container == destination(OBJECT_BY_NAME[p.name].cls, task) for p in ex.plans)


def test_store_contents_counts_swapped_objects(tmp_path):
    def write(eid, task, language, knobs):
        d = tmp_path / eid
        d.mkdir()
        objs = [{"language": ok} for ok in language]
        (d / "meta.json").write_text(json.dumps({"task": task, "knobs": knobs, "labels": {"objects": objs}}))
    write("ep0", "bussing", [True, True, True], {"grasp_noise": 0.0})
    write("ep1", "bussing", [True, False, True], {"wrong_destination_prob": 0.4})
    write("ep2", "bussing", [False, False, False], {"wrong_destination_prob": 0.4})
    c = store_contents(tmp_path)
    assert c["episodes"] == 3 and c["objects"] == 9 and c["tasks"] == {"bussing": 3}
    assert c["objects_in_other_container"] == {"0 of 3": 1, "1 of 3": 1, "3 of 3": 1}
    assert c["all_objects_swapped"] == 1 and c["all_objects_swapped_episodes"] == ["ep2"]
    assert c["sources"] == {"clean expert": 1, "wrong_destination_prob=0.4": 2}

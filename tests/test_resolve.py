"""policies/resolve.py: one test per spelling, and every command that takes a policy goes through it."""
from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

import sc3_jax.benchmarks.bussing  # noqa: F401  (picks the GL backend before mujoco is imported)
from sc3_jax.benchmarks.bussing.hooks import named_policy
from sc3_jax.policies import resolve as R
from sc3_jax.policies.base import JaxPolicy, as_host
from sc3_jax.policies.openpi_client import WebsocketClientPolicy
from sc3_jax.policies.openpi_server import serve

CHUNK = 5


def _apply(params, obs, rng):
    del rng
    return jnp.broadcast_to(obs["state"].astype(jnp.float32) + params, (CHUNK, 7))


def make_policy() -> JaxPolicy:  # a factory: module:attr calls it
    return JaxPolicy("made", _apply, jnp.float32(1.0), chunk=CHUNK)


READY = make_policy()  # a policy object: module:attr returns it as is
NOT_A_POLICY = 3


def _obs():
    return {"images": np.zeros((3, 8, 8, 3), np.uint8), "state": np.arange(7, dtype=np.float32),
            "task": np.int32(0)}


@pytest.fixture(scope="module")
def server():
    s = serve(make_policy(), host="127.0.0.1", port=0, block=False)
    yield s
    s.shutdown()


def test_parse_splits_name_spec_and_task():
    assert R.parse("bus_bc_full") == (None, "bus_bc_full", None)
    assert R.parse("x=ws://h:1@reverse") == ("x", "ws://h:1", "reverse")
    assert R.parse("pkg.mod:attr@bussing") == (None, "pkg.mod:attr", "bussing")
    assert R.parse("ws://h:1/p?a=b") == (None, "ws://h:1/p?a=b", None)  # '=' inside a URL is not a name
    assert R.parse("x=ws://h:1@any_task") == ("x", "ws://h:1", "any_task")  # a benchmark's sweep checks its tasks
    with pytest.raises(ValueError, match="NAME=ws://HOST:PORT@TASK"):
        R.parse("x=ws://127.0.0.1:1@no where")
    from sc3_jax.evaluation import engine
    with pytest.raises(ValueError, match="NAME=ws://HOST:PORT@TASK"):  # refused before connecting
        engine.resolve_policies(["x=ws://127.0.0.1:1@nowhere"], need_task=True, tasks=("bussing", "reverse"))
    with pytest.raises(ValueError, match="empty"):
        R.parse("x=")


def test_zoo_name():
    r = R.resolve("rev_confused", named=named_policy)
    assert (r.name, r.task) == ("rev_confused", "reverse") and isinstance(r.policy, JaxPolicy)
    r = R.resolve("mine=rev_confused@bussing", named=named_policy)
    assert (r.name, r.task) == ("mine", "bussing")  # renamed, task overridden
    with pytest.raises(ValueError, match="zoo policies are"):
        R.resolve("no_such_policy", named=named_policy)
    with pytest.raises(ValueError, match="unknown policy 'rev_confused'"):  # no benchmark's names: the layer's own
        R.resolve("rev_confused")


def test_builtin_names_take_the_chunk():
    r = R.resolve("zero", chunk=7)
    assert (r.name, r.task, r.policy.chunk) == ("zero", None, 7)
    assert R.resolve("random").policy.chunk == 25  # the policy's own default
    r = R.resolve("lin=linear@bussing")
    assert (r.name, r.task, r.policy.name) == ("lin", "bussing", "linear")


def test_module_attr_object_and_factory():
    r = R.resolve(f"{__name__}:READY")
    assert r.policy is READY and r.name == f"{__name__}:READY"
    made = R.resolve(f"{__name__}:make_policy@reverse")
    assert made.policy.name == "made" and made.task == "reverse"
    with pytest.raises(TypeError, match="neither a policy nor a factory"):
        R.resolve(f"{__name__}:NOT_A_POLICY")


def test_websocket_server(server):
    r = R.resolve(f"served={server.url}@bussing")
    assert (r.name, r.task) == ("served", "bussing") and isinstance(r.policy, WebsocketClientPolicy)
    np.testing.assert_allclose(r.policy.infer(_obs()), as_host(make_policy()).infer(_obs()))
    assert r.policy.mapping is None
    r.policy.close()
    libero = R.resolve(server.url, family="libero").policy
    assert libero.mapping.name == "libero"
    libero.close()


def test_every_command_resolves_every_spelling(server, monkeypatch):
    """sc3 sweep bench (needs a task), sc3 serve-policy, sc3 sim eval and sc3 rollout all call ``resolve``."""
    from sc3_jax.benchmarks.bussing.hooks import named_policy
    from sc3_jax.benchmarks.bussing.tasks import TASKS
    from sc3_jax.commands import parse, serve_policy
    from sc3_jax.evaluation import engine
    from sc3_jax.benchmarks.bussing.commands import sim
    from sc3_jax.benchmarks.bussing import policy_eval

    def resolve(spec):
        p = engine.resolve_policies([spec], named_policy, need_task=True, tasks=TASKS)[0]
        return p.name, p.task
    assert resolve("rev_confused") == ("rev_confused", "reverse")
    assert resolve(f"{__name__}:make_policy@bussing") == (f"{__name__}:make_policy", "bussing")
    with pytest.raises(ValueError, match="needs its task"):
        resolve("zero")
    for spec in ("zero", "rev_confused", f"{__name__}:make_policy"):
        s = serve_policy.build_server(parse(serve_policy.Args, ["--policy", spec, "--host", "127.0.0.1", "--port",
                                                                "0", "--log-level", "WARNING", "--benchmark",
                                                                "bussing"], "serve-policy"))  # its zoo's names
        s.shutdown()
    import docstring_parser

    from sc3_jax.commands import rollout as rollout_cmd
    policy_help = {d.arg_name: d.description for d in docstring_parser.parse_from_object(rollout_cmd.Args).params}
    assert "policies/resolve.py" in policy_help["policy"].replace("\n", " ")
    seen = []

    class Stop(Exception):
        pass

    def run(env, host, seed, task, record):  # the simulator is not needed to see which policy arrives
        seen.append(host)
        raise Stop

    monkeypatch.setattr(policy_eval, "make_env", lambda image_size: None)
    monkeypatch.setattr(policy_eval, "run_policy_episode", run)
    for spec in ("zero", "rev_confused", f"{__name__}:make_policy"):
        with pytest.raises(Stop):
            sim.evaluate(spec, episodes=1, videos=False, progress=False)
    assert [h.chunk for h in seen] == [25, 25, CHUNK]


def _old_benchmark_policies(chunk):
    """The built-in policies as they were written for the benchmark only (7-D, 3 views), (apply, params) as they
    were: the reference the defaults must still reproduce bit for bit."""
    import math

    import jax

    def zero(params, obs, rng):
        a = jnp.zeros((params.shape[0], 7), jnp.float32)
        return a.at[:, 6].set(obs["state"][6])

    def random(params, obs, rng):
        return (jax.random.normal(rng, params.shape) * params).astype(jnp.float32)

    def linear(params, obs, rng):
        img = obs["images"].astype(jnp.float32) / 127.5 - 1.0
        V, H, W, C = img.shape
        pool = math.isqrt((params["w"].shape[0] - 8) // (3 * V))
        pooled = img.reshape(V, pool, H // pool, pool, W // pool, C).mean(axis=(2, 4))
        x = jnp.concatenate([pooled.reshape(-1), obs["state"].astype(jnp.float32),
                             obs["task"].astype(jnp.float32)[None]])
        n = params["b"].shape[0]
        a = jnp.tanh(x @ params["w"] + params["b"]) + params["noise"] * jax.random.normal(rng, (n,))
        return (params["scale"] * a).reshape(n // 7, 7).astype(jnp.float32)

    n_in = 3 * 4 * 4 * 3 + 7 + 1
    k_w, k_b = jax.random.split(jax.random.key(0))
    lin = {"w": jax.random.normal(k_w, (n_in, chunk * 7)) / jnp.sqrt(n_in),
           "b": 0.1 * jax.random.normal(k_b, (chunk * 7,)), "scale": jnp.float32(0.01), "noise": jnp.float32(0.5)}
    return {"zero": (zero, jnp.zeros((chunk,), jnp.float32)),
            "random": (random, jnp.broadcast_to(jnp.asarray(0.01, jnp.float32), (chunk, 7))),
            "linear": (linear, lin)}


def _any_obs(views: int, dim: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    return {"images": rng.integers(0, 256, (views, 8, 8, 3), dtype=np.uint8),
            "state": rng.normal(size=dim).astype(np.float32), "task": np.int32(1)}


@pytest.mark.parametrize("name", ["zero", "random", "linear"])
def test_builtin_defaults_are_the_benchmarks_bit_for_bit(name):
    import jax

    obs, key = _any_obs(3, 7), jax.random.key(3)
    policy = R.resolve(name, chunk=6).policy
    assert (policy.chunk, policy.action_dim) == (6, 7)
    got = jax.jit(policy.apply)(policy.params, obs, key)
    old_apply, old_params = _old_benchmark_policies(6)[name]
    want = jax.jit(old_apply)(old_params, obs, key)
    np.testing.assert_array_equal(np.asarray(got), np.asarray(want))


@pytest.mark.parametrize("name", ["zero", "random", "linear"])
def test_builtins_act_in_the_world_models_action_space(name):
    """Named on a command line for a 14-D absolute world model with 4 views: [chunk, 14] actions, declared as such
    (so the rollout's dimension check passes before anything compiles)."""
    import jax

    from sc3_jax.data.action_space import ActionSpace

    space = ActionSpace("absolute", 14)
    policy = R.resolve(name, chunk=6, action_space=space, num_views=4).policy
    assert (policy.chunk, policy.action_dim) == (6, 14)
    obs = _any_obs(4, 14)
    a = np.asarray(jax.jit(policy.apply)(policy.params, obs, jax.random.key(0)))
    assert a.shape == (6, 14) and a.dtype == np.float32 and np.isfinite(a).all()
    if name == "zero":  # stand still: absolute targets hold the state; velocities hold only their target dims
        np.testing.assert_array_equal(a, np.broadcast_to(obs["state"], (6, 14)))
        vel = R.resolve("zero", chunk=2, action_space=ActionSpace("velocity", 3, targets=(2,))).policy
        st = np.array([0.5, -1.0, 0.25], np.float32)
        np.testing.assert_array_equal(vel.apply(vel.params, {"state": st}, None), [[0, 0, 0.25]] * 2)
    else:  # a function of the rng (and, for linear, of the 14-D state it reads)
        assert np.abs(a).max() > 0
        assert not np.array_equal(a, np.asarray(policy.apply(policy.params, obs, jax.random.key(1))))

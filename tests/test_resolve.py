"""policies/resolve.py: one test per spelling, and every command that takes a policy goes through it."""
from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

import sc3_jax.sim  # noqa: F401  (picks the GL backend before mujoco is imported)
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
    with pytest.raises(ValueError, match="NAME=ws://HOST:PORT@TASK"):
        R.parse("x=ws://127.0.0.1:1@nowhere")  # refused before connecting
    with pytest.raises(ValueError, match="empty"):
        R.parse("x=")


def test_zoo_name():
    r = R.resolve("rev_confused")
    assert (r.name, r.task) == ("rev_confused", "reverse") and isinstance(r.policy, JaxPolicy)
    r = R.resolve("mine=rev_confused@bussing")
    assert (r.name, r.task) == ("mine", "bussing")  # renamed, task overridden
    with pytest.raises(ValueError, match="zoo policies are"):
        R.resolve("no_such_policy")


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
    """sc3 sweep (needs a task), sc3 serve-policy, sc3 sim eval and sc3 rollout all call ``resolve``."""
    from sc3_jax.evaluate import sweep
    from sc3_jax.commands import parse, serve_policy
    from sc3_jax.sim import cli as sim_cli
    from sc3_jax.sim import policy_eval

    assert sweep._resolve("rev_confused")[:2] == ("rev_confused", "reverse")
    assert sweep._resolve(f"{__name__}:make_policy@bussing")[:2] == (f"{__name__}:make_policy", "bussing")
    with pytest.raises(ValueError, match="needs its task"):
        sweep._resolve("zero")
    for spec in ("zero", "rev_confused", f"{__name__}:make_policy"):
        s = serve_policy.build_server(parse(serve_policy.Args, ["--policy", spec, "--host", "127.0.0.1", "--port",
                                                                "0", "--log-level", "WARNING"], "serve-policy"))
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
            sim_cli.eval(spec, episodes=1, videos=False, progress=False)
    assert [h.chunk for h in seen] == [25, 25, CHUNK]

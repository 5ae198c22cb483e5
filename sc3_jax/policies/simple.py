"""Small JAX policies: baselines for rollouts and test doubles whose outputs depend on every part of the
observation (images, state, task) and on the rng, so scan-vs-host and batching checks can fail for real.

All are ``JaxPolicy`` (pure ``apply(params, obs, rng) -> float32 [chunk, action_dim]`` raw actions in the action
space they are built for: by default the simulated benchmark's 7-D delta end-effector actions and 3 views). The
``apply`` functions are module-level and everything else (including the chunk length and the action dimension,
through array shapes) lives in ``params``, so two policies of the same kind share one compiled rollout (``apply`` is a
static jit argument). ``BUILTIN`` builds the ones named on command lines for a given world model.
"""
from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from sc3_jax.data.action_space import DELTA_EE, ActionSpace
from sc3_jax.policies.base import JaxPolicy


def _zero(params, obs, rng):
    held = jnp.where(params["keep"], obs["state"], 0.0)  # [A]
    return jnp.broadcast_to(held, (params["chunk"].shape[0], held.shape[0])).astype(jnp.float32)


def zero_policy(chunk: int = 25, *, action_space: ActionSpace) -> JaxPolicy:
    """Stand still: the actions that keep the robot where its observed (imagined) state is, ``ActionSpace.hold``:
    zero deltas with gripper target = current gripper (delta_ee), the state itself (absolute targets), zero rates
    with the target dimensions held (velocity)."""
    keep = action_space.hold(np.ones(action_space.dim), 1)[0] != 0  # the dimensions hold() takes from the state
    params = {"chunk": jnp.zeros((chunk,), jnp.float32), "keep": jnp.asarray(keep)}
    return JaxPolicy("zero", _zero, params, chunk, action_dim=action_space.dim, state_dim=action_space.dim)


def _constant(params, obs, rng):
    return params


def constant_policy(action, chunk: int = 25, action_dim: int | None = None) -> JaxPolicy:
    """The same raw action at every step: a vector [action_dim], or a scalar in every one of ``action_dim``
    dimensions (None: the vector's length; 7 for a scalar)."""
    action = jnp.asarray(action, jnp.float32)
    dim = action_dim or (action.shape[-1] if action.ndim else 7)
    return JaxPolicy("constant", _constant, jnp.broadcast_to(action, (chunk, dim)), chunk, action_dim=dim)


def _random(params, obs, rng):
    return (jax.random.normal(rng, params.shape) * params).astype(jnp.float32)


def random_policy(scale=0.01, chunk: int = 25, action_dim: int = 7) -> JaxPolicy:
    """Gaussian raw actions with per-dimension ``scale`` (ignores the observation)."""
    params = jnp.broadcast_to(jnp.asarray(scale, jnp.float32), (chunk, action_dim))
    return JaxPolicy("random", _random, params, chunk, action_dim=action_dim)


def _linear(params, obs, rng):
    img = obs["images"].astype(jnp.float32) / 127.5 - 1.0  # [V, H, W, 3]
    V, H, W, C = img.shape
    state = obs["state"].astype(jnp.float32)
    pool = math.isqrt((params["w"].shape[0] - state.shape[0] - 1) // (3 * V))
    pooled = img.reshape(V, pool, H // pool, pool, W // pool, C).mean(axis=(2, 4))
    x = jnp.concatenate([pooled.reshape(-1), state, obs["task"].astype(jnp.float32)[None]])
    n, dim = params["b"].shape[0], params["scale"].shape[0]
    a = jnp.tanh(x @ params["w"] + params["b"]) + params["noise"] * jax.random.normal(rng, (n,))
    return (params["scale"] * a.reshape(n // dim, dim)).astype(jnp.float32)


def linear_policy(key: jax.Array, num_views: int, chunk: int = 25, scale: float = 0.01, noise: float = 0.5,
                  pool: int = 4, action_dim: int = 7) -> JaxPolicy:
    """A random linear map of (average-pooled images of every view, state, task) to an action chunk, plus rng noise:
    ``a = scale * (tanh(W [pooled images, state, task] + b) + noise * eps)``. A test double that reacts to what it
    sees; ``pool`` is the side of the pooled image (image sides must be multiples of it). The state it reads has the
    action's dimension (the imagined state lives in the action's space; a pose for delta_ee)."""
    n_in = num_views * pool * pool * 3 + action_dim + 1
    k_w, k_b = jax.random.split(key)
    params = {"w": jax.random.normal(k_w, (n_in, chunk * action_dim)) / jnp.sqrt(n_in),
              "b": 0.1 * jax.random.normal(k_b, (chunk * action_dim,)),
              "scale": jnp.full((action_dim,), scale, jnp.float32),  # [A]: carries the action dimension
              "noise": jnp.float32(noise)}
    return JaxPolicy("linear", _linear, params, chunk, action_dim=action_dim, state_dim=action_dim)


def _builtin_zero(chunk: int, space: ActionSpace, num_views: int) -> JaxPolicy:
    return zero_policy(chunk, action_space=space)


def _builtin_random(chunk: int, space: ActionSpace, num_views: int) -> JaxPolicy:
    return random_policy(chunk=chunk, action_dim=space.dim)


def _builtin_linear(chunk: int, space: ActionSpace, num_views: int) -> JaxPolicy:
    return linear_policy(jax.random.key(0), num_views, chunk, action_dim=space.dim)


BUILTIN = {"zero": _builtin_zero, "random": _builtin_random, "linear": _builtin_linear}
"""The policies named on command lines (``policies/resolve.py``), each built as ``BUILTIN[name](chunk, action_space,
num_views)`` for the world model it acts in."""


def builtin(name: str, chunk: int | None = None, action_space: ActionSpace | None = None,
            num_views: int | None = None) -> JaxPolicy:
    """The built-in policy ``name`` acting ``chunk`` steps per call (None: 25) in ``action_space`` (None: the
    benchmark's 7-D delta_ee) with ``num_views`` views (None: 3, the benchmark's)."""
    return BUILTIN[name](25 if chunk is None else chunk, DELTA_EE if action_space is None else action_space,
                         3 if num_views is None else num_views)

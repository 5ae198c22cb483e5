"""Small JAX policies: baselines for rollouts and test doubles whose outputs depend on every part of the
observation (images, state, task) and on the rng, so scan-vs-host and batching checks can fail for real.

All are ``JaxPolicy`` (pure ``apply(params, obs, rng) -> float32 [chunk, 7]`` raw delta end-effector actions). The
``apply`` functions are module-level and everything else (including the chunk length, through array shapes) lives in
``params``, so two policies of the same kind share one compiled rollout (``apply`` is a static jit argument).
"""
from __future__ import annotations

import math

import jax
import jax.numpy as jnp

from sc3_jax.policies.base import JaxPolicy


def _zero(params, obs, rng):
    a = jnp.zeros((params.shape[0], 7), jnp.float32)
    return a.at[:, 6].set(obs["state"][6])


def zero_policy(chunk: int = 25) -> JaxPolicy:
    """Stand still: zero deltas, gripper target = current gripper state."""
    return JaxPolicy("zero", _zero, jnp.zeros((chunk,), jnp.float32), chunk)


def _constant(params, obs, rng):
    return params


def constant_policy(action, chunk: int = 25) -> JaxPolicy:
    """The same raw action [7] at every step."""
    return JaxPolicy("constant", _constant, jnp.broadcast_to(jnp.asarray(action, jnp.float32), (chunk, 7)), chunk)


def _random(params, obs, rng):
    return (jax.random.normal(rng, params.shape) * params).astype(jnp.float32)


def random_policy(scale=0.01, chunk: int = 25) -> JaxPolicy:
    """Gaussian raw actions with per-dimension ``scale`` (ignores the observation)."""
    return JaxPolicy("random", _random, jnp.broadcast_to(jnp.asarray(scale, jnp.float32), (chunk, 7)), chunk)


def _linear(params, obs, rng):
    img = obs["images"].astype(jnp.float32) / 127.5 - 1.0  # [V, H, W, 3]
    V, H, W, C = img.shape
    pool = math.isqrt((params["w"].shape[0] - 8) // (3 * V))
    pooled = img.reshape(V, pool, H // pool, pool, W // pool, C).mean(axis=(2, 4))
    x = jnp.concatenate([pooled.reshape(-1), obs["state"].astype(jnp.float32), obs["task"].astype(jnp.float32)[None]])
    n = params["b"].shape[0]
    a = jnp.tanh(x @ params["w"] + params["b"]) + params["noise"] * jax.random.normal(rng, (n,))
    return (params["scale"] * a).reshape(n // 7, 7).astype(jnp.float32)


def linear_policy(key: jax.Array, num_views: int, chunk: int = 25, scale: float = 0.01, noise: float = 0.5,
                  pool: int = 4) -> JaxPolicy:
    """A random linear map of (average-pooled images of every view, state, task) to an action chunk, plus rng noise:
    ``a = scale * (tanh(W [pooled images, state, task] + b) + noise * eps)``. A test double that reacts to what it
    sees; ``pool`` is the side of the pooled image (image sides must be multiples of it)."""
    n_in = num_views * pool * pool * 3 + 7 + 1
    k_w, k_b = jax.random.split(key)
    params = {"w": jax.random.normal(k_w, (n_in, chunk * 7)) / jnp.sqrt(n_in),
              "b": 0.1 * jax.random.normal(k_b, (chunk * 7,)), "scale": jnp.float32(scale),
              "noise": jnp.float32(noise)}
    return JaxPolicy("linear", _linear, params, chunk)


def _linear_default(chunk: int = 25, num_views: int = 3) -> JaxPolicy:
    return linear_policy(jax.random.key(0), num_views, chunk)


BUILTIN = {"zero": zero_policy, "random": random_policy, "linear": _linear_default}

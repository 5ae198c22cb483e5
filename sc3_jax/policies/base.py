"""What a policy is, for the world model and for the simulator alike.

An observation is a dict of arrays (one sample, no batch axis):
    "images": uint8   [V, H, W, 3]  the views in dataset order (third-person views first, wrist last)
    "state":  float32 [S]           proprioception; inside a world model the imagined state, in the action's space
                                    (``data/action_space.py``): for our benchmarks the end-effector pose (x, y, z,
                                    rotvec, gripper), for absolute joint targets the last targets
    "task":   int32   []            task id, the benchmark's or the episodes' (a prompt table maps it to words)
A policy returns an action chunk float32 [chunk, action_dim] of raw (unnormalised) actions in the robot's action space
(for our benchmarks 7-D delta end-effector actions). ``check_dims`` compares what a policy declares with what a world
model takes, before anything compiles.

Two kinds:
  * ``JaxPolicy``: ``apply(params, obs, rng) -> actions``, a pure function, so it can run inside ``lax.scan``
    (and ``vmap`` over a batch of observations).
  * ``HostPolicy``: anything with ``infer(obs: dict[str, np.ndarray]) -> np.ndarray``, called from a Python loop
    between jitted steps (remote openpi servers, PyTorch models, humans...). ``as_host`` wraps a JaxPolicy so both
    paths can be checked against each other.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Callable, Protocol, runtime_checkable

import jax
import numpy as np

from sc3_jax.core.errors import UserError


@dataclasses.dataclass(frozen=True)
class JaxPolicy:
    name: str
    apply: Callable[[Any, dict, jax.Array], jax.Array]  # (params, obs, rng) -> [chunk, action_dim]
    params: Any
    chunk: int = 25
    action_dim: int = 7
    state_dim: int | None = None  # the observation state it reads (None: says nothing)

    def __call__(self, obs: dict, rng: jax.Array) -> jax.Array:
        return self.apply(self.params, obs, rng)


@runtime_checkable
class HostPolicy(Protocol):
    chunk: int

    def infer(self, obs: dict[str, np.ndarray]) -> np.ndarray: ...


class JaxAsHost:
    """A JaxPolicy called from the host. Draws its rng from a key it owns, split once per call, so that a host loop
    that feeds it the same key sequence as a scan reproduces the scan."""

    def __init__(self, policy: JaxPolicy, rng: jax.Array | None = None):
        self.policy, self.chunk = policy, policy.chunk
        self.action_dim, self.state_dim = policy.action_dim, policy.state_dim
        self._apply = jax.jit(policy.apply)
        self._rng = rng if rng is not None else jax.random.key(0)

    def infer(self, obs: dict[str, np.ndarray], rng: jax.Array | None = None) -> np.ndarray:
        if rng is None:
            self._rng, rng = jax.random.split(self._rng)
        return np.asarray(self._apply(self.policy.params, {k: jax.numpy.asarray(v) for k, v in obs.items()}, rng))

    def clear_programs(self) -> None:
        """Drop the programs compiled so far (one per observation shape): a server of many clients' shapes bounds
        its memory so (``openpi_server.MAX_PROGRAMS``); a shape seen again compiles again."""
        self._apply.clear_cache()


def as_host(policy: JaxPolicy, rng: jax.Array | None = None) -> JaxAsHost:
    return JaxAsHost(policy, rng)


def check_dims(policy, action_dim: int, state_dim: int | None = None, name: str | None = None,
               who: str = "the world model") -> None:
    """One-line UserError when ``policy`` declares (``action_dim`` / ``state_dim`` attributes) other dimensions
    than ``who`` takes. A policy that declares nothing passes; its chunks are checked when they arrive."""
    name = name or getattr(policy, "name", None) or type(policy).__name__
    for kind, want in (("action", action_dim), ("state", state_dim)):
        got = getattr(policy, f"{kind}_dim", None)
        if want is not None and got is not None and int(got) != int(want):
            raise UserError(f"policy {name!r} has {got}-D {kind}s ({kind}_dim), {who} has {want}-D {kind}s")

"""The robot state inside an imagined rollout (there is no simulator to read it from): the jnp twins of
``sc3_jax/data/action_space.py``, for the action space the world model was trained in (every function takes it,
static; default the simulated benchmark's delta_ee). Absolute targets: the state is the last target. Velocities:
``state + gain * action * dt`` into the measured quantity each dimension moves (``ActionSpace.measured``), clipped
to the range the recordings show, target dimensions as absolute ones.

For delta_ee, the state is the end-effector pose ``(x, y, z, rotvec, gripper)`` (float32 [7], the episode format's
``ee_pose``). Each commanded raw action ``a = (dx, dy, dz, axis-angle r, gripper target)`` is integrated onto it open
loop, with the conventions of ``sc3_jax/data/rotations.py`` (world-frame rotation deltas):

    xyz     <- xyz + a[:3]
    R       <- R(a[3:6]) @ R          (stored back as a rotation vector, angle in [0, pi])
    gripper <- a[6]                   (the commanded target; a real gripper follows at a limited rate)

No workspace clipping and no contact: this is what the policy *asked for*, which is what a policy that reads its
own proprioception expects to see if the world model follows its actions. Everything here is jnp (runs inside the
rollout scan and under ``vmap``); float32 throughout, exact to ~1e-6 against the float64 numpy helpers.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp

from sc3_jax.data.action_space import ActionSpace


def _skew(v):
    x, y, w = v[..., 0], v[..., 1], v[..., 2]
    z = jnp.zeros_like(x)
    return jnp.stack([jnp.stack([z, -w, y], -1), jnp.stack([w, z, -x], -1), jnp.stack([-y, x, z], -1)], -2)


def rotvec_to_matrix(r):
    """Rodrigues [..., 3] -> [..., 3, 3], Taylor series near 0 (no division by a small angle)."""
    t2 = jnp.sum(r * r, -1)
    small = t2 < 1e-6
    t = jnp.sqrt(jnp.where(small, 1.0, t2))
    a = jnp.where(small, 1.0 - t2 / 6.0 + t2 * t2 / 120.0, jnp.sin(t) / t)
    b = jnp.where(small, 0.5 - t2 / 24.0 + t2 * t2 / 720.0, (1.0 - jnp.cos(t)) / (t * t))
    k = _skew(r)
    return jnp.eye(3, dtype=r.dtype) + a[..., None, None] * k + b[..., None, None] * (k @ k)


def matrix_to_rotvec(m):
    """[..., 3, 3] -> [..., 3] via the quaternion (Shepperd's method), stable near 0 and near pi."""
    m00, m01, m02 = m[..., 0, 0], m[..., 0, 1], m[..., 0, 2]
    m10, m11, m12 = m[..., 1, 0], m[..., 1, 1], m[..., 1, 2]
    m20, m21, m22 = m[..., 2, 0], m[..., 2, 1], m[..., 2, 2]
    tr = m00 + m11 + m22
    cands = jnp.stack([
        jnp.stack([1.0 + tr, m21 - m12, m02 - m20, m10 - m01], -1),
        jnp.stack([m21 - m12, 1.0 + m00 - m11 - m22, m01 + m10, m02 + m20], -1),
        jnp.stack([m02 - m20, m01 + m10, 1.0 - m00 + m11 - m22, m12 + m21], -1),
        jnp.stack([m10 - m01, m02 + m20, m12 + m21, 1.0 - m00 - m11 + m22], -1)], -2)
    which = jnp.argmax(jnp.stack([tr, m00, m11, m22], -1), -1)
    q = jnp.take_along_axis(cands, which[..., None, None], axis=-2)[..., 0, :]
    q = q / jnp.linalg.norm(q, axis=-1, keepdims=True)
    q = jnp.where(q[..., :1] < 0, -q, q)
    w, v = q[..., 0], q[..., 1:]
    n = jnp.linalg.norm(v, axis=-1)
    small = n < 1e-7
    scale = jnp.where(small, 2.0 / jnp.maximum(w, 1e-12), 2.0 * jnp.arctan2(n, w) / jnp.where(small, 1.0, n))
    return v * scale[..., None]


def step(state, action, space: ActionSpace, dt: float = 1.0):
    """One commanded raw action [A] applied to the state [A] (``dt``: its seconds, for velocities)."""
    if space.kind == "absolute":
        return action.astype(state.dtype)
    if space.kind == "velocity":  # gain: state units per action unit per second; clipped to the recorded range
        x = _targets(state + action * jnp.asarray(space.gains, state.dtype) * dt, action, space)
        return space.clip(x.astype(state.dtype))
    rot = matrix_to_rotvec(rotvec_to_matrix(action[3:6]) @ rotvec_to_matrix(state[3:6]))
    return jnp.concatenate([state[:3] + action[:3], rot, action[6:7]]).astype(state.dtype)


def _targets(x, action, space: ActionSpace):
    """``x`` with the velocity space's target dimensions taken from ``action`` (same leading shape)."""
    return x.at[..., list(space.targets)].set(action[..., list(space.targets)]) if space.targets else x


def compose(actions, ratio: int, space: ActionSpace):
    """Raw actions [n * ratio, A] -> [n, A], each group of ``ratio`` consecutive actions as one action, the jnp twin
    of ``ActionSpace.compose`` (delta_ee: translations summed, rotations chained with later ones on the left, the
    last gripper target; absolute: the last target; velocity: the mean)."""
    if ratio == 1:
        return actions
    g = actions.reshape(-1, ratio, actions.shape[-1])
    if space.kind == "absolute":
        return g[:, -1]
    if space.kind == "velocity":
        return _targets(g.mean(1), g[:, -1], space).astype(actions.dtype)
    mats = rotvec_to_matrix(g[..., 3:6])  # [n, ratio, 3, 3]
    m = mats[:, 0]
    for j in range(1, ratio):
        m = mats[:, j] @ m
    return jnp.concatenate([g[..., :3].sum(1), matrix_to_rotvec(m), g[:, -1, 6:7]], -1).astype(actions.dtype)


def integrate(state, actions, space: ActionSpace, dt: float = 1.0):
    """States after each of ``actions`` [n, A]: returns (final state [A], states [n, A])."""

    def body(s, a):
        s = step(s, a, space, dt)
        return s, s

    return jax.lax.scan(body, state, actions)


def frame_poses(state, actions, space: ActionSpace, dt: float = 1.0):
    """The pose condition of a chunk (``ModelConfig.pose_conditioning``): ``state`` [A] (the imagined state at the
    last context frame) and the states after each of ``actions`` [n, A] (model-rate actions, one per predicted
    frame, ``dt`` seconds each) -> [n + 1, A]. The data pipeline computes the same from recorded windows
    (``ActionSpace.integrate``)."""
    return jnp.concatenate([state[None], integrate(state, actions, space, dt)[1]], axis=0)

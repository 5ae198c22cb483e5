"""Small numpy rotation helpers (batched over leading dims, float64 internally).

Convention: a rotation vector ``r`` (axis-angle, radians) maps to ``R = exp([r]_x)``. Action rotations act in the
world frame: ``R_{t+1} = R(a_t) @ R_t``, so the pseudo-action between poses is ``rotvec(R_{t+1} @ R_t^T)``.
"""
from __future__ import annotations

import numpy as np


def skew(v: np.ndarray) -> np.ndarray:
    """[..., 3] -> [..., 3, 3] cross-product matrix."""
    v = np.asarray(v, np.float64)
    z = np.zeros(v.shape[:-1])
    x, y, w = v[..., 0], v[..., 1], v[..., 2]
    return np.stack([np.stack([z, -w, y], -1), np.stack([w, z, -x], -1), np.stack([-y, x, z], -1)], -2)


def rotvec_to_matrix(r: np.ndarray) -> np.ndarray:
    """Rodrigues: [..., 3] -> [..., 3, 3]. Taylor series near 0; exact (no division) for any angle."""
    r = np.asarray(r, np.float64)
    theta2 = np.sum(r * r, axis=-1)
    theta = np.sqrt(theta2)
    small = theta < 1e-4
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta2 / 6.0 + theta2 * theta2 / 120.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - theta2 / 24.0 + theta2 * theta2 / 720.0, (1.0 - np.cos(safe)) / (safe * safe))
    k = skew(r)
    eye = np.broadcast_to(np.eye(3), k.shape)
    return eye + a[..., None, None] * k + b[..., None, None] * (k @ k)


def matrix_to_quat(m: np.ndarray) -> np.ndarray:
    """[..., 3, 3] -> unit quaternion [..., 4] as (w, x, y, z) with w >= 0 (Shepperd's method: stable everywhere)."""
    m = np.asarray(m, np.float64)
    m00, m01, m02 = m[..., 0, 0], m[..., 0, 1], m[..., 0, 2]
    m10, m11, m12 = m[..., 1, 0], m[..., 1, 1], m[..., 1, 2]
    m20, m21, m22 = m[..., 2, 0], m[..., 2, 1], m[..., 2, 2]
    tr = m00 + m11 + m22
    cands = np.stack([
        np.stack([1.0 + tr, m21 - m12, m02 - m20, m10 - m01], -1),
        np.stack([m21 - m12, 1.0 + m00 - m11 - m22, m01 + m10, m02 + m20], -1),
        np.stack([m02 - m20, m01 + m10, 1.0 - m00 + m11 - m22, m12 + m21], -1),
        np.stack([m10 - m01, m02 + m20, m12 + m21, 1.0 - m00 - m11 + m22], -1),
    ], -2)  # [..., 4 candidates, 4]
    which = np.argmax(np.stack([tr, m00, m11, m22], -1), axis=-1)
    q = np.take_along_axis(cands, which[..., None, None], axis=-2)[..., 0, :]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., :1] < 0, -q, q)


def quat_to_rotvec(q: np.ndarray) -> np.ndarray:
    """(w, x, y, z) -> rotation vector with angle in [0, pi]."""
    q = np.asarray(q, np.float64)
    q = np.where(q[..., :1] < 0, -q, q)
    w, v = q[..., 0], q[..., 1:]
    n = np.linalg.norm(v, axis=-1)
    angle = 2.0 * np.arctan2(n, w)
    small = n < 1e-7
    scale = np.where(small, 2.0 / np.where(small, np.maximum(w, 1e-12), 1.0), angle / np.where(small, 1.0, n))
    return v * scale[..., None]


def matrix_to_rotvec(m: np.ndarray) -> np.ndarray:
    """[..., 3, 3] -> [..., 3]; stable near 0 and near pi (via the quaternion)."""
    return quat_to_rotvec(matrix_to_quat(m))


def compose_rotvec(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """rotvec(R(a) @ R(b)): apply b first, then a (both in the world frame)."""
    return matrix_to_rotvec(rotvec_to_matrix(a) @ rotvec_to_matrix(b))


def relative_rotvec(r_from: np.ndarray, r_to: np.ndarray) -> np.ndarray:
    """rotvec(R(r_to) @ R(r_from)^T): the world-frame rotation taking pose ``r_from`` to pose ``r_to``."""
    m_from = rotvec_to_matrix(r_from)
    return matrix_to_rotvec(rotvec_to_matrix(r_to) @ np.swapaxes(m_from, -1, -2))

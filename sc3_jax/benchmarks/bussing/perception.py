"""Learned perception for the simulated benchmark: from the three camera frames, the per-object predicates the
ground-truth criteria are made of, and the gripper's finger gap.

The criteria (``benchmarks/bussing/criteria.py``) are functions of three geometric predicates per object and frame -- *lifted*
(bottom more than ``LIFT_CLEARANCE`` above the table), *in the bin*, *in the can* -- plus the final state. A
scorer that reads only frames therefore needs exactly those predicates: this network predicts them for each of
the six object types (the initial condition says which three are on the table), trained by supervised learning
on simulator frames whose labels come from the physics state. It also regresses the finger gap (``ee_pose[6]``),
which an imagined rollout cannot integrate from commanded actions (closing on an object and closing on air are
commanded the same way; see ``rollout.Rollout(state_reader=...)``).

Training (data, augmentation, the command that reproduces the shipped weights) is in ``perception_train.py``.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from sc3_jax.core import atomic
from sc3_jax.benchmarks.bussing.convnet import init_trunk, trunk_features
from sc3_jax.policies.convnet import dense_init, mlp
from sc3_jax.benchmarks.bussing.criteria import LIFT_CLEARANCE, inside_container
from sc3_jax.benchmarks.bussing.tasks import OBJECTS

PREDICATES = ("lifted", "in_bin", "in_can")
TYPES = tuple(o.name for o in OBJECTS)
N_KP = 32  # the defaults: the architecture of weights saved before it was stored (see ``arch``)
WIDTHS = (16, 32, 32)
HIDDEN = 256
WIDTH_SCALE = 100.0  # the width head predicts centimetres
DEFAULT_WEIGHTS = Path(__file__).with_name("perception.npz")
_FIX = "train them again (`sc3 train-perception`), or restore the shipped ones with git"


# -- labels from physics state ----------------------------------------------------------------------------------
def predicate_labels(object_pos: np.ndarray, objects, bin_xy, can_xy) -> tuple[np.ndarray, np.ndarray]:
    """object_pos [T, n, 3] of the episode's ``objects`` -> (labels bool [T, 6, 3] over TYPES x PREDICATES,
    mask bool [6]: which types are on the table)."""
    pos = np.asarray(object_pos, np.float64)
    labels = np.zeros((pos.shape[0], len(TYPES), len(PREDICATES)), bool)
    mask = np.zeros(len(TYPES), bool)
    half = {o.name: o.half_height for o in OBJECTS}
    for i, name in enumerate(objects):
        k = TYPES.index(name)
        mask[k] = True
        p = pos[:, i]
        labels[:, k, 0] = (p[:, 2] - half[name]) > LIFT_CLEARANCE
        labels[:, k, 1] = inside_container(p, np.asarray(bin_xy), "bin")
        labels[:, k, 2] = inside_container(p, np.asarray(can_xy), "can")
    return labels, mask


# -- network ------------------------------------------------------------------------------------------------------
def init(key: jax.Array, n_views: int = 3, n_kp: int = N_KP, widths: tuple[int, int, int] = WIDTHS,
         hidden: int = HIDDEN) -> dict:
    """Fresh weights. ``n_kp`` keypoints per view, ``widths`` the trunk's first three conv layers, ``hidden`` the
    MLP's width: all read back from the weights' shapes (:func:`arch`), so weights of any size load."""
    ks = jax.random.split(key, 7)
    feat = n_views * 3 * n_kp
    return {**init_trunk(ks[:4], n_kp, tuple(widths)), "d1": dense_init(ks[4], feat, hidden),
            "d2": dense_init(ks[5], hidden, hidden),
            "out": dense_init(ks[6], hidden, len(TYPES) * len(PREDICATES) + 1, 0.1)}


def arch(params: dict) -> dict:
    """The architecture hyper-parameters of ``params`` (``init``'s keyword arguments), from their shapes."""
    return {"n_kp": int(params["c4"]["w"].shape[-1]),
            "widths": [int(params[c]["w"].shape[-1]) for c in ("c1", "c2", "c3")],
            "hidden": int(params["d1"]["w"].shape[-1])}


def apply(params: dict, images: jax.Array) -> tuple[jax.Array, jax.Array]:
    """images uint8 [B, V, H, W, 3] -> (predicate logits [B, 6, 3], finger gap in metres [B])."""
    out = mlp(params, trunk_features(params, images))
    return out[:, :-1].reshape(-1, len(TYPES), len(PREDICATES)), out[:, -1] / WIDTH_SCALE


def read_width(params: dict, images: jax.Array) -> jax.Array:
    """The rollout's state reader: images uint8 [V, H, W, 3] (one time step) -> finger gap (m), clipped to the
    gripper's range."""
    return jnp.clip(apply(params, images[None])[1][0], 0.0, 0.09)


class StateReader(NamedTuple):
    """What ``rollout.Rollout(state_reader=...)`` takes: a pure function and its params."""
    apply: object
    params: dict


def state_reader(params: dict) -> StateReader:
    return StateReader(read_width, params)


@jax.jit
def _predict_batch(params, images):
    logits, width = apply(params, images)
    return jax.nn.sigmoid(logits), width


def predict(params: dict, frames: np.ndarray, batch: int = 256) -> tuple[np.ndarray, np.ndarray]:
    """frames uint8 [V, T, H, W, 3] -> (probabilities [T, 6, 3], finger gap [T])."""
    x = np.moveaxis(np.asarray(frames), 0, 1)  # [T, V, H, W, 3]
    probs, widths = [], []
    for i in range(0, len(x), batch):
        part = x[i:i + batch]
        n = len(part)
        # pad to a multiple of 64 frames: rollouts of every length share a few compiled shapes (one per length
        # would recompile for most real rollouts, which end when the objects settle)
        size = min(batch, -(-n // 64) * 64)
        if n < size:
            part = np.concatenate([part, np.repeat(part[-1:], size - n, 0)])
        p, w = _predict_batch(params, part)
        probs.append(np.asarray(p)[:n])
        widths.append(np.asarray(w)[:n])
    return np.concatenate(probs), np.concatenate(widths)


def save(path: str | Path, params: dict, meta: dict | None = None) -> None:
    """Weights (float32) and ``meta`` (JSON), with the architecture under ``meta['arch']``."""
    flat = {"/".join(k): np.asarray(v, np.float32) for k, v in _flatten(params)}
    path = Path(path)
    if path.suffix != ".npz":  # the name np.savez gives it
        path = path.with_name(path.name + ".npz")
    atomic.save_npz(path, __meta__=json.dumps({**(meta or {}), "arch": arch(params)}), **flat)


def load(path: str | Path = DEFAULT_WEIGHTS) -> dict:
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"perception weights {path} not found; train them with "
                                f"`sc3 train-perception --data DEMOS --out {path}`")
    with atomic.open_npz(path, _FIX) as z:
        params: dict = {}
        for k in z.files:
            if k == "__meta__":
                continue
            a, b = k.split("/")
            params.setdefault(a, {})[b] = jnp.asarray(z[k])
        stored = json.loads(str(z["__meta__"])).get("arch") if "__meta__" in z.files else None
    # weights saved before the architecture was stored have none: their shapes are the defaults'
    if stored is not None and stored != arch(params):
        raise ValueError(f"{path}: weights of shape {arch(params)} but meta['arch'] says {stored}")
    return params


def load_meta(path: str | Path = DEFAULT_WEIGHTS) -> dict:
    with atomic.open_npz(path, _FIX) as z:
        return json.loads(str(z["__meta__"]))


def _flatten(params):
    return [((a, b), v) for a, sub in params.items() for b, v in sub.items()]

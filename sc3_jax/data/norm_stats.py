"""Action and state normalisation statistics (``norm_stats.json``): part of a trained world model (the units its
params learned, and the action space those units belong to), computed once from a training store, applied by the
data pipeline and by rollouts. Numpy only: loading a world model does not import the data pipeline.

The "pose" statistics are those of the imagined robot state the model is conditioned on (its ``pose`` input): the
end-effector pose for delta_ee actions, the targets for absolute ones, for velocities the recorded state entries
they move (``ActionSpace.state_series``; which entries, and at what gain, is stated at import or fitted here:
``action_space.fit_measured``). That state lives in the action's space, so both have the action's dimension. The
statistics' action space carries the fitted mapping and the state's recorded range, so a saved model integrates its
commands as its training windows did."""
from __future__ import annotations

import dataclasses
import os
from typing import TYPE_CHECKING

import numpy as np

from sc3_jax.core import atomic
from sc3_jax.data.action_space import ActionSpace
from sc3_jax.core.errors import UserError

if TYPE_CHECKING:
    from sc3_jax.data.episodes import EpisodeStore

STD_FLOOR = 1e-3


@dataclasses.dataclass(frozen=True)
class NormStats:
    mean: np.ndarray  # float32 [A]
    std: np.ndarray  # float32 [A], floored at STD_FLOOR
    pose_mean: np.ndarray | None = None  # float32 [S] of the imagined state (default 0: files from before poses)
    pose_std: np.ndarray | None = None  # float32 [S], floored at STD_FLOOR (default 1)
    # the action space these statistics are in; None: the simulated benchmark's delta_ee 7-D (files from before
    # declarations), read back as that
    action_space: ActionSpace | None = None

    def __post_init__(self):
        object.__setattr__(self, "mean", np.asarray(self.mean, np.float32).reshape(-1))
        object.__setattr__(self, "std", np.maximum(np.asarray(self.std, np.float32).reshape(-1), STD_FLOOR))
        n = self.mean.shape[0]
        space = self.action_space if self.action_space is not None else ActionSpace(dim=n)
        if space.dim != n:
            raise ValueError(f"norm stats of {n}-D actions in a {space.dim}-D action space")
        object.__setattr__(self, "action_space", space)
        pm = np.zeros(n) if self.pose_mean is None else self.pose_mean
        ps = np.ones(n) if self.pose_std is None else self.pose_std
        object.__setattr__(self, "pose_mean", np.asarray(pm, np.float32).reshape(-1))
        object.__setattr__(self, "pose_std", np.maximum(np.asarray(ps, np.float32).reshape(-1), STD_FLOOR))

    @property
    def action_dim(self) -> int:
        return int(self.mean.shape[0])

    @property
    def state_dim(self) -> int:
        return int(self.pose_mean.shape[0])

    @classmethod
    def from_actions(cls, actions: np.ndarray, action_space: ActionSpace | None = None) -> "NormStats":
        a = np.asarray(actions, np.float64).reshape(-1, np.shape(actions)[-1])
        return cls(a.mean(0), a.std(0), action_space=action_space)

    @classmethod
    def from_store(cls, store: EpisodeStore) -> "NormStats":
        """Over all recorded actions and imagined-state values of every episode (each episode validated;
        EpisodeError names a bad one). Without any recorded state values (delta_ee without ee_pose) the state
        statistics are 0 / 1."""
        from sc3_jax.data.action_space import fit_measured

        dt = 1.0 / float(store.fps)
        ids = store.episode_ids()
        # velocity commands of a quantity the state records under other entries: which entries, and their gains
        space = fit_measured(store.action_space, ((ep.actions, ep.state) for ep in
                                                  (store.load(e, mmap=True) for e in ids)), dt)
        total, total_sq, count = 0.0, 0.0, 0
        p_total, p_sq, p_low, p_high = 0.0, 0.0, np.inf, -np.inf
        for eid in ids:
            ep = store.load(eid, mmap=True)
            series = space.state_series(ep.actions, ep.ee_pose, ep.state, dt)
            a = ep.actions.astype(np.float64)
            total = total + a.sum(0)
            total_sq = total_sq + (a * a).sum(0)
            if series is not None:
                p = np.asarray(series).astype(np.float64)
                p_total, p_sq = p_total + p.sum(0), p_sq + (p * p).sum(0)
                p_low, p_high = np.minimum(p_low, p.min(0)), np.maximum(p_high, p.max(0))
            count += a.shape[0]
        if count == 0:
            raise UserError(f"{store.root}: no episodes to compute action statistics from (an empty store): "
                            "import or generate episodes first")
        mean = total / count
        var = np.maximum(total_sq / count - mean * mean, 0.0)
        if np.ndim(p_total) == 0:  # no recorded state values
            return cls(mean, np.sqrt(var), action_space=space)
        p_mean = p_total / count
        p_var = np.maximum(p_sq / count - p_mean * p_mean, 0.0)
        # the imagined state stays where the recordings went (velocities; ActionSpace.with_range)
        return cls(mean, np.sqrt(var), p_mean, np.sqrt(p_var), space.with_range(p_low, p_high))

    def normalize(self, a: np.ndarray) -> np.ndarray:
        return ((np.asarray(a, np.float32) - self.mean) / self.std).astype(np.float32)

    def denormalize(self, a: np.ndarray) -> np.ndarray:
        return (np.asarray(a, np.float32) * self.std + self.mean).astype(np.float32)

    def normalize_pose(self, p: np.ndarray) -> np.ndarray:
        """The imagined state (``pose`` condition) in the model's units."""
        return ((np.asarray(p, np.float32) - self.pose_mean) / self.pose_std).astype(np.float32)

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """float32 (action mean [A], action std [A], state mean [S], state std [S]): what rollouts take on device."""
        return self.mean, self.std, self.pose_mean, self.pose_std

    def as_array(self) -> np.ndarray:
        """float32 [4, A]: action mean, action std, pose mean, pose std (state and action of one size)."""
        return np.stack(self.arrays()).astype(np.float32)

    def to_dict(self) -> dict:
        return {"mean": self.mean.tolist(), "std": self.std.tolist(), "pose_mean": self.pose_mean.tolist(),
                "pose_std": self.pose_std.tolist(), "action_space": self.action_space.to_dict()}

    def save(self, path: str | os.PathLike) -> None:
        atomic.write_json(path, self.to_dict())

    @classmethod
    def load(cls, path: str | os.PathLike) -> "NormStats":
        """The statistics saved at ``path``, checked at the door: a JSON object whose ``mean`` / ``std`` (and
        ``pose_mean`` / ``pose_std`` where saved) are finite vectors of the action's dimension, standard deviations
        positive, and an action space (``ActionSpace.from_dict``: measured entries, gains, range) of that
        dimension; anything else is one line naming the field (a retyped or cut field was a traceback, a negative
        or NaN std a model quietly run in other units)."""
        from sc3_jax.core.validate import json_object

        fix = "restore it from the model it came with (`sc3 train` writes it)"
        d = json_object(atomic.read_json(path, fix), str(path), fix)
        vec = {}
        for key in ("mean", "std", "pose_mean", "pose_std"):
            if key not in d:
                if key in ("mean", "std"):
                    raise UserError(f"{path}: no {key!r} (the action statistics); {fix}")
                continue
            v = d[key]
            ok = isinstance(v, list) and v and all(isinstance(x, (int, float)) and not isinstance(x, bool)
                                                   for x in v)
            x = np.asarray(v, np.float64) if ok else None
            if x is None or not np.all(np.isfinite(x)) or ("std" in key and not np.all(x > 0)):
                need = "positive finite numbers" if "std" in key else "finite numbers"
                raise UserError(f"{path}: {key} is {str(v)[:80]}, expected a list of {need}; {fix}")
            if vec and x.shape != vec["mean"].shape:
                raise UserError(f"{path}: {key} has {x.size} entries, mean {vec['mean'].size}: one per action "
                                f"dimension; {fix}")
            vec[key] = x.astype(np.float32)
        if ("pose_mean" in vec) != ("pose_std" in vec):
            raise UserError(f"{path}: pose_mean and pose_std come together; {fix}")
        space = ActionSpace.from_dict(d.get("action_space"), vec["mean"].shape[0], f"{path}: action_space")
        return cls(vec["mean"], vec["std"], vec.get("pose_mean"), vec.get("pose_std"), space)

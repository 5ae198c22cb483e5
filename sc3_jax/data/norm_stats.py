"""Action and pose normalisation statistics (``norm_stats.json``): part of a trained world model (the units its
params learned), computed once from a training store, applied by the data pipeline and by rollouts. Numpy only:
loading a world model does not import the data pipeline."""
from __future__ import annotations

import dataclasses
import os
from typing import TYPE_CHECKING

import numpy as np

from sc3_jax import atomic

if TYPE_CHECKING:
    from sc3_jax.data.episodes import EpisodeStore

STD_FLOOR = 1e-3


@dataclasses.dataclass(frozen=True)
class NormStats:
    mean: np.ndarray  # float32 [7]
    std: np.ndarray  # float32 [7], floored at STD_FLOOR
    pose_mean: np.ndarray | None = None  # float32 [7] of ee_pose (default 0: stats files from before poses)
    pose_std: np.ndarray | None = None  # float32 [7], floored at STD_FLOOR (default 1)

    def __post_init__(self):
        object.__setattr__(self, "mean", np.asarray(self.mean, np.float32).reshape(-1))
        object.__setattr__(self, "std", np.maximum(np.asarray(self.std, np.float32).reshape(-1), STD_FLOOR))
        n = self.mean.shape[0]
        pm = np.zeros(n) if self.pose_mean is None else self.pose_mean
        ps = np.ones(n) if self.pose_std is None else self.pose_std
        object.__setattr__(self, "pose_mean", np.asarray(pm, np.float32).reshape(-1))
        object.__setattr__(self, "pose_std", np.maximum(np.asarray(ps, np.float32).reshape(-1), STD_FLOOR))

    @classmethod
    def from_actions(cls, actions: np.ndarray) -> "NormStats":
        a = np.asarray(actions, np.float64).reshape(-1, np.shape(actions)[-1])
        return cls(a.mean(0), a.std(0))

    @classmethod
    def from_store(cls, store: EpisodeStore) -> "NormStats":
        """Over all recorded actions of every episode (each episode validated; EpisodeError names a bad one)."""
        total, total_sq, count = 0.0, 0.0, 0
        p_total, p_sq = 0.0, 0.0
        for eid in store.episode_ids():
            ep = store.load(eid, mmap=True)
            a, p = ep.actions.astype(np.float64), ep.ee_pose.astype(np.float64)
            total = total + a.sum(0)
            total_sq = total_sq + (a * a).sum(0)
            p_total, p_sq = p_total + p.sum(0), p_sq + (p * p).sum(0)
            count += a.shape[0]
        if count == 0:
            raise ValueError(f"{store.root}: no episodes to compute action statistics from")
        mean, p_mean = total / count, p_total / count
        var = np.maximum(total_sq / count - mean * mean, 0.0)
        p_var = np.maximum(p_sq / count - p_mean * p_mean, 0.0)
        return cls(mean, np.sqrt(var), p_mean, np.sqrt(p_var))

    def normalize(self, a: np.ndarray) -> np.ndarray:
        return ((np.asarray(a, np.float32) - self.mean) / self.std).astype(np.float32)

    def denormalize(self, a: np.ndarray) -> np.ndarray:
        return (np.asarray(a, np.float32) * self.std + self.mean).astype(np.float32)

    def normalize_pose(self, p: np.ndarray) -> np.ndarray:
        return ((np.asarray(p, np.float32) - self.pose_mean) / self.pose_std).astype(np.float32)

    def as_array(self) -> np.ndarray:
        """float32 [4, 7]: action mean, action std, pose mean, pose std (what rollouts take on device)."""
        return np.stack([self.mean, self.std, self.pose_mean, self.pose_std]).astype(np.float32)

    def to_dict(self) -> dict:
        return {"mean": self.mean.tolist(), "std": self.std.tolist(), "pose_mean": self.pose_mean.tolist(),
                "pose_std": self.pose_std.tolist()}

    def save(self, path: str | os.PathLike) -> None:
        atomic.write_json(path, self.to_dict())

    @classmethod
    def load(cls, path: str | os.PathLike) -> "NormStats":
        d = atomic.read_json(path)
        pose = [np.array(d[k], np.float32) if k in d else None for k in ("pose_mean", "pose_std")]
        return cls(np.array(d["mean"], np.float32), np.array(d["std"], np.float32), *pose)

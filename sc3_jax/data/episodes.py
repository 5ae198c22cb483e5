"""The on-disk episode format: one place that defines it, used by every writer (sim demos, synthetic env,
LeRobot import) and every reader (training pipeline, rollouts).

Layout (all arrays plain ``.npy`` so readers can memory-map them and touch only the frames they need):

    root/
      dataset.json                 {"format": "sc3-episodes", "version": 1, "views": [...], "fps": 20,
                                    "action_dim": 7, "image_size": [H, W]}
      <episode_id>/
        frames/<view>.npy          uint8   [T, H, W, 3]  one file per camera view
        actions.npy                float32 [T, 7]  action[t] is applied after frame t:
                                                   (dx, dy, dz, axis-angle rx, ry, rz, gripper target)
        ee_pose.npy                float32 [T, 7]  end-effector pose at frame t: (x, y, z, axis-angle, gripper)
        meta.json                  {"prompt": str, "length": T, "labels": {...}, ...free-form metadata}

Episodes are written to a temporary directory and renamed into place, so a crash or a bad episode never leaves a
half-written episode and never touches episodes already written. Every validation error names the episode and
the field at fault.
"""
from __future__ import annotations

import dataclasses
import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from sc3_jax import atomic
from sc3_jax.errors import UserError

FORMAT = "sc3-episodes"
VERSION = 1
ACTION_DIM = 7


class EpisodeError(UserError):
    """A malformed episode. ``episode`` and ``field`` say where."""

    def __init__(self, episode: str, field: str, problem: str):
        self.episode, self.field, self.problem = episode, field, problem
        super().__init__(f"episode {episode!r}, field {field!r}: {problem}")


@dataclasses.dataclass(frozen=True)
class Episode:
    episode_id: str
    frames: dict[str, np.ndarray]  # view -> uint8 [T, H, W, 3]
    actions: np.ndarray  # float32 [T, 7]
    ee_pose: np.ndarray  # float32 [T, 7]
    prompt: str = ""
    meta: dict[str, Any] = dataclasses.field(default_factory=dict)

    @property
    def length(self) -> int:
        return int(self.actions.shape[0])


def validate_episode(ep: Episode, views: list[str], action_dim: int = ACTION_DIM,
                     image_size: tuple[int, int] | None = None, min_length: int = 1) -> None:
    """Raise EpisodeError naming the episode and field for the first problem found."""
    name = ep.episode_id
    actions = np.asarray(ep.actions)
    if actions.ndim != 2 or actions.shape[1] != action_dim:
        raise EpisodeError(name, "actions", f"expected shape [T, {action_dim}], got {list(actions.shape)}")
    length = actions.shape[0]
    if length < min_length:
        raise EpisodeError(name, "length", f"episode has {length} steps, at least {min_length} are needed")
    if not np.all(np.isfinite(actions)):
        raise EpisodeError(name, "actions", f"contains NaN/inf at steps {_bad_steps(actions)}")
    pose = np.asarray(ep.ee_pose)
    if pose.shape != (length, 7):
        raise EpisodeError(name, "ee_pose", f"expected shape [{length}, 7], got {list(pose.shape)}")
    if not np.all(np.isfinite(pose)):
        raise EpisodeError(name, "ee_pose", f"contains NaN/inf at steps {_bad_steps(pose)}")
    for view in views:
        if view not in ep.frames:
            raise EpisodeError(name, f"frames/{view}", f"missing view (have {sorted(ep.frames)})")
        f = ep.frames[view]
        if f.dtype != np.uint8 or f.ndim != 4 or f.shape[-1] != 3:
            raise EpisodeError(name, f"frames/{view}", f"expected uint8 [T, H, W, 3], got {f.dtype} {list(f.shape)}")
        if f.shape[0] != length:
            raise EpisodeError(name, f"frames/{view}", f"{f.shape[0]} frames but {length} actions")
        if image_size is not None and tuple(f.shape[1:3]) != tuple(image_size):
            raise EpisodeError(name, f"frames/{view}", f"image size {list(f.shape[1:3])}, dataset has {list(image_size)}")


def _bad_steps(x: np.ndarray) -> list[int]:
    return np.nonzero(~np.all(np.isfinite(x), axis=-1))[0][:5].tolist()


class EpisodeStore:
    """Reads and writes one episode directory. ``create=True`` starts a new dataset (or reopens a compatible one)."""

    def __init__(self, root: str | os.PathLike, views: list[str] | None = None, fps: float | None = None,
                 image_size: tuple[int, int] | None = None, action_dim: int = ACTION_DIM, create: bool = False):
        self.root = Path(root)
        header = self.root / "dataset.json"
        if header.exists():
            info = atomic.read_json(header)
            if info.get("format") != FORMAT:
                raise ValueError(f"{header}: not an sc3 episode dataset (format={info.get('format')!r})")
            for key, want in (("views", views), ("fps", fps), ("action_dim", action_dim if create else None)):
                if want is not None and info[key] != (list(want) if key == "views" else want):
                    raise ValueError(f"{header}: dataset has {key}={info[key]!r}, asked for {want!r}")
        elif create:
            if views is None or fps is None or image_size is None:
                raise ValueError("creating a dataset needs views, fps and image_size")
            self.root.mkdir(parents=True, exist_ok=True)
            info = {"format": FORMAT, "version": VERSION, "views": list(views), "fps": fps,
                    "action_dim": action_dim, "image_size": list(image_size)}
            atomic.write_json(header, info)
        else:
            raise FileNotFoundError(f"{self.root}: no dataset.json (not an sc3 episode dataset)")
        self.info = info
        self.views: list[str] = list(info["views"])
        self.fps: float = info["fps"]
        self.action_dim: int = info["action_dim"]
        self.image_size: tuple[int, int] = tuple(info["image_size"])

    # -- reading ---------------------------------------------------------------------------------------------
    def episode_ids(self) -> list[str]:
        """Complete episodes only (temporary directories of interrupted writes are ignored), sorted."""
        return sorted(p.name for p in self.root.iterdir() if p.is_dir() and (p / "meta.json").exists()
                      and not p.name.startswith("."))

    def __len__(self) -> int:
        return len(self.episode_ids())

    def __contains__(self, episode_id: str) -> bool:
        return (self.root / episode_id / "meta.json").exists()

    def load(self, episode_id: str, mmap: bool = True, validate: bool = True, min_length: int = 1) -> Episode:
        d = self.root / episode_id
        if not (d / "meta.json").exists():
            raise EpisodeError(episode_id, "meta.json", f"missing in {d}")
        mode = "r" if mmap else None
        frames = {}
        for view in self.views:
            path = d / "frames" / f"{view}.npy"
            if not path.exists():
                raise EpisodeError(episode_id, f"frames/{view}", f"missing view file {path}")
            frames[view] = np.load(path, mmap_mode=mode)
        arrays = {}
        for field in ("actions", "ee_pose"):
            path = d / f"{field}.npy"
            if not path.exists():
                raise EpisodeError(episode_id, field, f"missing file {path}")
            arrays[field] = np.load(path)
        meta = json.loads((d / "meta.json").read_text())
        ep = Episode(episode_id, frames, arrays["actions"], arrays["ee_pose"], meta.get("prompt", ""), meta)
        if validate:
            validate_episode(ep, self.views, self.action_dim, self.image_size, min_length)
        return ep

    # -- writing ---------------------------------------------------------------------------------------------
    def write(self, ep: Episode, overwrite: bool = False) -> Path:
        """Validate then write atomically. Raises (writing nothing) on a bad episode."""
        validate_episode(ep, self.views, self.action_dim, self.image_size)
        final = self.root / ep.episode_id
        if final.exists() and not overwrite:
            raise FileExistsError(f"episode {ep.episode_id!r} already exists in {self.root}")
        tmp = Path(tempfile.mkdtemp(prefix=f".tmp-{ep.episode_id}-", dir=self.root))
        try:
            (tmp / "frames").mkdir()
            for view in self.views:
                np.save(tmp / "frames" / f"{view}.npy", np.ascontiguousarray(ep.frames[view], dtype=np.uint8))
            np.save(tmp / "actions.npy", np.asarray(ep.actions, np.float32))
            np.save(tmp / "ee_pose.npy", np.asarray(ep.ee_pose, np.float32))
            meta = {**ep.meta, "prompt": ep.prompt, "length": ep.length}
            (tmp / "meta.json").write_text(json.dumps(meta, indent=1, default=_json_default))
            if final.exists():
                shutil.rmtree(final)
            os.replace(tmp, final)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        return final


def _json_default(x):
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    raise TypeError(f"not JSON serialisable: {type(x)}")

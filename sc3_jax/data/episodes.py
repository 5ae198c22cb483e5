"""The on-disk episode format: one place that defines it, used by every writer (sim demos, synthetic env,
LeRobot import) and every reader (training pipeline, rollouts).

Layout (all arrays plain ``.npy`` so readers can memory-map them and touch only the frames they need):

    root/
      dataset.json                 {"format": "sc3-episodes", "version": 1, "views": [...], "fps": 20,
                                    "action_dim": A, "image_size": [H, W],
                                    "action_space": {"kind": "delta_ee" | "absolute" | "velocity", "dim": A,
                                                     "names": [...]},
                                    "state": {"dim": S, "names": [...]} or null, "ee_pose": true | false,
                                    "object_state": {"dim": O, "names": [...]} or null}
      <episode_id>/
        frames/<view>.npy          uint8   [T, H, W, 3]  one file per camera view
        actions.npy                float32 [T, A]  action[t] is applied after frame t, in the declared action space
                                                   (``data/action_space.py``; the simulated benchmark's delta_ee:
                                                   dx, dy, dz, axis-angle rx, ry, rz, gripper target)
        ee_pose.npy                float32 [T, 7]  end-effector pose at frame t: (x, y, z, axis-angle, gripper);
                                                   only where dataset.json says "ee_pose": true
        state.npy                  float32 [T, S]  proprioceptive state at frame t (e.g. joint positions); only
                                                   where dataset.json declares a "state"
        object_state.npy           float32 [T, O]  the state of the scene's objects at frame t (e.g. a block's
                                                   position: LeRobot's observation.environment_state); only where
                                                   dataset.json declares an "object_state"
        meta.json                  {"prompt": str, "length": T, "labels": {...}, ...free-form metadata}

A store written before these declarations (no "action_space", no "ee_pose" key) reads as the simulated benchmark's:
delta_ee actions of its action_dim, an ee_pose, no state. One written before "object_state" (every store
before it) has none.

Episodes are written to a temporary directory and renamed into place, so a crash or a bad episode never leaves a
half-written episode and never touches episodes already written. Every validation error names the episode and
the field at fault.
"""
from __future__ import annotations

import dataclasses
import json
import os
import shutil
from pathlib import Path
from typing import Any

import numpy as np

from sc3_jax.core import atomic
from sc3_jax.data.action_space import ActionSpace
from sc3_jax.core.errors import UserError
from sc3_jax.core.safe_names import check_name, join_inside
from sc3_jax.core.validate import is_count, is_finite_number, json_object, load_npy, numeric, regular_file

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
    actions: np.ndarray  # float32 [T, A]
    ee_pose: np.ndarray | None  # float32 [T, 7]; None where the dataset recorded no end-effector pose
    prompt: str = ""
    meta: dict[str, Any] = dataclasses.field(default_factory=dict)
    state: np.ndarray | None = None  # float32 [T, S] proprioceptive state, where the dataset declares one
    object_state: np.ndarray | None = None  # float32 [T, O] the objects' state, where the dataset declares one

    @property
    def length(self) -> int:
        return int(self.actions.shape[0])


def validate_episode(ep: Episode, views: list[str], action_dim: int = ACTION_DIM,
                     image_size: tuple[int, int] | None = None, min_length: int = 1, has_pose: bool = True,
                     state_dim: int | None = None, object_state_dim: int | None = None) -> None:
    """Raise EpisodeError naming the episode and field for the first problem found. ``has_pose`` / ``state_dim`` /
    ``object_state_dim``: what the dataset declares (an ee_pose [T, 7]; a state [T, state_dim]; an object state
    [T, object_state_dim]); an array it does not declare is refused too, so nothing is silently dropped."""
    name = ep.episode_id
    actions = np.asarray(ep.actions)
    if actions.ndim != 2 or actions.shape[1] != action_dim:
        raise EpisodeError(name, "actions", f"expected shape [T, {action_dim}], got {list(actions.shape)}")
    length = actions.shape[0]
    if length < min_length:
        raise EpisodeError(name, "length", f"episode has {length} steps, at least {min_length} are needed")
    if not np.all(np.isfinite(actions)):
        raise EpisodeError(name, "actions", f"contains NaN/inf at steps {_bad_steps(actions)}")
    for field, x, dim, declared in (("ee_pose", ep.ee_pose, 7, has_pose),
                                    ("state", ep.state, state_dim, state_dim is not None),
                                    ("object_state", ep.object_state, object_state_dim, object_state_dim is not None)):
        if not declared:
            if x is not None:
                raise EpisodeError(name, field, "the dataset declares none (dataset.json): create the store with it")
            continue
        x = np.asarray(x)
        if x.shape != (length, dim):
            raise EpisodeError(name, field, f"expected shape [{length}, {dim}], got {list(x.shape)}")
        if not np.all(np.isfinite(x)):
            raise EpisodeError(name, field, f"contains NaN/inf at steps {_bad_steps(x)}")
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
    """Reads and writes one episode directory. ``create=True`` starts a new dataset (or reopens a compatible one)
    with the given declarations: ``action_space`` (default: delta_ee of ``action_dim``), ``state_dim`` /
    ``state_names`` (a proprioceptive state per frame; None: none), ``has_pose`` (an end-effector pose per frame),
    ``object_state_dim`` / ``object_state_names`` (the state of the scene's objects per frame, e.g. a block's
    position; None: none)."""

    def __init__(self, root: str | os.PathLike, views: list[str] | None = None, fps: float | None = None,
                 image_size: tuple[int, int] | None = None, action_dim: int | None = None, create: bool = False,
                 action_space: ActionSpace | None = None, state_dim: int | None = None,
                 state_names: list[str] | None = None, has_pose: bool = True,
                 object_state_dim: int | None = None, object_state_names: list[str] | None = None):
        self.root = Path(root)
        header = self.root / "dataset.json"
        for v in views or ():  # each becomes frames/<view>.npy: checked before anything is written
            check_name(v, "view")
        if action_space is None:
            action_space = ActionSpace(dim=ACTION_DIM if action_dim is None else action_dim)
        elif action_dim is not None and action_dim != action_space.dim:
            raise ValueError(f"action_dim {action_dim} but action_space is {action_space.dim}-D")
        state = _declaration(state_dim, state_names, "s", "state")
        objects = _declaration(object_state_dim, object_state_names, "o", "object state")
        declared = {"action_dim": action_space.dim, "action_space": action_space.to_dict(), "state": state,
                    "ee_pose": bool(has_pose), "object_state": objects}
        if header.exists():
            # the store's own regular file (a dataset.json linked to another store's was read as this one's)
            regular_file(header, "restore it from a copy (or write the store again)", inside=self.root)
            info = read_header(header)
            have = {**info, **_declared(info)}
            # a reopened store is the one asked for: an import resumed with another --image-size skipped every
            # episode as "already there", at the size they were
            size = list(image_size) if image_size is not None and create else None
            asked = {k: v for k, v in (("views", views and list(views)), ("fps", fps), ("image_size", size))
                     if v is not None}
            for key, want in {**asked, **(declared if create else {})}.items():
                if have[key] != want:
                    raise UserError(f"{header}: dataset has {key}={have[key]!r}, asked for {want!r}")
        elif create:
            if views is None or fps is None or image_size is None:
                raise ValueError("creating a dataset needs views, fps and image_size")
            self.root.mkdir(parents=True, exist_ok=True)
            info = {"format": FORMAT, "version": VERSION, "views": list(views), "fps": fps,
                    "image_size": list(image_size), **declared}
            atomic.write_json(header, info)
        else:
            raise FileNotFoundError(f"{self.root}: no dataset.json (not an sc3 episode dataset)")
        self.info = info
        self.views: list[str] = [check_name(v, f"{header}: view") for v in info["views"]]  # frames/<view>.npy
        self.fps: float = info["fps"]
        self.action_dim: int = info["action_dim"]
        self.image_size: tuple[int, int] = tuple(info["image_size"])
        self.action_space: ActionSpace = ActionSpace.from_dict(info.get("action_space"), self.action_dim,
                                                               f"{header}: action_space")
        self.has_pose: bool = bool(info.get("ee_pose", True))
        st = info.get("state")
        self.state_dim: int | None = None if st is None else int(st["dim"])
        self.state_names: tuple[str, ...] = () if st is None else tuple(st.get("names") or ())
        ob = info.get("object_state")  # a store written before the declaration has none
        self.object_state_dim: int | None = None if ob is None else int(ob["dim"])
        self.object_state_names: tuple[str, ...] = () if ob is None else tuple(ob.get("names") or ())

    # -- reading ---------------------------------------------------------------------------------------------
    def episode_ids(self) -> list[str]:
        """Complete episodes only (temporary directories of interrupted writes are ignored), sorted."""
        return sorted(p.name for p in self.root.iterdir() if p.is_dir() and (p / "meta.json").exists()
                      and not p.name.startswith("."))

    def check_whole(self) -> None:
        """One line naming an episode directory that lost its meta.json (emptied, or damaged by hand), which
        :meth:`episode_ids` passes over as no episode: a command taking the store's first N read the next one in its
        place without a word. An interrupted write is a dot-named temporary, never one of these."""
        hollow = sorted(p.name for p in self.root.iterdir() if p.is_dir() and not p.name.startswith(".")
                        and not (p / "meta.json").exists())
        if hollow:
            more = f" (and {len(hollow) - 1} more: {', '.join(hollow[1:4])}{', ...' if len(hollow) > 4 else ''})" \
                if len(hollow) > 1 else ""
            raise UserError(f"{self.root / hollow[0]}: an episode directory without its meta.json{more}, emptied or "
                            "damaged; restore it from a copy, or delete it")

    def __len__(self) -> int:
        return len(self.episode_ids())

    def __contains__(self, episode_id: str) -> bool:
        return (self.root / episode_id / "meta.json").exists()

    def load(self, episode_id: str, mmap: bool = True, validate: bool = True, min_length: int = 1) -> Episode:
        d = join_inside(self.root, episode_id)
        if not (d / "meta.json").exists():
            raise EpisodeError(episode_id, "meta.json", f"missing in {d}")
        fix = f"restore the episode from a copy, or delete {d} (a resumed import writes it again)"
        frames = {}
        for view in self.views:
            path = d / "frames" / f"{view}.npy"
            if not path.exists():
                raise EpisodeError(episode_id, f"frames/{view}", f"missing view file {path}")
            frames[view] = load_npy(path, fix, mmap, inside=self.root)  # the store's own regular files only
        arrays = {"ee_pose": None, "state": None, "object_state": None}
        for field in self.array_fields():
            path = d / f"{field}.npy"
            if not path.exists():
                raise EpisodeError(episode_id, field, f"missing file {path}")
            arrays[field] = numeric(load_npy(path, fix, inside=self.root), str(path), fix)
        regular_file(d / "meta.json", fix, inside=self.root)
        meta = json_object(atomic.read_json(d / "meta.json", fix), str(d / "meta.json"), fix)
        prompt = meta.get("prompt", "")
        if not isinstance(prompt, str):
            raise EpisodeError(episode_id, "meta.json", f"prompt is {type(prompt).__name__}, expected text; {fix}")
        ep = Episode(episode_id, frames, arrays["actions"], arrays["ee_pose"], prompt, meta, arrays["state"],
                     arrays["object_state"])
        if validate:
            self.validate(ep, min_length)
        return ep

    def array_fields(self) -> tuple[str, ...]:
        """The per-episode arrays besides frames this dataset has (``<field>.npy``)."""
        return ("actions",) + (("ee_pose",) if self.has_pose else ()) + (("state",) if self.state_dim else ()) \
            + (("object_state",) if self.object_state_dim else ())

    def validate(self, ep: Episode, min_length: int = 1) -> None:
        validate_episode(ep, self.views, self.action_dim, self.image_size, min_length, self.has_pose,
                         self.state_dim, self.object_state_dim)

    # -- writing ---------------------------------------------------------------------------------------------
    def write(self, ep: Episode, overwrite: bool = False) -> Path:
        """Validate then write atomically. Raises (writing nothing) on a bad episode."""
        self.validate(ep)
        final = join_inside(self.root, check_name(ep.episode_id, "episode id"))
        if final.exists() and not overwrite:
            raise FileExistsError(f"episode {ep.episode_id!r} already exists in {self.root}")
        tmp = atomic.temp_dir(final)
        try:
            (tmp / "frames").mkdir()
            for view in self.views:
                np.save(tmp / "frames" / f"{view}.npy", np.ascontiguousarray(ep.frames[view], dtype=np.uint8))
            for field in self.array_fields():
                np.save(tmp / f"{field}.npy", np.asarray(getattr(ep, field), np.float32))
            meta = {**ep.meta, "prompt": ep.prompt, "length": ep.length}
            (tmp / "meta.json").write_text(json.dumps(meta, indent=1, default=_json_default))
            if final.exists():
                shutil.rmtree(final)
            os.replace(tmp, final)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        return final


def read_header(path: Path) -> dict:
    """A store's dataset.json, checked field by field: a retyped or missing declaration is one line naming it,
    not a KeyError or TypeError wherever it is first used."""
    fix = "restore it from a copy (or write the store again)"
    info = json_object(atomic.read_json(path, fix), str(path), fix)
    if info.get("format") != FORMAT:
        raise UserError(f"{path}: not an sc3 episode dataset (format={info.get('format')!r})")

    def need(key: str, ok: bool, want: str):
        if not ok:
            raise UserError(f"{path}: {key} is {info.get(key, 'missing')!r}, expected {want}; {fix}")
    views, size, state, objects = info.get("views"), info.get("image_size"), info.get("state"), info.get("object_state")
    need("views", isinstance(views, list) and bool(views) and all(isinstance(v, str) for v in views),
         "a list of view names")
    need("fps", is_finite_number(info.get("fps")) and 0 < info["fps"] <= 10_000, "a positive frame rate")
    need("action_dim", is_count(info.get("action_dim"), 4096), "a positive integer")
    need("image_size", isinstance(size, list) and len(size) == 2 and all(is_count(x, 65536) for x in size),
         "[H, W], two positive integers")
    need("state", state is None or (isinstance(state, dict) and is_count(state.get("dim"), 4096)),
         'null or {"dim": S, "names": [...]}')
    need("ee_pose", isinstance(info.get("ee_pose", True), bool), "true or false")
    need("object_state", objects is None or (isinstance(objects, dict) and is_count(objects.get("dim"), 4096) and (
        objects.get("names") is None or (isinstance(objects["names"], list) and len(objects["names"]) == objects["dim"]
                                         and all(isinstance(n, str) for n in objects["names"])))),
         'null or {"dim": O, "names": [O names]}')
    return info


def _declared(info: dict) -> dict:
    """The declarations of a dataset.json as it is read (defaults for stores written before them)."""
    return {"action_dim": info["action_dim"],
            "action_space": ActionSpace.from_dict(info.get("action_space"), info["action_dim"]).to_dict(),
            "state": info.get("state"), "ee_pose": bool(info.get("ee_pose", True)),
            "object_state": info.get("object_state")}


def _declaration(dim: int | None, names: list[str] | None, prefix: str, what: str) -> dict | None:
    """dataset.json's ``{"dim": D, "names": [...]}`` of a per-frame vector (None: the store has none)."""
    if dim is None:
        return None
    out = {"dim": int(dim), "names": list(names or [f"{prefix}{i}" for i in range(int(dim))])}
    if len(out["names"]) != out["dim"]:
        raise ValueError(f"{len(out['names'])} {what} names for a {dim}-D {what}")
    return out


def _json_default(x):
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    raise TypeError(f"not JSON serialisable: {type(x)}")

"""The importer: a LeRobot dataset converted into our episode store (``sc3_jax.data.episodes``), with the action
space the dataset is declared to have (``import_lerobot``; its numeric options checked first: ``check_options``).

LeRobot's info.json has no action-space declaration: the caller gives it, or our own export's ``sc3_action_space``
entry (``lerobot.INFO_ACTION_SPACE``) does.
"""
from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from sc3_jax.core import locks
from sc3_jax.core.errors import UserError
from sc3_jax.data.lerobot import ENVIRONMENT_STATE_KEY, INFO_ACTION_SPACE, OPTIONAL, LeRobotEpisodes
from sc3_jax.data.lerobot_error import LeRobotError

MIN_EPISODE_FRAMES = 2  # an imported episode shorter than this is skipped (said): nothing can be learnt from it
# an imported episode's meta.json {criterion: bool}, what `sc3 sweep episodes --real STORE` reads
LABELS_FIELD = "labels"
MAX_SIDE = 4096  # pixels a side of an imported frame: a 20000 x 20000 one is 1.2 GB, per frame and view


def check_options(out, fps: float | None, image_size) -> None:
    """The numeric options of an import and its --out, in one line each before anything is read or written (``--fps
    0`` was a ZeroDivisionError, ``--image-size 0 -5`` a cv2 traceback after the store's dataset.json was written,
    which then refused the corrected rerun)."""
    from sc3_jax.core.validate import in_range, out_dir

    if fps is not None:
        in_range("--fps", fps, 1e-3, 10_000, "frames per second")
    for side in image_size or ():
        in_range("--image-size", side, 1, MAX_SIDE, "pixels a side")
    if image_size is not None and len(image_size) != 2:
        raise UserError(f"--image-size {' '.join(map(str, image_size))}: expected H W")
    out_dir(out, "--out")


def import_lerobot(root: str | os.PathLike, out: str | os.PathLike, views=None, wrist_views=None,
                   fps: float | None = None, image_size: tuple[int, int] | None = None, action_key: str = "action",
                   pose_key: str | None = "observation.state", allow_missing_pose: bool = False,
                   progress: bool = False, *, action_space: str | None = None,
                   action_names: list[str] | None = None, action_targets: list[int] | None = None,
                   state_key: str | None = OPTIONAL, episodes=None,  # type: ignore[assignment]
                   id_prefix: str = "", object_state_key: str | None = OPTIONAL) -> dict:  # type: ignore[assignment]
    """Convert the LeRobot dataset at ``root`` into an episode store at ``out``.

    The action space (``data/action_space.py``): ``action_space`` ("delta_ee", "absolute" or "velocity") with
    ``action_names`` (default: the feature's own names) and, for velocities, ``action_targets`` (indices of
    position-target dimensions such as a gripper); else our own export's ``sc3_action_space`` entry in info.json;
    else, for 7-D actions, the simulated benchmark's delta_ee (how stores were imported before declarations).
    Other actions without a declaration are refused (one line saying what to pass).

    ``pose_key``: a 7-D feature that becomes our ``ee_pose`` (x, y, z, rotation vector, gripper). delta_ee actions
    need one unless ``allow_missing_pose`` (then the store has no ee_pose: no pseudo-actions, motion relative to the
    start); for other action spaces it is optional (used where it names a 7-D feature other than the state).
    ``state_key``: the proprioceptive state feature of any size (default ``observation.state`` when present and not
    already the ee_pose; None: none), stored as ``state``. ``object_state_key``: the feature holding the state of the
    scene's objects, of any size (default ``observation.environment_state`` when present -- except when resuming an
    import into a store written without one, which keeps its declaration; None: none), stored as ``object_state``
    with the feature's names. ``image_size`` resizes every view (our store has one size
    for all views). A ``next.success`` feature becomes each episode's meta ``"labels": {"success": any frame's}``
    (the real outcomes ``sc3 sweep episodes --real STORE`` reads). ``episodes``: the episode_index values to import (a
    container; None: all), so that one dataset gives a training store and a held-out one. Episodes are named
    ``{id_prefix}lerobot{episode_index:06d}``; existing ones are skipped (resumable). One prefix holds one dataset: a
    lab's several recording sessions go into one store under a prefix each (``id_prefix``: letters, digits, ``_``,
    ``-``).
    """
    if not re.fullmatch(r"[A-Za-z0-9_-]*", id_prefix):
        raise LeRobotError(out, f"id prefix {id_prefix!r}: letters, digits, '_' and '-' only (it names folders)")
    check_options(out, fps, image_size)
    from .action_space import ActionSpace, names_of
    from .episodes import Episode, EpisodeStore

    src = LeRobotEpisodes(root, views=views, wrist_views=wrist_views, fps=fps, action_key=action_key,
                          state_key=None)
    feats, info_path = src.features, Path(root) / "meta" / "info.json"
    chosen = [i for i in range(len(src)) if episodes is None or src.episode_index(i) in episodes]
    have = [src.episode_index(i) for i in range(len(src))]
    lacking = episodes.missing(set(have)) if callable(getattr(episodes, "missing", None)) else []
    if lacking:  # asked for by name: importing the others without a word left a store short of what was asked
        shown = ", ".join(map(str, lacking[:5])) + (f", ... ({len(lacking)} in all)" if len(lacking) > 5 else "")
        raise LeRobotError(root, f"--episodes asks for episode_index {shown}, which this dataset does not have (it "
                                 f"has {len(have)} episodes, episode_index {min(have, default=0)}.."
                                 f"{max(have, default=-1)}): leave them out, or give an open range (e.g. 20:)")
    if not chosen:  # nothing would be imported, yet the command would say "train on it"
        raise LeRobotError(root, f"--episodes selects none of its {len(have)} episodes (episode_index "
                                 f"{min(have, default=0)}..{max(have, default=-1)})")
    dim = int(np.prod(feats[action_key]["shape"]))
    declared = src.info.get(INFO_ACTION_SPACE)
    if action_space is not None:
        space = ActionSpace(action_space, dim, tuple(action_names or names_of(feats[action_key].get("names"), dim)),
                            tuple(action_targets or ()))
    elif declared is not None:
        space = ActionSpace.from_dict(declared, dim, f"{info_path}: {INFO_ACTION_SPACE}")
    elif dim == 7:
        space = ActionSpace("delta_ee", 7)
    else:
        raise LeRobotError(info_path, f"{dim}-D {action_key!r} and no action-space declaration: pass action_space "
                                      f"'absolute' (position targets), 'velocity' or 'delta_ee'")
    is_pose = lambda k: k in feats and list(feats[k]["shape"]) == [7]  # noqa: E731
    if state_key is OPTIONAL:
        state_key = "observation.state" if "observation.state" in feats else None
        if space.kind == "delta_ee" and state_key == pose_key and is_pose(pose_key):
            state_key = None  # the benchmark's layout: observation.state is the pose
    elif state_key is not None and state_key not in feats:
        raise LeRobotError(info_path, f"state key {state_key!r} not in features {sorted(feats)}")
    has_pose = is_pose(pose_key) and (space.kind == "delta_ee" or pose_key != state_key)
    if space.kind == "delta_ee" and not has_pose and not allow_missing_pose:
        shape = feats[pose_key]["shape"] if pose_key in feats else "missing"
        raise LeRobotError(pose_key, f"our ee_pose needs a 7-D feature, this one is {shape}; pass another pose "
                                     f"key or allow_missing_pose")
    auto = object_state_key is OPTIONAL
    object_state_key = _object_state_key(object_state_key, feats, info_path, Path(out))
    if auto and object_state_key is None and ENVIRONMENT_STATE_KEY in feats and progress:
        print(f"  {ENVIRONMENT_STATE_KEY} not imported: {out} was written without object states (import into a "
              "new store to keep them)", flush=True)
    src.pose_key, src.state_key = (pose_key if has_pose else None), state_key
    src.object_state_key = object_state_key
    state_dim = int(np.prod(feats[state_key]["shape"])) if state_key else None
    state_names = (names_of(feats[state_key].get("names"), state_dim) or None) if state_key else None
    object_dim = int(np.prod(feats[object_state_key]["shape"])) if object_state_key else None
    object_names = (names_of(feats[object_state_key].get("names"), object_dim) or None) if object_state_key else None
    sizes = {tuple(feats[k]["shape"][:2]) for k in src.cameras.values()}
    if image_size is None and len(sizes) > 1:
        raise LeRobotError(root, f"cameras have different sizes {sorted(sizes)}: pass image_size to resize them")
    size = tuple(image_size) if image_size is not None else sizes.pop()
    fps_out = int(src.fps) if float(src.fps).is_integer() else src.fps  # keep "fps": 20 as our stores write it
    store = EpisodeStore(out, views=src.views, fps=fps_out, image_size=size, create=True, action_space=space,
                         state_dim=state_dim, state_names=state_names, has_pose=has_pose,
                         object_state_dim=object_dim, object_state_names=object_names)
    source = str(Path(root).resolve())
    written = skipped = labelled = 0
    short: list[int] = []
    with locks.hold(store.root, "import"):  # two imports into one store would race on its episodes
        _check_same_source(store, source, id_prefix, {src.episode_index(i) for i in chosen})
        for i in chosen:
            ep = src.episode(i)
            eid = f"{id_prefix}lerobot{ep.episode_index:06d}"
            if eid in store:
                skipped += 1
                continue
            if ep.length < MIN_EPISODE_FRAMES:  # no training window and no initial condition can come of it
                short.append(ep.episode_index)
                if progress:
                    print(f"  skipped episode {ep.episode_index}: {ep.length} frame(s), fewer than "
                          f"{MIN_EPISODE_FRAMES}", flush=True)
                continue
            frames = {v: _resize(f, size) for v, f in ep.frames.items()}
            meta = {"source": "lerobot", "lerobot_root": source, "episode_index": ep.episode_index,
                    "tasks": ep.tasks, "source_fps": src.source_fps, "camera_keys": src.cameras,
                    "wrist_views": list(src.wrist_views), "timestamps": ep.timestamps.tolist(),
                    "ee_pose_source": pose_key if has_pose else "none", "state_source": state_key or "none",
                    **({"object_state_source": object_state_key} if object_state_key else {})}
            # the real outcome, so that `sc3 sweep episodes --real STORE` needs no LeRobot source
            if ep.success is not None:
                meta[LABELS_FIELD] = {"success": ep.success}
                labelled += 1
            store.write(Episode(eid, frames, ep.actions.reshape(ep.length, dim), ep.pose, ep.prompt, meta,
                                None if ep.state is None else ep.state.reshape(ep.length, state_dim),
                                None if ep.object_state is None else ep.object_state.reshape(ep.length, object_dim)))
            written += 1
            if progress:
                print(f"  {eid}: {ep.length} frames", flush=True)
    return {"out": str(out), "written": written, "skipped": skipped, "too_short": short, "views": src.views,
            "fps": fps_out, "action_space": space.to_dict(), "state_dim": state_dim, "ee_pose": has_pose,
            "object_state_dim": object_dim,
            "success_labels": labelled}  # of the episodes written: those whose meta holds next.success


def _object_state_key(key, feats: dict, info_path: Path, out: Path) -> str | None:
    """The feature that becomes the store's ``object_state``: ``key``, checked; by default (``OPTIONAL``)
    observation.environment_state where the dataset has it, unless ``out`` is a store written without one (an import
    resumed into a store from before object states: its declaration stays, the episodes it holds have none)."""
    if key is OPTIONAL:
        if ENVIRONMENT_STATE_KEY not in feats:
            return None
        header = out / "dataset.json"
        if header.exists():
            from .episodes import read_header

            if read_header(header).get("object_state") is None:
                return None
        return ENVIRONMENT_STATE_KEY
    if key is not None and key not in feats:
        raise LeRobotError(info_path, f"object state key {key!r} not in features {sorted(feats)}")
    return key


def _check_same_source(store, source: str, prefix: str, indices: set[int]) -> None:
    """Importing dataset B into a store made from dataset A under the same id prefix would skip B's episodes as
    "already there" (their ids are episode indices) and keep A's; importing A again under another prefix would hold
    its episodes twice. Both refused, naming the store's source and prefix: duplicates are found by what was
    imported (source and episode_index), not by their names."""
    from sc3_jax.core import atomic

    held = []  # (id prefix, LeRobot root, episode_index, id) of every imported episode of the store
    for eid in store.episode_ids():
        m = re.fullmatch(r"(.*)lerobot(\d+)", eid)
        if m is not None:
            meta = atomic.read_json(store.root / eid / "meta.json", "restore it (the episode's metadata)")
            if meta.get("source") == "lerobot":
                held.append((m[1], meta.get("lerobot_root"), meta.get("episode_index"), eid))
    for pre, came, _, _ in held:
        if pre == prefix and came not in (None, source):
            raise LeRobotError(store.root, f"holds episodes imported from {came}, not from {source}"
                                           f"{' under this prefix' if prefix else ''}: import into another --out or "
                                           "under another --id-prefix")
    for pre, came, index, eid in held:
        if pre != prefix and came == source and index in indices:
            raise LeRobotError(store.root, f"holds episode {index} of {source} already, as {eid} (id prefix "
                                           f"{pre!r}): importing it again under {prefix!r} would give it twice; "
                                           f"resume with --id-prefix {pre!r}")


def _resize(frames: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    if tuple(frames.shape[1:3]) == tuple(size):
        return np.ascontiguousarray(frames)
    import cv2

    return np.stack([cv2.resize(f, (size[1], size[0]), interpolation=cv2.INTER_AREA) for f in frames])

"""grain pipeline: training windows with multi-FPS strides and pseudo-actions, normalised actions, local batches.

A *window* starting at frame ``t0`` with stride ``s`` holds frames ``t0 + s*i`` for ``i in range(K + T)`` of every
view (K = ``cfg.context_frames`` clean context frames, T = ``cfg.future_frames`` future frames) and T actions: action
``j`` moves frame ``K-1+j`` to frame ``K+j`` (frame indices ``t = t0 + s*(K-1+j)`` -> ``t + s``):

- recorded (stride 1): ``actions[t]``; stride s > 1: the s recorded deltas ``actions[t..t+s-1]`` composed
  (xyz summed, rotations composed exactly ``R(a_{t+s-1}) ... R(a_t)``, gripper = last target ``actions[t+s-1, 6]``);
- pseudo (probability ``cfg.pseudo_action_prob`` per sample): from end-effector poses,
  ``(xyz_{t+s} - xyz_t, rotvec(R_{t+s} R_t^T), gripper target actions[t+s-1, 6])``.

The gripper entry has one meaning everywhere: the *commanded* target width (what a policy outputs and what
rollouts integrate), never the measured finger gap of ``ee_pose`` (which lags the command and stops on a grasped
object: on an expert episode the two differ by up to 5.6 cm).

Both are normalised with ``NormStats`` (per-dimension mean/std over all recorded actions of the store).

Every window also carries the *pose condition* ``pose`` [T + 1, 7]: the end-effector pose of frame K-1 (its gripper
entry the command in force, ``actions[t-1, 6]``) and of every future frame, integrated from that pose with the
window's actions -- the numpy twin of ``imagination_state.frame_poses``, which rollouts use -- normalised with the
pose statistics of ``NormStats``.

Batch i of process p is a deterministic function of (cfg.seed, i, p, process_count): the index of all valid
(episode, start) pairs (valid for the largest stride) is shuffled per epoch, repeated forever, per-sample draws
(stride, pseudo) come from ``random_map`` (seeded by the *global* sample index), and process p of n takes samples
``[i*B + p*B/n, i*B + (p+1)*B/n)`` of the global sample stream, so concatenating the local batches of all
processes in process order gives exactly the single-process global batch.
"""
from __future__ import annotations

import collections
import dataclasses
import os
import threading
from typing import NamedTuple

import grain
import numpy as np

from sc3_jax.data import rotations
from sc3_jax.data.episodes import Episode, EpisodeStore
from sc3_jax.data.norm_stats import NormStats

_OPEN_LOCK = threading.Lock()


# -- window semantics (pure functions, also used by rollouts / tests) -------------------------------------------
def window_frame_indices(start: int, stride: int, context_frames: int, future_frames: int) -> np.ndarray:
    return start + stride * np.arange(context_frames + future_frames)


def window_span(stride: int, context_frames: int, future_frames: int) -> int:
    """Number of episode frames a window covers (first to last frame inclusive)."""
    return (context_frames + future_frames - 1) * stride + 1


def compose_actions(actions: np.ndarray, t: int, stride: int) -> np.ndarray:
    """The single action equivalent to recorded ``actions[t : t+stride]`` (float32 [7])."""
    a = np.asarray(actions[t:t + stride], np.float64)
    if a.shape[0] != stride:
        raise IndexError(f"need actions[{t}:{t + stride}], episode has {len(actions)}")
    out = np.empty(7)
    out[:3] = a[:, :3].sum(0)
    if stride == 1:
        out[3:6] = a[0, 3:6]
    else:
        m = np.eye(3)
        for r in a[:, 3:6]:  # later rotations act on the left (world frame)
            m = rotations.rotvec_to_matrix(r) @ m
        out[3:6] = rotations.matrix_to_rotvec(m)
    out[6] = a[-1, 6]
    return out.astype(np.float32)


def pseudo_actions(ee_pose: np.ndarray, frame_indices: np.ndarray, actions: np.ndarray | None = None) -> np.ndarray:
    """Actions between consecutive given frames from end-effector poses: float32 [len(frame_indices) - 1, 7].
    The gripper entry is the command in force at the end of each interval, ``actions[t_next - 1, 6]`` (the one
    meaning the gripper entry has everywhere); without ``actions`` the measured gap ``ee_pose[t_next, 6]`` stands
    in for it (data that recorded no commands)."""
    idx = np.asarray(frame_indices)
    p = np.asarray(ee_pose, np.float64)[idx]
    out = np.empty((len(p) - 1, 7))
    out[:, :3] = p[1:, :3] - p[:-1, :3]
    out[:, 3:6] = rotations.relative_rotvec(p[:-1, 3:6], p[1:, 3:6])
    out[:, 6] = p[1:, 6] if actions is None else np.asarray(actions)[idx[1:] - 1, 6]
    return out.astype(np.float32)


def start_pose(actions: np.ndarray, ee_pose: np.ndarray, t: int) -> np.ndarray:
    """The pose condition of frame t: the measured pose with the gripper command in force (``actions[t-1, 6]``;
    at t = 0 none was given yet, so the measured gap)."""
    p = np.asarray(ee_pose[t], np.float32).copy()
    if t > 0:
        p[6] = actions[t - 1, 6]
    return p


def integrate_poses(pose: np.ndarray, actions: np.ndarray) -> np.ndarray:
    """float32 [n + 1, 7]: ``pose`` and the poses after each of ``actions`` [n, 7] (xyz summed, rotations composed
    on the left, gripper = command); the numpy twin of ``imagination_state.frame_poses``. The rotations are
    converted in two batched calls and composed as matrices: per-step conversions cost more than the rest of a
    training window (a data-loading bottleneck on an accelerator)."""
    pose, actions = np.asarray(pose, np.float64), np.asarray(actions, np.float64)
    steps = rotations.rotvec_to_matrix(actions[:, 3:6])  # [n, 3, 3]
    mats = [rotations.rotvec_to_matrix(pose[3:6])]
    for m in steps:
        mats.append(m @ mats[-1])
    out = np.empty((len(actions) + 1, 7))
    out[0] = pose
    out[1:, :3] = pose[:3] + np.cumsum(actions[:, :3], axis=0)
    out[1:, 3:6] = rotations.matrix_to_rotvec(np.stack(mats[1:])) if len(actions) else 0.0
    out[1:, 6] = actions[:, 6]
    return out.astype(np.float32)


def window_actions(actions: np.ndarray, ee_pose: np.ndarray, start: int, stride: int, context_frames: int,
                   future_frames: int, pseudo: bool) -> np.ndarray:
    """Un-normalised float32 [T, 7] actions of a window (see the module docstring)."""
    idx = window_frame_indices(start, stride, context_frames, future_frames)[context_frames - 1:]
    if pseudo:
        return pseudo_actions(ee_pose, idx, actions)
    return np.stack([compose_actions(actions, int(t), stride) for t in idx[:-1]])


# -- episode access ---------------------------------------------------------------------------------------------
class _EpisodeReader:
    """Picklable, thread-safe LRU of memory-mapped episodes (file handles are opened lazily in each process)."""

    def __init__(self, root: str, episode_ids: list[str], views: tuple[str, ...], max_open: int = 256):
        self.root, self.episode_ids, self.views, self.max_open = root, list(episode_ids), tuple(views), max_open
        self._init_cache()

    def _init_cache(self):
        self._cache: collections.OrderedDict[int, Episode] = collections.OrderedDict()
        self._lock = threading.Lock()
        self._store = None

    def __getstate__(self):
        return {k: getattr(self, k) for k in ("root", "episode_ids", "views", "max_open")}

    def __setstate__(self, state):
        self.__dict__.update(state)
        self._init_cache()

    def get(self, i: int) -> Episode:
        with self._lock:
            ep = self._cache.get(i)
            if ep is not None:
                self._cache.move_to_end(i)
                return ep
        # Opening is serialised: np.load parses .npy headers with ast.literal_eval, which is not thread-safe on
        # CPython 3.11 ("SystemError: AST constructor recursion depth mismatch" under grain read threads).
        with _OPEN_LOCK:
            if self._store is None:
                self._store = EpisodeStore(self.root)
            ep = self._store.load(self.episode_ids[i], mmap=True, validate=False)
        with self._lock:
            self._cache[i] = ep
            while len(self._cache) > self.max_open:
                self._cache.popitem(last=False)
        return ep


class _TrajectoryReader:
    """Picklable, thread-safe cache of every episode's ``actions`` and ``ee_pose`` (a few kB each), for windows
    whose frames come from the latent cache: parsing an episode's meta.json on every LRU miss cost more than the
    rest of the window."""

    def __init__(self, root: str, episode_ids: list[str]):
        self.root, self.episode_ids = root, list(episode_ids)
        self._init_cache()

    def _init_cache(self):
        self._cache: dict[int, _Trajectory] = {}
        self._lock = threading.Lock()

    def __getstate__(self):
        return {"root": self.root, "episode_ids": self.episode_ids}

    def __setstate__(self, state):
        self.__dict__.update(state)
        self._init_cache()

    def get(self, i: int) -> "_Trajectory":
        tr = self._cache.get(i)
        if tr is None:
            d = os.path.join(self.root, self.episode_ids[i])
            with _OPEN_LOCK:  # np.load's header parsing is not thread-safe (see _EpisodeReader.get)
                tr = _Trajectory(np.load(os.path.join(d, "actions.npy")), np.load(os.path.join(d, "ee_pose.npy")))
            with self._lock:
                self._cache[i] = tr
        return tr


class _Trajectory(NamedTuple):
    actions: np.ndarray
    ee_pose: np.ndarray


@dataclasses.dataclass(frozen=True)
class WindowIndex:
    episode_ids: list[str]
    pairs: np.ndarray  # int64 [N, 2]: (episode number, start frame)

    def __len__(self) -> int:
        return int(self.pairs.shape[0])


def build_index(store: EpisodeStore, cfg) -> WindowIndex:
    """Validate every episode (mmap: cheap) and list every (episode, start) valid for the largest stride.
    Raises EpisodeError naming the episode and field; reads only, never modifies the store."""
    views = tuple(cfg.views)
    missing = [v for v in views if v not in store.views]
    if missing:
        raise ValueError(f"{store.root}: dataset views {store.views} lack {missing} (DataConfig.views={views})")
    if tuple(store.image_size) != tuple(cfg.image_size):
        raise ValueError(f"{store.root}: dataset image size {tuple(store.image_size)}, "
                         f"DataConfig.image_size={tuple(cfg.image_size)}")
    if not cfg.strides or min(cfg.strides) < 1:
        raise ValueError(f"strides must be positive integers, got {cfg.strides}")
    span = window_span(max(cfg.strides), cfg.context_frames, cfg.future_frames)
    ids = store.episode_ids()
    if not ids:
        raise ValueError(f"{store.root}: no episodes")
    pairs = []
    for n, eid in enumerate(ids):
        ep = store.load(eid, mmap=True, validate=True, min_length=span)
        starts = np.arange(ep.length - span + 1)
        pairs.append(np.stack([np.full_like(starts, n), starts], -1))
    return WindowIndex(ids, np.concatenate(pairs).astype(np.int64))


class _MakeWindow:
    """random_map transform: (episode number, start) + per-sample rng -> one training window."""

    def __init__(self, reader: _EpisodeReader, cfg, stats: NormStats, latents=None):
        self.reader, self.stats, self.latents = reader, stats, latents
        self.views = tuple(cfg.views)
        self.K, self.T = cfg.context_frames, cfg.future_frames
        self.strides = tuple(int(s) for s in cfg.strides)
        self.p = float(cfg.pseudo_action_prob)

    def __call__(self, pair, rng: np.random.Generator) -> dict:
        stride = self.strides[int(rng.integers(len(self.strides)))]
        pseudo = bool(rng.random() < self.p)
        ep_num, start = int(pair[0]), int(pair[1])
        ep = self.reader.get(ep_num)
        idx = window_frame_indices(start, stride, self.K, self.T)
        acts = window_actions(ep.actions, ep.ee_pose, start, stride, self.K, self.T, pseudo)
        pose = integrate_poses(start_pose(ep.actions, ep.ee_pose, int(idx[self.K - 1])), acts)
        out = {"actions": self.stats.normalize(acts), "pose": self.stats.normalize_pose(pose),
               "stride": np.int32(stride), "pseudo": np.bool_(pseudo), "episode": np.int32(ep_num),
               "start": np.int32(start)}
        if self.latents is not None:  # cached tokenizer latents instead of frames (data/latent_cache.py)
            out["latents"] = self.latents.window(ep_num, idx)
        else:
            out["frames"] = np.stack([np.asarray(ep.frames[v][idx]) for v in self.views])  # only these frames
        return out


class _LocalToGlobal:
    """Local sample j of process p -> global sample index."""

    def __init__(self, global_batch: int, local_batch: int, process_index: int):
        self.g, self.l, self.p = global_batch, local_batch, process_index

    def __call__(self, j):
        j = int(j)
        return (j // self.l) * self.g + self.p * self.l + (j % self.l)


class _Fetch:
    def __init__(self, samples: grain.MapDataset):
        self.samples = samples

    def __call__(self, g):
        return self.samples[int(g)]


def collate(samples: list[dict]) -> dict:
    return {k: np.stack([s[k] for s in samples]) for k in samples[0]}


def make_dataset(cfg, store: EpisodeStore, stats: NormStats, process_index: int = 0, process_count: int = 1,
                 index: WindowIndex | None = None, latents=None) -> grain.MapDataset:
    """Infinite ``MapDataset`` of this process's local batches (``ds[i]`` = local batch i): dict with
    ``frames`` uint8 [b, V, K+T, H, W, 3] (V in cfg.views order; with ``latents``, a ``latent_cache.LatentReader``,
    ``latents`` float16 [b, V, K+T, h, w, C] instead), ``actions`` float32 [b, T, 7] (normalised), ``pose``
    float32 [b, T+1, 7] (normalised pose condition), ``stride`` int32 [b], ``pseudo`` bool [b], plus
    ``episode``/``start`` int32 [b] (provenance, for debugging), where b = cfg.batch_size // process_count."""
    if cfg.batch_size % process_count:
        raise ValueError(f"batch_size {cfg.batch_size} is not divisible by process_count {process_count}")
    if not 0 <= process_index < process_count:
        raise ValueError(f"process_index {process_index} not in [0, {process_count})")
    index = index if index is not None else build_index(store, cfg)
    reader = (_TrajectoryReader(str(store.root), index.episode_ids) if latents is not None
              else _EpisodeReader(str(store.root), index.episode_ids, tuple(cfg.views)))
    samples = (grain.MapDataset.source(index.pairs)
               .shuffle(seed=int(cfg.seed))
               .repeat()
               .random_map(_MakeWindow(reader, cfg, stats, latents), seed=int(cfg.seed) + 1))
    local_batch = cfg.batch_size // process_count
    num_local = (len(samples) // cfg.batch_size) * local_batch
    local = (grain.MapDataset.range(num_local)
             .map(_LocalToGlobal(cfg.batch_size, local_batch, process_index))
             .map(_Fetch(samples)))
    return local.batch(local_batch, drop_remainder=True, batch_fn=collate)


def make_iterator(cfg, store: EpisodeStore, stats: NormStats, process_index: int = 0, process_count: int = 1,
                  dataset: grain.MapDataset | None = None) -> grain.DatasetIterator:
    """Iterator over local batches with ``get_state()`` / ``set_state(state)`` for exact resume. With
    ``cfg.read_threads > 0`` batches are read ahead by that many threads (same order, same state semantics)."""
    ds = dataset if dataset is not None else make_dataset(cfg, store, stats, process_index, process_count)
    if cfg.read_threads > 0:
        opts = grain.ReadOptions(num_threads=int(cfg.read_threads), prefetch_buffer_size=2 * int(cfg.read_threads))
    else:
        opts = grain.ReadOptions(num_threads=0, prefetch_buffer_size=0)
    return iter(ds.to_iter_dataset(opts))

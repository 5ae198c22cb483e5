"""grain pipeline: training windows with multi-FPS strides and pseudo-actions, normalised actions, local batches.

A *window* starting at frame ``t0`` with stride ``s`` holds frames ``t0 + s*i`` for ``i in range(K + T)`` of every
view (K = ``cfg.context_frames`` clean context frames, T = ``cfg.future_frames`` future frames) and T actions: action
``j`` moves frame ``K-1+j`` to frame ``K+j`` (frame indices ``t = t0 + s*(K-1+j)`` -> ``t + s``):

- recorded (stride 1): ``actions[t]``; stride s > 1: the s recorded actions ``actions[t..t+s-1]`` composed as the
  dataset's action space says (``data/action_space.py``; delta_ee: xyz summed, rotations composed exactly
  ``R(a_{t+s-1}) ... R(a_t)``, gripper = last target ``actions[t+s-1, 6]``; absolute targets: the last one;
  velocities: the mean);
- pseudo (probability ``cfg.pseudo_action_prob`` per sample; delta_ee datasets with an ``ee_pose`` only, any other
  dataset refuses a non-zero probability): from end-effector poses,
  ``(xyz_{t+s} - xyz_t, rotvec(R_{t+s} R_t^T), gripper target actions[t+s-1, 6])``.

The gripper entry has one meaning everywhere: the *commanded* target width (what a policy outputs and what
rollouts integrate), never the measured finger gap of ``ee_pose`` (which lags the command and stops on a grasped
object: on an expert episode the two differ by up to 5.6 cm).

Both are normalised with ``NormStats`` (per-dimension mean/std over all recorded actions of the store).

Every window also carries the *pose condition* ``pose`` [T + 1, A]: the imagined robot state of frame K-1
(``ActionSpace.start_state``; delta_ee: the end-effector pose with the gripper command in force, ``actions[t-1, 6]``)
and of every future frame, integrated from it with the window's actions (``ActionSpace.integrate``, at ``s / fps``
seconds per action) -- the numpy twin of ``imagination_state.frame_poses``, which rollouts use -- normalised with
the state statistics of ``NormStats``.

Batch i of process p is a deterministic function of (cfg.seed, i, p, process_count): the index of all valid
(episode, start) pairs (valid for the largest stride; with ``cfg.window_weights``, windows where an object moves or
the gripper acts repeated: ``data/window_weights.py``) is shuffled per epoch, repeated forever, per-sample draws
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

from sc3_jax.data import window_weights
from sc3_jax.data.action_space import DELTA_EE, ActionSpace
from sc3_jax.data.episodes import Episode, EpisodeStore
from sc3_jax.data.norm_stats import NormStats
from sc3_jax.core.errors import UserError

_OPEN_LOCK = threading.Lock()


# -- window semantics (pure functions, also used by rollouts / tests) -------------------------------------------
def window_frame_indices(start: int, stride: int, context_frames: int, future_frames: int) -> np.ndarray:
    return start + stride * np.arange(context_frames + future_frames)


def window_span(stride: int, context_frames: int, future_frames: int) -> int:
    """Number of episode frames a window covers (first to last frame inclusive)."""
    return (context_frames + future_frames - 1) * stride + 1


def compose_actions(actions: np.ndarray, t: int, stride: int, space: ActionSpace) -> np.ndarray:
    """The single action equivalent to recorded ``actions[t : t+stride]`` (float32 [A])."""
    a = actions[t:t + stride]
    if len(a) != stride:
        raise IndexError(f"need actions[{t}:{t + stride}], episode has {len(actions)}")
    return space.compose(a)


def pseudo_actions(ee_pose: np.ndarray, frame_indices: np.ndarray, actions: np.ndarray | None = None) -> np.ndarray:
    """Actions between consecutive given frames from end-effector poses: float32 [len(frame_indices) - 1, 7]
    (``ActionSpace.pseudo``: the gripper entry is the command in force at the end of each interval)."""
    return DELTA_EE.pseudo(ee_pose, frame_indices, actions)


def start_pose(actions: np.ndarray, ee_pose: np.ndarray, t: int) -> np.ndarray:
    """The pose condition of frame t: the measured pose with the gripper command in force (``actions[t-1, 6]``;
    at t = 0 none was given yet, so the measured gap)."""
    return DELTA_EE.start_state(actions, ee_pose, None, t)


def integrate_poses(pose: np.ndarray, actions: np.ndarray, space: ActionSpace,
                    dt: float = 1.0) -> np.ndarray:
    """float32 [n + 1, A]: ``pose`` and the imagined states after each of ``actions`` [n, A] (``dt`` seconds per
    action, for velocities); the numpy twin of ``imagination_state.frame_poses``."""
    return space.integrate(pose, actions, dt)


def window_actions(actions: np.ndarray, ee_pose: np.ndarray | None, start: int, stride: int, context_frames: int,
                   future_frames: int, pseudo: bool, space: ActionSpace) -> np.ndarray:
    """Un-normalised float32 [T, A] actions of a window (see the module docstring)."""
    idx = window_frame_indices(start, stride, context_frames, future_frames)[context_frames - 1:]
    if pseudo:
        return space.pseudo(ee_pose, idx, actions)
    return np.stack([compose_actions(actions, int(t), stride, space) for t in idx[:-1]])


def window_pose(space: ActionSpace, actions: np.ndarray, ee_pose: np.ndarray | None, state: np.ndarray | None,
                t: int, window_acts: np.ndarray, dt: float) -> np.ndarray:
    """Un-normalised float32 [T + 1, A] pose condition of a window whose frame K-1 is episode frame ``t``."""
    return space.integrate(space.start_state(actions, ee_pose, state, t), window_acts, dt)


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
    """Picklable, thread-safe cache of every episode's ``actions``, ``ee_pose`` and ``state`` (those the store has;
    a few kB each), for windows whose frames come from the latent cache: parsing an episode's meta.json on every LRU
    miss cost more than the rest of the window."""

    def __init__(self, root: str, episode_ids: list[str], fields: tuple[str, ...] = ("actions", "ee_pose")):
        self.root, self.episode_ids, self.fields = root, list(episode_ids), tuple(fields)
        self._init_cache()

    def _init_cache(self):
        self._cache: dict[int, _Trajectory] = {}
        self._lock = threading.Lock()

    def __getstate__(self):
        return {"root": self.root, "episode_ids": self.episode_ids, "fields": self.fields}

    def __setstate__(self, state):
        self.__dict__.update(state)
        self._init_cache()

    def get(self, i: int) -> "_Trajectory":
        tr = self._cache.get(i)
        if tr is None:
            d = os.path.join(self.root, self.episode_ids[i])
            with _OPEN_LOCK:  # np.load's header parsing is not thread-safe (see _EpisodeReader.get)
                tr = _Trajectory(**{f: np.load(os.path.join(d, f"{f}.npy")) for f in self.fields})
            with self._lock:
                self._cache[i] = tr
        return tr


class _Trajectory(NamedTuple):
    actions: np.ndarray
    ee_pose: np.ndarray | None = None
    state: np.ndarray | None = None


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
        raise UserError(f"{store.root}: dataset views {store.views} lack {missing} (data.views={list(views)})")
    if tuple(store.image_size) != tuple(cfg.image_size):
        raise UserError(f"{store.root}: dataset image size {list(store.image_size)}, "
                        f"data.image_size={list(cfg.image_size)}")
    refusal = store.action_space.pseudo_refusal(store.has_pose) if cfg.pseudo_action_prob > 0 else None
    if refusal:
        raise UserError(f"{store.root}: data.pseudo_action_prob={cfg.pseudo_action_prob}, but {refusal}")
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

    def __init__(self, reader: _EpisodeReader, cfg, stats: NormStats, latents=None, *, fps: float):
        self.reader, self.stats, self.latents, self.fps = reader, stats, latents, float(fps)
        self.space = stats.action_space
        self.views = tuple(cfg.views)
        self.K, self.T = cfg.context_frames, cfg.future_frames
        self.strides = tuple(int(s) for s in cfg.strides)
        self.p = float(cfg.pseudo_action_prob)
        self.anchor = bool(cfg.anchor)

    def __call__(self, pair, rng: np.random.Generator) -> dict:
        stride = self.strides[int(rng.integers(len(self.strides)))]
        pseudo = bool(rng.random() < self.p)
        ep_num, start = int(pair[0]), int(pair[1])
        ep = self.reader.get(ep_num)
        idx = window_frame_indices(start, stride, self.K, self.T)
        acts = window_actions(ep.actions, ep.ee_pose, start, stride, self.K, self.T, pseudo, self.space)
        pose = window_pose(self.space, ep.actions, ep.ee_pose, ep.state, int(idx[self.K - 1]), acts,
                           stride / self.fps)
        out = {"actions": self.stats.normalize(acts), "pose": self.stats.normalize_pose(pose),
               "stride": np.int32(stride), "pseudo": np.bool_(pseudo), "episode": np.int32(ep_num),
               "start": np.int32(start)}
        if self.anchor:  # the episode's first frame in front of the context, ``start`` frames before it
            idx, out["anchor_gap"] = np.concatenate([[0], idx]), np.int32(start)
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
    ``frames`` uint8 [b, V, K+T, H, W, 3] (V in cfg.views order; with ``cfg.anchor`` the episode's first frame in
    front, [b, V, 1+K+T, ...], and ``anchor_gap`` int32 [b] the frames between it and the first context frame; with
    ``latents``, a ``latent_cache.LatentReader``, ``latents`` float16 [b, V, K+T, h, w, C] instead), ``actions`` float32 [b, T, A] (normalised), ``pose``
    float32 [b, T+1, A] (normalised pose condition), ``stride`` int32 [b], ``pseudo`` bool [b], plus
    ``episode``/``start`` int32 [b] (provenance, for debugging), where b = cfg.batch_size // process_count.
    ``stats`` must be in the store's action space (a fine-tune keeps its source's units, not its space)."""
    if not stats.action_space.same_kind(store.action_space):
        raise UserError(f"{store.root}: dataset.json declares {store.action_space.kind} "
                        f"{store.action_space.dim}-D actions, the norm stats are of {stats.action_space.kind} "
                        f"{stats.action_space.dim}-D ones (a world model trained on another robot)")
    if cfg.batch_size % process_count:
        raise ValueError(f"batch_size {cfg.batch_size} is not divisible by process_count {process_count}")
    if not 0 <= process_index < process_count:
        raise ValueError(f"process_index {process_index} not in [0, {process_count})")
    index = index if index is not None else build_index(store, cfg)
    fields = tuple(f for f in store.array_fields() if f in _Trajectory._fields)  # what windows read
    reader = (_TrajectoryReader(str(store.root), index.episode_ids, fields) if latents is not None
              else _EpisodeReader(str(store.root), index.episode_ids, tuple(cfg.views)))
    # data.window_weights: windows where something happens repeated (default: index.pairs itself, the uniform order)
    pairs = window_weights.weighted_pairs(store, index, cfg, say=process_index == 0)
    samples = (grain.MapDataset.source(pairs)
               .shuffle(seed=int(cfg.seed))
               .repeat()
               .random_map(_MakeWindow(reader, cfg, stats, latents, fps=store.fps), seed=int(cfg.seed) + 1))
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

"""The learned robot state: what the robot's own sensors would read inside an imagined rollout.

A policy reads ``observation.state`` (joints, velocities, gripper, end-effector xyz: any size S the dataset records),
and inside the world model there is no robot to read it from. Integrating the commanded actions is exact only when
the actions are targets or velocities of that very state; for end-effector deltas under a joint state, or a state
that holds velocities, it is wrong. So a small network learns the state from the data the world model learns from:

    s_k = s_{k-1} + f(s_{k-1}, a_k, frame_k)      (normalised units; f: a 3-layer MLP)

``a_k`` is the model-rate action that moved frame k-1 to frame k, ``frame_k`` the frame it produced (every view,
area-resized to 8 x 8: where the arm is, not its texture). In a rollout ``frame_k`` is the imagined frame, so the
state follows what the video shows, and the head runs after the DiT: a world model trained before gains the robot's
state without training the DiT again (GE-Sim 2.0's "state expert" decodes proprioception from the video in the same
spirit). It is trained on sequences of ``UNROLL`` steps fed its own predictions (a rollout applies it for every
kept frame of every chunk, so one-step training alone would let errors compound), with noise on the frame features
(imagined frames are blurrier than recorded ones).

Saved as ``state_head.npz`` beside a world model's ``config.json`` (a training workdir or an export): parameters
and the normalisation of states and actions, all float32 (a few hundred KB).
"""
from __future__ import annotations

import dataclasses
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from sc3_jax.core import atomic
from sc3_jax.core.errors import UserError

FILE = "state_head.npz"
FEATURE_SIZE = (8, 8)  # each view area-resized to this many pixels: the arm's and the objects' positions
UNROLL = 8  # steps of each training sequence, fed the head's own predictions


@dataclasses.dataclass(frozen=True)
class FitConfig:
    """How the head is trained (``sc3 train-state``; ``sc3 train`` uses the defaults)."""

    steps: int = 3000
    """optimizer steps"""
    batch: int = 64
    """sequences per step"""
    lr: float = 1e-3
    """Adam learning rate (cosine decay to 0)"""
    hidden: int = 256
    """width of the MLP's two hidden layers"""
    feature_noise: float = 0.05
    """Gaussian noise on the frame features during training, in pixel units of [-1, 1]"""
    seed: int = 0
    """initialisation, batches and noise"""


def features(frames_unit: jax.Array) -> jax.Array:
    """Frame features [..., V * 8 * 8 * 3] of frames [..., V, H, W, 3] in [-1, 1] (the same function in training
    and in a rollout)."""
    *lead, V, H, W, C = frames_unit.shape
    small = jax.image.resize(frames_unit.astype(jnp.float32), (*lead, V, *FEATURE_SIZE, C), "linear", antialias=True)
    return small.reshape(*lead, V * FEATURE_SIZE[0] * FEATURE_SIZE[1] * C)


def _step_n(head: dict, s_n, action, feats):
    """One step in normalised state units: ``s_n`` [S], the raw model-rate ``action`` [A], the frame's
    :func:`features`."""
    a_n = (action - head["action_mean"]) / head["action_std"]
    x = jnp.concatenate([s_n, a_n, feats], axis=-1)
    h = jax.nn.gelu(x @ head["w1"] + head["b1"])
    h = jax.nn.gelu(h @ head["w2"] + head["b2"])
    return s_n + h @ head["w3"] + head["b3"]


def unroll_features(head: dict, state, actions, feats):
    """States [n, S] (raw units) after each of ``actions`` [n, A], from ``state`` [S], given the :func:`features`
    [n, F] of the frames the actions produced."""
    def body(s, x):
        s = _step_n(head, s, *x)
        return s, s
    s_n = (state - head["state_mean"]) / head["state_std"]
    return jax.lax.scan(body, s_n, (actions, feats))[1] * head["state_std"] + head["state_mean"]


def unroll(head: dict, state, actions, frames_unit):
    """:func:`unroll_features` of frames [n, V, H, W, 3] in [-1, 1] (a rollout's kept frames)."""
    return unroll_features(head, state, actions, features(frames_unit))


# ================================================================================================================
# Data: sequences of (state, model-rate action, frame) from an episode store
# ================================================================================================================
def transitions(store_path: str | Path, views, stride: int, action_space, episodes=None):
    """Per episode of the store: (states [n, S], model-rate actions [n - 1, A], frame features [n, F]) at every
    ``stride``-th frame from each phase 0..stride-1 (so every frame is used), actions composed over each stride as
    the training windows and a rollout compose them."""
    from sc3_jax.data.episodes import EpisodeStore
    from sc3_jax.model.tokenizer import to_unit

    store = EpisodeStore(store_path)
    if not store.state_dim:
        raise UserError(f"{store_path}: the episode store records no robot state (dataset.json \"state\"): there is "
                        "nothing to learn; its world model hands policies the integrated commands")
    feats_of = jax.jit(lambda f: features(to_unit(f)))
    out = []
    for eid in store.episode_ids()[:episodes]:
        ep = store.load(eid)
        frames = np.stack([np.asarray(ep.frames[v]) for v in views], axis=1)  # [T, V, H, W, 3]
        f_all = np.asarray(feats_of(frames))
        for phase in range(min(stride, ep.length)):
            idx = np.arange(phase, ep.length, stride)
            if len(idx) < 2:
                continue
            acts = np.stack([action_space.compose(ep.actions[i:i + stride]) for i in idx[:-1]])
            out.append((np.asarray(ep.state, np.float32)[idx], acts.astype(np.float32), f_all[idx]))
    if not out:
        raise UserError(f"{store_path}: no episode has two frames {stride} apart")
    return out


def _flat(seqs, n: int):
    """The sequences end to end, as flat arrays -- states [N, S], actions [N, A] (row i moves state i to i + 1; a
    zero row ends each sequence), features [N, F] float16 -- and the starts [W] of every ``n``-step window inside one
    sequence: a window is gathered from them on the device, so memory grows with the frames, not with n."""
    states, acts, feats, starts, at = [], [], [], [], 0
    for st, ac, fe in seqs:
        states.append(st)
        acts.append(np.concatenate([ac, np.zeros((1, ac.shape[1]), np.float32)]))
        feats.append(fe.astype(np.float16))
        starts.append(at + np.arange(len(ac) - n + 1))
        at += len(st)
    return (np.concatenate(states), np.concatenate(acts), np.concatenate(feats),
            np.concatenate(starts).astype(np.int32))


# ================================================================================================================
# Training, saving, loading
# ================================================================================================================
def init(key, state_dim: int, action_dim: int, feature_dim: int, hidden: int) -> dict:
    k1, k2, k3 = jax.random.split(key, 3)
    n_in = state_dim + action_dim + feature_dim
    return {"w1": jax.random.normal(k1, (n_in, hidden)) / np.sqrt(n_in), "b1": jnp.zeros(hidden),
            "w2": jax.random.normal(k2, (hidden, hidden)) / np.sqrt(hidden), "b2": jnp.zeros(hidden),
            "w3": jax.random.normal(k3, (hidden, state_dim)) * 0.01 / np.sqrt(hidden), "b3": jnp.zeros(state_dim)}


NORMS = ("state_mean", "state_std", "action_mean", "action_std")


def fit(seqs, cfg: FitConfig = FitConfig(), progress: bool = False) -> tuple[dict, dict]:
    """The head trained on ``transitions(...)``'s sequences: (head, {"loss": final training loss, "sequences": n})."""
    import optax
    from tqdm import tqdm

    n = min(UNROLL, min(len(a) for _, a, _ in seqs))
    states, acts, feats, starts = _flat(seqs, n)
    real = np.concatenate([a for _, a, _ in seqs])  # the actions without the padding rows
    norm = {"state_mean": states.mean(0), "state_std": np.maximum(states.std(0), 1e-3),
            "action_mean": real.mean(0), "action_std": np.maximum(real.std(0), 1e-3)}
    key = jax.random.key(cfg.seed)
    params = init(key, states.shape[1], acts.shape[1], feats.shape[-1], cfg.hidden)
    opt = optax.adam(optax.cosine_decay_schedule(cfg.lr, cfg.steps))
    norm_j = {k: jnp.asarray(v) for k, v in norm.items()}
    data = tuple(jnp.asarray(x) for x in (states, acts, feats, starts))

    def loss(p, g, k):
        """Windows starting at flat rows ``g`` [b]: n steps fed the head's own predictions."""
        st, ac, fe, _ = data
        idx = g[:, None] + jnp.arange(n)[None]  # [b, n]: the actions of each window
        head = {**p, **norm_j}
        f = fe[idx + 1].astype(jnp.float32)
        f = f + cfg.feature_noise * jax.random.normal(k, f.shape)
        pred = jax.vmap(unroll_features, (None, 0, 0, 0))(head, st[g], ac[idx], f)  # [b, n, S], raw units
        return jnp.mean(jnp.square((pred - st[idx + 1]) / norm_j["state_std"]))

    @jax.jit
    def train_step(p, o, k):
        kb, kn = jax.random.split(k)
        g = data[3][jax.random.randint(kb, (cfg.batch,), 0, len(starts))]
        val, grads = jax.value_and_grad(loss)(p, g, kn)
        upd, o = opt.update(grads, o)
        return optax.apply_updates(p, upd), o, val

    o = opt.init(params)
    val = jnp.nan
    for i in tqdm(range(cfg.steps), desc="state head", unit="step", disable=not progress):
        params, o, val = train_step(params, o, jax.random.fold_in(key, i + 1))
    head = {k: np.asarray(v, np.float32) for k, v in {**params, **norm}.items()}
    return head, {"loss": float(val), "sequences": len(starts), "unroll": n}


def save(head: dict, model_dir: str | Path, meta: dict) -> Path:
    """``model_dir/state_head.npz`` (atomically): the head and ``meta`` (what it was trained on, its figures)."""
    import json
    path = Path(model_dir) / FILE
    atomic.save_npz(path, **head, meta=np.asarray(json.dumps(meta)))
    return path


def load(model_dir: str | Path) -> dict | None:
    """The head saved beside the world model at ``model_dir`` as jnp arrays, or None when it has none."""
    path = Path(model_dir) / FILE
    if not path.exists():
        return None
    with atomic.open_npz(path, "train it again: sc3 train-state --world-model WORLD_MODEL") as z:
        return {k: jnp.asarray(z[k]) for k in z.files if k != "meta"}


def state_dim(head: dict | None) -> int:
    return 0 if head is None else int(head["state_mean"].shape[0])


# ================================================================================================================
# A world model's head: trained on its training store, judged on held-out episodes
# ================================================================================================================
def errors(head: dict, seqs) -> dict:
    """Held-out figures over whole episodes, unrolled from each one's first state as a rollout would be (recorded
    frames): the RMS error per state dimension in units of that dimension's spread, averaged over dimensions, for
    the head and for holding the first state."""
    std = np.asarray(head["state_std"])
    run = jax.jit(unroll_features)
    se_head, se_hold, n = 0.0, 0.0, 0
    for states, acts, feats in seqs:
        pred = np.asarray(run(head, jnp.asarray(states[0]), jnp.asarray(acts), jnp.asarray(feats[1:])))
        se_head += float(np.sum(np.square((pred - states[1:]) / std)))
        se_hold += float(np.sum(np.square((states[:1] - states[1:]) / std)))
        n += states[1:].size
    return {"head": float(np.sqrt(se_head / max(n, 1))), "hold": float(np.sqrt(se_hold / max(n, 1)))}


def train_for(model_dir: str | Path, data: str | None = None, cfg: FitConfig = FitConfig(),
              progress: bool = True) -> tuple[Path, dict]:
    """Train the head of the world model at ``model_dir`` on its training store (``data``: another store of the same
    robot), holding out the store's last tenth of episodes (at least one) for the figures; saves it beside the model.
    Returns (its path, {"heldout": errors(...), "episodes": {...}, "fit": fit(...)'s figures})."""
    from sc3_jax.model import checkpoint
    from sc3_jax.data.episodes import EpisodeStore

    wcfg, stats = checkpoint.read_config(model_dir), checkpoint.read_norm_stats(model_dir)
    data = data or wcfg.data.path
    store = EpisodeStore(data)
    stride = max(1, round(store.fps / wcfg.rollout.control_hz))
    ids = store.episode_ids()
    held = max(1, len(ids) // 10) if len(ids) > 1 else 0
    seqs = transitions(data, wcfg.data.views, stride, stats.action_space, episodes=len(ids))
    per_ep = len(seqs) // max(len(ids), 1)  # transitions() gives `stride` phases per episode, in episode order
    train_seqs, held_seqs = seqs[:len(seqs) - held * per_ep], seqs[len(seqs) - held * per_ep:][::max(per_ep, 1)]
    head, fitted = fit(train_seqs or seqs, cfg, progress)
    info = {"store": str(data), "stride": stride, "episodes": {"train": len(ids) - held, "heldout": held},
            "fit": fitted, "heldout": errors(head, held_seqs) if held_seqs else None,
            "state_names": list(store.state_names)}
    return save(head, model_dir, info), info

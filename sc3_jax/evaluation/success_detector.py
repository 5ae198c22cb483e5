"""A success detector learnt from a lab's own labelled episodes, to score imagined rollouts where no simulator says
whether the task was done (``sc3 train-detector``; ``sweep episodes --scorer detector:DIR``).

Labels. An episode store keeps one outcome per episode (``meta.json`` ``"labels": {criterion: bool}``; ``sc3 data
import-lerobot`` writes LeRobot's ``next.success`` there). Per frame we follow LeRobot's convention that a recorded
episode ends once its task is done:
  * positive: the last ``end_frames`` frames of an episode labelled done (the task's final state);
  * negative: the last ``end_frames`` frames of an episode labelled not done (its final state: the hardest
    negatives, e.g. the object set down beside its target), other frames of it at random, and frames of a done
    episode more than ``margin_s`` seconds before its end (the task not yet done);
frames in between are left out (the task is being finished there). A data set whose episodes run on after success
breaks this rule; its detector's held-out agreement (below) says so.

The net: a small CNN over every view at its own size (views side by side; a block a few pixels wide would vanish in a
resize), max-pooled over the image (done is a local configuration: object on target) then an MLP -> one logit.

An episode (real or imagined) is judged done when ``consecutive`` successive frames are each above ``threshold``:
LeRobot's own evaluation reduces ``next.success`` with ``any``, and two frames in a row keep one noisy imagined frame
from deciding. ``train`` measures this rule on held-out episodes against their labels (``agreement``), the number to
read before trusting the detector on imagined rollouts.
"""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax

from sc3_jax.core import atomic
from sc3_jax.core.errors import UserError
from sc3_jax.policies import convnet
from sc3_jax.policies.convnet import conv, conv_init, dense_init, mlp

WEIGHTS, INFO = "detector.npz", "detector.json"


@dataclasses.dataclass(frozen=True)
class DetectorConfig:
    criterion: str = "success"
    """the episode label it learns (meta.json "labels")"""
    end_frames: int = 2
    """frames at the end of a done episode taken as done"""
    margin_s: float = 1.5
    """frames of a done episode this many seconds before its end or earlier are taken as not done"""
    negatives_per_episode: int = 6
    """not-done frames drawn per episode (at random, from the seed)"""
    steps: int = 1500
    """training steps"""
    batch: int = 32
    """frames per step, half of them done"""
    lr: float = 1e-3
    """peak learning rate (cosine decay to 5% of it)"""
    heldout_frac: float = 0.1
    """the last tenth of the episodes (in id order) are held out for the figures (none when there are fewer than 10)"""
    threshold: float = 0.5
    """a frame is done above this probability"""
    consecutive: int = 2
    """a rollout is done once this many successive frames are"""
    seed: int = 0
    """the frame draws and the initialisation"""


def init(key: jax.Array, widths: tuple[int, int, int] = (16, 32, 32)) -> dict:
    ks = jax.random.split(key, 6)
    w1, w2, w3 = widths
    return {"c1": conv_init(ks[0], 3, 3, w1), "c2": conv_init(ks[1], 3, w1, w2), "c3": conv_init(ks[2], 3, w2, w3),
            "d1": dense_init(ks[3], 2 * w3, 64), "d2": dense_init(ks[4], 64, 64), "out": dense_init(ks[5], 64, 1, 0.1)}


def logits(net: dict, frames: jax.Array) -> jax.Array:
    """frames uint8 [B, V, H, W, 3] -> [B] logits of done."""
    b, v, h, w, _ = frames.shape
    x = jnp.moveaxis(frames, 1, 2).reshape(b, h, v * w, 3).astype(jnp.float32) / 255.0 - 0.5  # views side by side
    x = jax.nn.relu(conv(x, net["c1"], 2))
    x = jax.nn.relu(conv(x, net["c2"], 2))
    x = jax.nn.relu(conv(x, net["c3"], 1))
    return mlp(net, jnp.concatenate([x.max((1, 2)), x.mean((1, 2))], -1))[:, 0]


def decide(probs: np.ndarray, threshold: float, consecutive: int) -> bool:
    """Done when ``consecutive`` successive frames are each above ``threshold`` (fewer frames: all of them)."""
    above = np.asarray(probs) > threshold
    k = min(consecutive, len(above))
    return bool(k and np.convolve(above, np.ones(k, int), "valid").max() >= k)


def _labelled_frames(ep, cfg: DetectorConfig, fps: float, rng: np.random.Generator):
    """(frames [N, V, H, W, 3], labels [N]) of one episode by the module's rule; None when it has no such label."""
    done = (ep.meta.get("labels") or {}).get(cfg.criterion)
    if not isinstance(done, bool):
        return None
    t = ep.length
    views = list(ep.frames)
    end = list(range(max(0, t - cfg.end_frames), t))
    if done:
        pos, last = end, []
        early = np.arange(0, max(0, t - cfg.end_frames - int(round(cfg.margin_s * fps))))
    else:  # a failure's final frames are the hardest negatives (the object dropped or set down beside the target)
        pos, last = [], end
        early = np.arange(0, max(0, t - cfg.end_frames))
    neg = sorted(rng.choice(early, min(len(early), cfg.negatives_per_episode), replace=False)) if len(early) else []
    neg = last + [int(i) for i in neg]
    idx = pos + neg
    frames = np.stack([np.stack([np.asarray(ep.frames[v][i]) for v in views]) for i in idx])
    return frames, np.array([1] * len(pos) + [0] * len(neg), np.float32)


def probabilities(net: dict, frames: np.ndarray, batch: int = 64) -> np.ndarray:
    """[T, V, H, W, 3] -> [T] probabilities of done."""
    return np.concatenate([np.asarray(jax.nn.sigmoid(_logits(net, jnp.asarray(frames[i:i + batch]))))
                           for i in range(0, len(frames), batch)]) if len(frames) else np.zeros(0, np.float32)


_logits = jax.jit(logits)


def train(store_path: str, out: str, cfg: DetectorConfig = DetectorConfig(), progress: bool = True) -> dict:
    """Fit the detector on ``store_path``'s labelled episodes; write OUT/detector.npz and OUT/detector.json (the
    configuration, the views and the held-out figures). Returns the json."""
    from tqdm import tqdm

    from sc3_jax.data.episodes import EpisodeStore

    store = EpisodeStore(store_path)
    ids = store.episode_ids()
    n_held = int(len(ids) * cfg.heldout_frac) if len(ids) >= 10 else 0
    train_ids, held_ids = ids[:len(ids) - n_held], ids[len(ids) - n_held:]
    rng = np.random.default_rng(cfg.seed)
    xs, ys = [], []
    for e in tqdm(train_ids, desc="detector frames", unit="episode", disable=not progress):
        got = _labelled_frames(store.load(e), cfg, store.fps, rng)
        if got is not None:
            xs.append(got[0])
            ys.append(got[1])
    if not xs:
        raise UserError(f"{store_path}: no episode has a boolean labels.{cfg.criterion} in its meta.json (import a "
                        "LeRobot dataset with next.success, or label the episodes)")
    x, y = np.concatenate(xs), np.concatenate(ys)
    pos, neg = np.flatnonzero(y == 1), np.flatnonzero(y == 0)
    if not len(pos) or not len(neg):
        raise UserError(f"{store_path}: the {cfg.criterion} labels are all {bool(len(pos))}: nothing to tell apart")
    net = init(jax.random.key(cfg.seed))
    opt = optax.adamw(optax.cosine_decay_schedule(cfg.lr, cfg.steps, 0.05), weight_decay=1e-4)
    opt_state = opt.init(net)

    @jax.jit
    def step(net, opt_state, frames, labels):
        def loss_fn(n):
            return optax.sigmoid_binary_cross_entropy(logits(n, frames), labels).mean()
        loss, g = jax.value_and_grad(loss_fn)(net)
        upd, opt_state = opt.update(g, opt_state, net)
        return optax.apply_updates(net, upd), opt_state, loss

    half = cfg.batch // 2
    for _ in tqdm(range(cfg.steps), desc="detector", unit="step", disable=not progress):
        idx = np.concatenate([rng.choice(pos, half), rng.choice(neg, cfg.batch - half)])
        net, opt_state, loss = step(net, opt_state, jnp.asarray(x[idx]), jnp.asarray(y[idx]))
    info = {"store": str(store_path), "views": list(store.views), "image_size": list(store.image_size),
            "config": dataclasses.asdict(cfg), "train": {"episodes": len(xs), "frames": int(len(y)),
                                                         "done_frames": int(len(pos)), "final_loss": float(loss)},
            "heldout": _heldout(net, store, held_ids, cfg)}
    Path(out).mkdir(parents=True, exist_ok=True)
    convnet.save_params(Path(out) / WEIGHTS, net)
    atomic.write_json(Path(out) / INFO, info)
    return info


def _heldout(net, store, ids, cfg: DetectorConfig) -> dict | None:
    """Frame accuracy by the labelling rule, and the episode rule's agreement with the episodes' own labels."""
    rng = np.random.default_rng(cfg.seed + 1)
    hits, frames, agree, n, tp, fp, npos = 0, 0, 0, 0, 0, 0, 0
    for e in ids:
        ep = store.load(e)
        got = _labelled_frames(ep, cfg, store.fps, rng)
        if got is None:
            continue
        p = probabilities(net, got[0])
        hits += int(((p > cfg.threshold) == (got[1] == 1)).sum())
        frames += len(p)
        whole = np.stack([np.stack([np.asarray(ep.frames[v][i]) for v in store.views]) for i in range(ep.length)])
        said, truth = decide(probabilities(net, whole), cfg.threshold, cfg.consecutive), ep.meta["labels"][cfg.criterion]
        agree, n = agree + (said == truth), n + 1
        tp, fp, npos = tp + (said and truth), fp + (said and not truth), npos + truth
    if not n:
        return None
    return {"episodes": n, "frame_accuracy": hits / frames, "episode_agreement": agree / n,
            "done_found": tp / npos if npos else None, "false_done": fp / (n - npos) if n > npos else None}


@dataclasses.dataclass
class Detector:
    """A trained detector as a ``sweep episodes`` scorer: ``{criterion: done}`` per rollout from its frames."""
    net: dict
    views: list[str]
    cfg: DetectorConfig

    def probabilities(self, frames: np.ndarray) -> np.ndarray:
        """frames uint8 [V, T, H, W, 3] (a RolloutView's) -> [T]."""
        if frames.shape[0] != len(self.views):
            raise UserError(f"the success detector was trained on {len(self.views)} view(s) {self.views}; the "
                            f"rollout has {frames.shape[0]}")
        return probabilities(self.net, np.moveaxis(np.asarray(frames), 0, 1))

    def __call__(self, view) -> dict[str, bool]:
        return {self.cfg.criterion: decide(self.probabilities(view.frames), self.cfg.threshold, self.cfg.consecutive)}


def load(path: str | Path) -> Detector:
    p = Path(path)
    if not (p / INFO).is_file():
        raise UserError(f"{path}: no {INFO} (a success detector: train one with `sc3 train-detector`)")
    info = json.loads((p / INFO).read_text())
    net = convnet.load_params(p / WEIGHTS, "train it again with `sc3 train-detector`")
    return Detector(net, info["views"], DetectorConfig(**info["config"]))

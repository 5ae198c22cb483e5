"""Learned perception for the simulated benchmark: from the three camera frames, the per-object predicates the
ground-truth criteria are made of, and the gripper's finger gap.

The criteria (``sim/criteria.py``) are functions of three geometric predicates per object and frame -- *lifted*
(bottom more than ``LIFT_CLEARANCE`` above the table), *in the bin*, *in the can* -- plus the final state. A
scorer that reads only frames therefore needs exactly those predicates: this network predicts them for each of
the six object types (the initial condition says which three are on the table), trained by supervised learning
on simulator frames whose labels come from the physics state. It also regresses the finger gap (``ee_pose[6]``),
which an imagined rollout cannot integrate from commanded actions (closing on an object and closing on air are
commanded the same way; see ``rollout.Rollout(state_reader=...)``).

Training frames are blurred and noised at random so that the network also reads a world model's softer frames.
Reproduce the shipped weights (see docs/sweep.md): ``python -m sc3_jax.evaluate.perception --store
runs/bussing/demos runs/bussing/scorer_data runs/bussing/scorer_zoo --generate 300 --generate-policies 140 --out
sc3_jax/evaluate/perception.npz``.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

from sc3_jax.sim.convnet import dense_init, init_trunk, mlp, trunk_features
from sc3_jax.sim.criteria import LIFT_CLEARANCE, inside_container
from sc3_jax.sim.tasks import OBJECTS

PREDICATES = ("lifted", "in_bin", "in_can")
TYPES = tuple(o.name for o in OBJECTS)
N_KP = 32
WIDTH_SCALE = 100.0  # the width head predicts centimetres
DEFAULT_WEIGHTS = Path(__file__).with_name("perception.npz")


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
def init(key: jax.Array, n_views: int = 3) -> dict:
    ks = jax.random.split(key, 7)
    feat = n_views * 3 * N_KP
    return {**init_trunk(ks[:4], N_KP), "d1": dense_init(ks[4], feat, 256), "d2": dense_init(ks[5], 256, 256),
            "out": dense_init(ks[6], 256, len(TYPES) * len(PREDICATES) + 1, 0.1)}


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
    flat = {"/".join(k): np.asarray(v, np.float32) for k, v in _flatten(params)}
    np.savez_compressed(path, __meta__=json.dumps(meta or {}), **flat)


def load(path: str | Path = DEFAULT_WEIGHTS) -> dict:
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"perception weights {path} not found; train them with "
                                f"`python -m sc3_jax.evaluate.perception --store DEMOS --out {path}`")
    with np.load(path) as z:
        params: dict = {}
        for k in z.files:
            if k == "__meta__":
                continue
            a, b = k.split("/")
            params.setdefault(a, {})[b] = jnp.asarray(z[k])
    return params


def load_meta(path: str | Path = DEFAULT_WEIGHTS) -> dict:
    with np.load(path) as z:
        return json.loads(str(z["__meta__"]))


def _flatten(params):
    return [((a, b), v) for a, sub in params.items() for b, v in sub.items()]


# -- training -----------------------------------------------------------------------------------------------------
SCORER_KNOBS = ({}, {"grasp_noise": 0.04}, {"release_noise": 0.08}, {"wrong_destination_prob": 0.5},
                {"action_noise": 0.012})


def generate_scorer_data(out: str | Path, episodes: int, seed: int = 50, image_size=(64, 64),
                         progress: bool = True, policies: bool = False) -> Path:
    """Episodes of *both* tasks written as an episode store with ``meta['object_pos']``: the scripted expert with a
    rotating mixture of failure knobs, or (``policies=True``) the zoo's policies in turn, 12 s each. The scorer is a
    measuring instrument, not the world model: it may see reverse bussing (utensils in the can, trash in the bin)
    and the behaviours of the policies it will score (retries, hovering) -- on simulator seeds ``seed * 100000 + i``,
    disjoint from the evaluation seeds it is validated on."""
    import dataclasses as dc

    from tqdm import tqdm

    from sc3_jax.data.episodes import Episode, EpisodeStore
    from sc3_jax.sim.env import BussingEnv
    from sc3_jax.sim.expert import ExpertKnobs, run_expert_episode
    env = BussingEnv(image_size=tuple(image_size))
    store = EpisodeStore(out, views=list(env.views), fps=env.control_hz, image_size=tuple(image_size), create=True)
    for i in tqdm(range(episodes), desc="scorer data", disable=not progress):
        sim_seed, task = seed * 100_000 + i, ("bussing", "reverse")[i % 2]
        eid = f"ep{sim_seed:07d}"
        if eid in store:
            continue
        if policies:
            from sc3_jax.policies.base import as_host
            from sc3_jax.sim.policy_eval import run_policy_episode
            from sc3_jax.sim.zoo import ZOO, load_policy
            name = sorted(ZOO)[i % len(ZOO)]
            task = ZOO[name].task
            r = run_policy_episode(env, as_host(load_policy(name)), sim_seed, task, max_steps=240)
            source = {"policy": name}
        else:
            knobs = ExpertKnobs(**SCORER_KNOBS[(i // 2) % len(SCORER_KNOBS)])
            r = run_expert_episode(env, sim_seed, task, knobs, record=True)
            source = {"knobs": dc.asdict(knobs)}
        store.write(Episode(eid, r.frames, r.actions, r.ee_pose, r.ic.prompt,
                            {"task": task, "sim_seed": sim_seed, **source,
                             "initial_condition": r.ic.to_json(), "object_pos": np.round(r.object_pos, 4).tolist()}))
    env.close()
    return Path(out)


def load_training_data(store_roots, stride: int = 2, max_episodes: int | None = None):
    """Frames (every ``stride``-th) of every episode of one or more episode stores with ``meta['object_pos']``
    (``sc3 sim demos``, :func:`generate_scorer_data`) and their labels:
    (images uint8 [N, V, H, W, 3], labels [N, 6, 3], masks [N, 6], widths [N], episode index [N])."""
    from sc3_jax.data.episodes import EpisodeStore
    roots = [store_roots] if isinstance(store_roots, (str, Path)) else list(store_roots)
    pairs = [(EpisodeStore(r), eid) for r in roots for eid in EpisodeStore(r).episode_ids()][:max_episodes]
    xs, ys, ms, ws, eps = [], [], [], [], []
    for j, (store, eid) in enumerate(pairs):
        store_root = store.root
        ep = store.load(eid, mmap=True, validate=False)
        if "object_pos" not in ep.meta:
            raise ValueError(f"{store_root}/{eid}: no meta['object_pos'] (re-generate the demos with this version)")
        ic = ep.meta["initial_condition"]
        lab, mask = predicate_labels(np.asarray(ep.meta["object_pos"])[:ep.length], ic["objects"], ic["bin_xy"],
                                     ic["can_xy"])
        idx = np.arange(0, ep.length, stride)
        xs.append(np.stack([np.asarray(ep.frames[v])[idx] for v in store.views], 1))
        ys.append(lab[idx])
        ms.append(np.repeat(mask[None], len(idx), 0))
        ws.append(np.asarray(ep.ee_pose)[idx, 6])
        eps.append(np.full(len(idx), j))
    return (np.concatenate(xs), np.concatenate(ys), np.concatenate(ms), np.concatenate(ws).astype(np.float32),
            np.concatenate(eps))


def _augment(key, images):
    """Random 3x3 box blur (half the samples) and pixel noise: the network must also read generated frames."""
    x = images.astype(jnp.float32)
    b, v, h, w, c = x.shape
    k1, k2 = jax.random.split(key)
    flat = x.reshape(b * v, h, w, c)
    pad = jnp.pad(flat, ((0, 0), (1, 1), (1, 1), (0, 0)), mode="edge")
    blurred = sum(pad[:, i:i + h, j:j + w] for i in range(3) for j in range(3)) / 9.0
    blur = jax.random.bernoulli(k1, 0.5, (b, 1, 1, 1, 1))
    x = jnp.where(blur, blurred.reshape(x.shape), x)
    x = x + jax.random.normal(k2, x.shape) * 4.0
    return jnp.clip(jnp.round(x), 0, 255).astype(jnp.uint8)


def loss_fn(params, images, labels, masks, widths):
    logits, width = apply(params, images)
    bce = optax.sigmoid_binary_cross_entropy(logits, labels.astype(jnp.float32)).mean(-1)  # [B, 6]
    m = masks.astype(jnp.float32)
    cls = (bce * m).sum() / jnp.maximum(m.sum(), 1.0)
    reg = jnp.mean((width - widths) ** 2) * WIDTH_SCALE ** 2 * 0.1  # (cm^2)
    return cls + reg, (cls, reg)


def train(data, steps: int = 2500, batch: int = 64, lr: float = 1e-3, seed: int = 0, holdout: float = 0.1,
          progress: bool = True) -> tuple[dict, dict]:
    """Train on ``load_training_data`` output; the last ``holdout`` fraction of episodes is held out and scored.
    Returns (params, metrics: held-out per-predicate accuracy and finger-gap error)."""
    from tqdm import tqdm
    images, labels, masks, widths, eps = data
    n_ep = int(eps.max()) + 1
    # held-out episodes drawn at random: stores are ordered by generation seed, i.e. by failure knob
    test_eps = np.random.default_rng(seed).permutation(n_ep)[:int(round(n_ep * holdout))]
    is_test = np.isin(eps, test_eps)
    train_idx, test_idx = np.flatnonzero(~is_test), np.flatnonzero(is_test)
    key = jax.random.key(seed)
    params = init(key, images.shape[1])
    opt = optax.adamw(optax.warmup_cosine_decay_schedule(0.0, lr, 100, steps), weight_decay=1e-4)
    opt_state = opt.init(params)

    @jax.jit
    def step(params, opt_state, key, x, y, m, w):
        x = _augment(key, x)
        (loss, aux), g = jax.value_and_grad(loss_fn, has_aux=True)(params, x, y, m, w)
        upd, opt_state = opt.update(g, opt_state, params)
        return optax.apply_updates(params, upd), opt_state, loss

    rng = np.random.default_rng(seed)
    for i in tqdm(range(steps), desc="perception", disable=not progress):
        j = rng.choice(train_idx, batch)
        params, opt_state, loss = step(params, opt_state, jax.random.fold_in(key, i), images[j], labels[j],
                                       masks[j], widths[j])
    metrics = {"steps": steps, "train_frames": int(len(train_idx)), "heldout_frames": int(len(test_idx))}
    if len(test_idx):
        probs, width = predict(params, np.moveaxis(images[test_idx], 1, 0))
        pred = probs > 0.5
        m = masks[test_idx]
        for k, name in enumerate(PREDICATES):
            metrics[f"heldout_acc/{name}"] = float((pred[..., k] == labels[test_idx][..., k])[m].mean())
        metrics["heldout_width_mae_m"] = float(np.abs(width - widths[test_idx]).mean())
    return params, metrics


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m sc3_jax.evaluate.perception", description=__doc__.split("\n")[0])
    ap.add_argument("--store", required=True, nargs="+", help="episode stores with meta['object_pos']")
    ap.add_argument("--generate", type=int, default=0, help="first write this many expert episodes (both tasks) "
                                                               "to the second-to-last --store")
    ap.add_argument("--generate-policies", type=int, default=0, help="and this many zoo-policy episodes (training "
                                                                       "seeds) to the last --store")
    ap.add_argument("--out", default=str(DEFAULT_WEIGHTS))
    ap.add_argument("--steps", type=int, default=2500)
    ap.add_argument("--stride", type=int, default=2)
    ap.add_argument("--max-episodes", type=int, default=None)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args(argv)
    t0 = time.time()
    if a.generate:
        generate_scorer_data(a.store[-2], a.generate)
    if a.generate_policies:
        generate_scorer_data(a.store[-1], a.generate_policies, seed=60, policies=True)
    data = load_training_data(a.store, a.stride, a.max_episodes)
    params, metrics = train(data, a.steps, seed=a.seed)
    metrics.update(seconds=round(time.time() - t0, 1), store=str(a.store), stride=a.stride)
    save(a.out, params, metrics)
    print(json.dumps(metrics, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Training the perception scorer (``perception.py``): scorer data, augmentation, the training loop, and a check of
any weights against physics on the real rollouts of a sweep store.

The scorer is a measuring instrument, not the world model: it may see reverse bussing and the zoo's behaviours
(retries, hovering), on simulator seeds disjoint from every seed a sweep evaluates on (``seed * 100_000 + i`` with
seed 50-79, against the sweep's blocks at 10M+). Frames are augmented the ways generated frames differ from rendered
ones (blur, pixel and patch noise, a per-view colour drift: ``degrade.py``), so the network also reads a world
model's frames.

The shipped weights (``perception.DEFAULT_WEIGHTS``): a wider network (``--keypoints 64 --widths 32 64 64 --hidden
384 --pos-weight 2``) fine-tuned on five stores, commands in docs/sweep.md#the-shipped-scorer. The previous ones, in
two stages:

1. ``sc3 train-perception --data runs/bussing/demos runs/bussing/scorer_data
   runs/bussing/scorer_zoo --generate 300 --generate-policies 140 --steps 3000 --out runs/bussing/perception.npz``
   (``scripts/bussing_sim.sh``);
2. after the zoo changed, warm-started on episodes of the new zoo: ``... --data runs/bussing/scorer_data
   runs/bussing/scorer_zoo runs/bussing/scorer_zoo2 --generate-policies 208 --policy-seed 70 --init
   runs/bussing/perception.npz --steps 3000 --lr 5e-4``.

Fresh weights take their size from ``--keypoints``, ``--widths`` and ``--hidden`` (stored in the .npz, see
``perception.arch``; the defaults are the shipped weights' size), and ``--pos-weight`` weights the loss of a positive
predicate label (each predicate holds in only 7-12% of the frames of the validation store).

``sc3 train-perception --validate STORE`` re-scores the real rollouts of a sweep results store (``sc3 sweep bench --modes
real``) with the weights and prints their agreement with physics, clean and degraded: how a scorer is chosen before a
sweep uses it.
"""
from __future__ import annotations

import dataclasses as dc
from collections import Counter
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax

from sc3_jax.core.errors import UserError
from sc3_jax.benchmarks.bussing import perception
from sc3_jax.benchmarks.bussing.perception import PREDICATES, WIDTH_SCALE, apply, predicate_labels, predict

SCORER_KNOBS = ({}, {"grasp_noise": 0.04}, {"release_noise": 0.08}, {"wrong_destination_prob": 0.5},
                {"action_noise": 0.012})


# -- data ---------------------------------------------------------------------------------------------------------
def generate_scorer_data(out: str | Path, episodes: int, seed: int = 50, image_size=(64, 64),
                         progress: bool = True, policies: bool = False) -> Path:
    """Episodes of *both* tasks written as an episode store with ``meta['object_pos']``: the scripted expert with a
    rotating mixture of failure knobs, or (``policies=True``) the zoo's policies in turn, 12 s each, on simulator
    seeds ``seed * 100_000 + i``. Resumable: episodes already in the store are skipped."""
    from tqdm import tqdm

    from sc3_jax.data.episodes import Episode, EpisodeStore
    from sc3_jax.benchmarks.bussing.env import BussingEnv
    from sc3_jax.benchmarks.bussing.expert import ExpertKnobs, run_expert_episode
    env = BussingEnv(image_size=tuple(image_size))
    store = EpisodeStore(out, views=list(env.views), fps=env.control_hz, image_size=tuple(image_size), create=True)
    for i in tqdm(range(episodes), desc="scorer data", disable=not progress):
        sim_seed, task = seed * 100_000 + i, ("bussing", "reverse")[i % 2]
        eid = f"ep{sim_seed:07d}"
        if eid in store:
            continue
        if policies:
            from sc3_jax.policies.base import as_host
            from sc3_jax.benchmarks.bussing.policy_eval import run_policy_episode
            from sc3_jax.benchmarks.bussing.zoo import ZOO, load_policy
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
        ep = store.load(eid, mmap=True, validate=False)
        if "object_pos" not in ep.meta:
            raise UserError(f"{store.root}/{eid}: no meta['object_pos'] (re-generate the demos with this version)")
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


# -- augmentation -------------------------------------------------------------------------------------------------
def augment(key: jax.Array, images: jax.Array) -> jax.Array:
    """uint8 [B, V, H, W, 3] -> the same, degraded at random the ways generated frames are (``degrade.py``, drawn
    per sample): a 3x3 box blur (p 0.5), a per-view colour drift (p 0.5: channel gain within +-10%, offset within
    +-15 grey levels, as ``degrade.colour_shift``), Gaussian noise of 40 grey levels on 10% of the 8x8 patches
    (p 0.3, as ``degrade.patch_noise``), and pixel noise of 4 grey levels everywhere."""
    x = images.astype(jnp.float32)
    b, v, h, w, c = x.shape
    k = jax.random.split(key, 8)
    flat = x.reshape(b * v, h, w, c)
    pad = jnp.pad(flat, ((0, 0), (1, 1), (1, 1), (0, 0)), mode="edge")
    blurred = sum(pad[:, i:i + h, j:j + w] for i in range(3) for j in range(3)) / 9.0
    x = jnp.where(jax.random.bernoulli(k[0], 0.5, (b, 1, 1, 1, 1)), blurred.reshape(x.shape), x)
    gain = jax.random.uniform(k[1], (b, v, 1, 1, 3), minval=0.9, maxval=1.1)
    offset = jax.random.uniform(k[2], (b, v, 1, 1, 3), minval=-15.0, maxval=15.0)
    x = jnp.where(jax.random.bernoulli(k[3], 0.5, (b, 1, 1, 1, 1)), x * gain + offset, x)
    p = 8
    hit = jax.random.bernoulli(k[4], 0.1, (b, v, h // p, w // p))
    mask = jnp.repeat(jnp.repeat(hit, p, 2), p, 3)[..., None] & jax.random.bernoulli(k[5], 0.3, (b, 1, 1, 1, 1))
    x = x + mask * jax.random.normal(k[6], x.shape) * 40.0
    x = x + jax.random.normal(k[7], x.shape) * 4.0
    return jnp.clip(jnp.round(x), 0, 255).astype(jnp.uint8)


# -- training -----------------------------------------------------------------------------------------------------
def loss_fn(params, images, labels, masks, widths, pos_weight: float = 1.0):
    """Masked binary cross-entropy of the predicates (a positive label's term weighted by ``pos_weight``: a
    predicate holds in a few percent of the frames only) plus the finger gap's squared error."""
    logits, width = apply(params, images)
    y = labels.astype(jnp.float32)
    bce = (optax.sigmoid_binary_cross_entropy(logits, y) * (1.0 + (pos_weight - 1.0) * y)).mean(-1)  # [B, 6]
    m = masks.astype(jnp.float32)
    cls = (bce * m).sum() / jnp.maximum(m.sum(), 1.0)
    reg = jnp.mean((width - widths) ** 2) * WIDTH_SCALE ** 2 * 0.1  # (cm^2)
    return cls + reg, (cls, reg)


def train(data, steps: int = 2500, batch: int = 64, lr: float = 1e-3, seed: int = 0, holdout: float = 0.1,
          init: dict | None = None, progress: bool = True, arch: dict | None = None,
          pos_weight: float = 1.0) -> tuple[dict, dict]:
    """Train on ``load_training_data`` output, from ``init`` (warm start) or fresh weights of architecture ``arch``
    (``perception.init``'s keywords; default: its defaults); a random ``holdout`` fraction of episodes is held out
    and scored. Returns (params, metrics: held-out per-predicate accuracy, precision and recall, and finger-gap
    error)."""
    from tqdm import tqdm
    images, labels, masks, widths, eps = data
    n_ep = int(eps.max()) + 1
    # held-out episodes drawn at random: stores are ordered by generation seed, i.e. by failure knob
    test_eps = np.random.default_rng(seed).permutation(n_ep)[:int(round(n_ep * holdout))]
    is_test = np.isin(eps, test_eps)
    train_idx, test_idx = np.flatnonzero(~is_test), np.flatnonzero(is_test)
    key = jax.random.key(seed)
    params = perception.init(key, images.shape[1], **(arch or {})) if init is None else init
    opt = optax.adamw(optax.warmup_cosine_decay_schedule(0.0, lr, min(100, steps // 10), steps), weight_decay=1e-4)
    opt_state = opt.init(params)

    @jax.jit
    def step(params, opt_state, key, x, y, m, w):
        x = augment(key, x)
        (loss, aux), g = jax.value_and_grad(loss_fn, has_aux=True)(params, x, y, m, w, pos_weight)
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
            p, t = pred[..., k][m], labels[test_idx][..., k][m]
            metrics[f"heldout_positive/{name}"] = float(t.mean())  # 1 - this: the accuracy of always answering no
            metrics[f"heldout_acc/{name}"] = float((p == t).mean())
            metrics[f"heldout_precision/{name}"] = float((p & t).sum() / max(p.sum(), 1))
            metrics[f"heldout_recall/{name}"] = float((p & t).sum() / max(t.sum(), 1))
        metrics["heldout_width_mae_m"] = float(np.abs(width - widths[test_idx]).mean())
    return params, metrics


# -- validation against physics -----------------------------------------------------------------------------------
def validate(results: str | Path, params: dict, score_stride: int = 2, degradations: bool = True) -> dict:
    """Agreement with physics of ``params`` on every real rollout of a sweep results store, scored as the sweep
    scores them (every ``score_stride``-th frame and the last; the same seeded degradations): {frames kind:
    agreement per criterion}, and under "majority_guess" the agreement of a scorer that gives every object each
    criterion's most common verdict (the floor)."""
    from sc3_jax.evaluation.scorers import RolloutView, agreement
    from sc3_jax.benchmarks.bussing.scorers import PerceptionScorer
    from sc3_jax.evaluation.results import ResultsStore
    from sc3_jax.benchmarks.bussing.tasks import make_initial_condition
    store = ResultsStore(results)
    real = [r for r in store.records() if r["mode"] == "real"]
    if not real:
        raise UserError(f"{results}: no real rollouts to validate on (run `sc3 sweep bench --modes real` first)")
    scorer = PerceptionScorer(params)
    scored: dict[str, list] = {}
    for r in real:
        ic = make_initial_condition(r["seed"], r["task"])
        view = RolloutView(r["id"], store.load_arrays(r["id"])["frames"], ic.objects, ic.destinations())
        clean, degraded = scorer.score_real(view, r["seed"], score_stride, degradations)
        for kind, outcomes in {"clean": clean, **degraded}.items():
            scored.setdefault(kind, []).append(outcomes)
    truth = [r["objects"] for r in real]
    return {**{kind: agreement(s, truth) for kind, s in scored.items()}, "majority_guess": majority_agreement(truth)}


def majority_agreement(truth: list[list[dict]]) -> dict[str, float]:
    """``agreement``'s keys for a scorer that ignores the frames and gives each criterion (and the outcome) its most
    common verdict among ``truth``: how much agreement the base rates alone buy."""
    from .tasks import CRITERIA

    objects = [o for rollout in truth for o in rollout]
    if not objects:
        raise ValueError("majority_agreement: no objects")
    return {k: max(Counter(o[k] for o in objects).values()) / len(objects) for k in CRITERIA + ("outcome",)} | \
        {"n_objects": len(objects)}

"""Training the SO-101 zoo's estimators from a LeRobot dataset (``sc3 so101 collect``'s, or any with the camera,
``observation.state`` and ``observation.environment_state``): frames labelled by the dataset's own block and goal
positions, as a lab would train a perception module on its logged data.

    sc3 so101 zoo-train --data DATASET [DATASET ...] [--heldout DATASET] [--out DIR]
"""
from __future__ import annotations

import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from sc3_jax.core import atomic
from .zoo import ZOO, ZOO_DIR, estimator_loss, init_estimator, save_params

ENV_STATE = "observation.environment_state"
# estimator -> (share of the dataset's episodes, steps): the small one sees a tenth of the data for a tenth of the
# steps, so its estimates are worse and every policy built on it fails more
RUNS = {"est_full.npz": (1.0, 3000), "est_small.npz": (0.1, 300)}


def load_frames(root: str | Path, episodes: int | None = None, every: int = 2):
    """(images uint8 [N, H, W, 3], state float32 [N, 14], labels float32 [N, 5] block xyz + goal xy) from every
    ``every``-th frame of the first ``episodes`` episodes of a LeRobot dataset, its first camera (the zoo's policies
    read the first view they are handed: the workspace camera)."""
    from sc3_jax.data.lerobot import LeRobotEpisodes
    eps = LeRobotEpisodes(root, pose_key=ENV_STATE)
    imgs, states, labels = [], [], []
    for i in range(len(eps) if episodes is None else min(episodes, len(eps))):
        ep = eps.episode(i)
        sel = np.arange(0, ep.length, every)
        imgs.append(ep.frames[eps.views[0]][sel])
        states.append(ep.state[sel])
        labels.append(np.concatenate([ep.pose[sel, :3], ep.pose[sel, 3:5]], 1))
    return (np.concatenate(imgs), np.concatenate(states).astype(np.float32),
            np.concatenate(labels).astype(np.float32))


def train_estimator(data, steps: int, seed: int = 0, batch: int = 32, lr: float = 1e-3, log_every: int = 250):
    import optax
    imgs, states, labels = (jnp.asarray(a) for a in data)
    net = init_estimator(jax.random.key(seed))
    opt = optax.adamw(optax.warmup_cosine_decay_schedule(0.0, lr, min(100, steps // 4), steps, lr * 0.05),
                      weight_decay=1e-4)
    opt_state = opt.init(net)

    @jax.jit
    def step(net, opt_state, idx):
        loss, g = jax.value_and_grad(estimator_loss)(net, imgs[idx], states[idx], labels[idx])
        upd, opt_state = opt.update(g, opt_state, net)
        return optax.apply_updates(net, upd), opt_state, loss

    rng, t0 = np.random.default_rng(seed), time.time()
    for s in range(1, steps + 1):
        net, opt_state, loss = step(net, opt_state, jnp.asarray(rng.integers(0, len(imgs), batch)))
        if s % log_every == 0 or s == 1:
            print(f"  step {s:5d} loss {float(loss):.4f} ({time.time() - t0:.0f} s)", flush=True)
    return net


def errors_cm(net, data, batch: int = 256) -> dict:
    """Mean absolute estimation error in cm: block xy, block z, goal xy."""
    from .zoo import estimate
    imgs, states, labels = data
    f = jax.jit(estimate)
    est = np.concatenate([np.asarray(f(net, jnp.asarray(imgs[i:i + batch]), jnp.asarray(states[i:i + batch])))
                          for i in range(0, len(imgs), batch)])
    err = np.abs(est - labels) * 100
    return {"block_xy": float(np.linalg.norm(err[:, :2], axis=1).mean()), "block_z": float(err[:, 2].mean()),
            "goal_xy": float(np.linalg.norm(err[:, 3:5], axis=1).mean())}


def _short(path) -> str:
    """A dataset's name for zoo.json: its folder and split (``data1/train``), not where it lay on the machine."""
    return "/".join(Path(path).parts[-2:])


def train_zoo(data: list[str | Path], heldout: str | Path | None = None, out: str | Path = ZOO_DIR) -> dict:
    """Train every estimator of ``RUNS`` on the datasets ``data`` (their held-out errors on ``heldout``), write them
    and ``zoo.json`` (the policies, their knobs, the estimators' recipe, errors and times) into ``out``."""
    from sc3_jax.data.lerobot import LeRobotEpisodes
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    sizes = [len(LeRobotEpisodes(d, pose_key=ENV_STATE)) for d in data]
    test = load_frames(heldout) if heldout else None
    summary = {}
    for name, (share, steps) in RUNS.items():
        # the same share of every dataset's episodes, concatenated
        parts = [load_frames(d, max(1, round(share * n))) for d, n in zip(data, sizes)]
        frames = tuple(np.concatenate(a) for a in zip(*parts))
        n = sum(max(1, round(share * k)) for k in sizes)
        print(f"{name}: {len(frames[0])} frames from {n} episodes, {steps} steps", flush=True)
        t0 = time.time()
        net = train_estimator(frames, steps)
        save_params(out / name, net)
        summary[name] = {"episodes": n, "steps": steps, "seconds": round(time.time() - t0),
                         **({"heldout_error_cm": errors_cm(net, test)} if test else {})}
        print(f"  {summary[name]}", flush=True)
    atomic.write_json(out / "zoo.json", {
        "policies": {k: {"weights": e.weights, "knobs": e.knobs.__dict__, "note": e.note} for k, e in ZOO.items()},
        "estimators": summary, "data": [_short(d) for d in data], "heldout": _short(heldout) if heldout else None,
        "command": "sc3 so101 zoo-train --data DATA --heldout HELDOUT"})
    return summary

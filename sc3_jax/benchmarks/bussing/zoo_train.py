"""Training the policy zoo's estimators (``zoo.py`` is the registry they are loaded from): generate the demo sets,
train every run, write the weights and ``zoo/zoo.json``.

    sc3 sim zoo-train --workdir /tmp/sc3_zoo     (see docs/sim.md)
    sc3 sim zoo-manifest                         rewrite zoo.json from the registry
"""
from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from sc3_jax.core import atomic
from sc3_jax.data.episodes import EpisodeStore
from .demos import _expert_runner, write_episodes
from .expert import ExpertKnobs
from .zoo import N_OBJ, PICK_X_MAX, XY_SCALE, ZOO, ZOO_DIR, ControlKnobs, init_net, net_apply, save_params


def load_training_data(store_root: str | Path, max_episodes: int | None = None, stride: int = 3):
    store = EpisodeStore(store_root)
    ids = store.episode_ids()[:max_episodes]
    imgs, states, labels = [], [], []
    for eid in ids:
        ep = store.load(eid, mmap=False)
        it = ep.meta["intent"]
        sel = np.arange(0, ep.length, stride)
        imgs.append(np.stack([ep.frames[v][sel] for v in store.views], 1))
        states.append(ep.ee_pose[sel])
        n = len(sel)
        lab = np.concatenate([np.asarray(it["obj_xy"])[sel].reshape(n, -1), np.asarray(it["obj_present"])[sel],
                              np.asarray(it["obj_dest"])[sel], np.asarray(it["held_dest"])[sel, None],
                              np.asarray(it["bin_xy"])[sel], np.asarray(it["can_xy"])[sel]], 1)
        labels.append(lab)
    return np.concatenate(imgs), np.concatenate(states).astype(np.float32), np.concatenate(labels).astype(np.float32)


def loss_fn(net, images, states, labels):
    n = N_OBJ
    out = net_apply(net, images, states)

    def bce(logit, y):
        return jnp.maximum(logit, 0) - logit * y + jnp.log1p(jnp.exp(-jnp.abs(logit)))

    present, dest, held = labels[:, 2 * n:3 * n], labels[:, 3 * n:4 * n], labels[:, 4 * n]
    xy_err = jnp.sum((out[:, :2 * n] - labels[:, :2 * n] * XY_SCALE).reshape(-1, n, 2) ** 2, -1)
    l_xy = jnp.sum(xy_err * present) / jnp.maximum(jnp.sum(present), 1.0)
    l_present = jnp.mean(bce(out[:, 2 * n:3 * n], present))
    dm = (dest >= 0).astype(jnp.float32)
    l_dest = jnp.sum(bce(out[:, 3 * n:4 * n], jnp.maximum(dest, 0)) * dm) / jnp.maximum(jnp.sum(dm), 1.0)
    hm = (held >= 0).astype(jnp.float32)
    l_hdest = jnp.sum(bce(out[:, 4 * n], jnp.maximum(held, 0)) * hm) / jnp.maximum(jnp.sum(hm), 1.0)
    l_cont = jnp.mean(jnp.sum((out[:, 4 * n + 1:] - labels[:, 4 * n + 1:] * XY_SCALE) ** 2, -1))
    total = 4.0 * l_xy + 2.0 * l_present + l_dest + l_hdest + l_cont
    return total, {"xy": l_xy, "present": l_present, "dest": l_dest, "hdest": l_hdest, "cont": l_cont}


def train_net(data, steps: int, checkpoints: dict[int, Path], seed: int = 0, batch: int = 32, lr: float = 1e-3,
              log_every: int = 100) -> dict:
    import optax
    imgs, states, labels = data
    key = jax.random.key(seed)
    net = init_net(key)
    schedule = optax.warmup_cosine_decay_schedule(0.0, lr, min(50, steps // 4), steps, lr * 0.05)
    opt = optax.adamw(schedule, weight_decay=1e-4)
    opt_state = opt.init(net)

    @jax.jit
    def train_step(net, opt_state, idx):
        (loss, aux), g = jax.value_and_grad(loss_fn, has_aux=True)(net, imgs_d[idx], states_d[idx], labels_d[idx])
        upd, opt_state = opt.update(g, opt_state, net)
        return optax.apply_updates(net, upd), opt_state, loss, aux

    imgs_d, states_d, labels_d = jnp.asarray(imgs), jnp.asarray(states), jnp.asarray(labels)
    rng = np.random.default_rng(seed)
    t0 = time.time()
    for s in range(1, steps + 1):
        idx = jnp.asarray(rng.integers(0, len(imgs), batch))
        net, opt_state, loss, aux = train_step(net, opt_state, idx)
        if s % log_every == 0 or s == 1:
            print(f"  step {s:5d} loss {float(loss):.4f} " + " ".join(f"{k}={float(v):.4f}" for k, v in aux.items())
                  + f" ({time.time() - t0:.0f}s)", flush=True)
        if s in checkpoints:
            save_params(checkpoints[s], net)
    return net


# run name -> (demo set, max episodes, steps, {checkpoint step: file suffix})
RUNS = {
    "clean": ("clean", None, 5000, {1500: "mid", 5000: "final"}),
    "small": ("clean", 30, 1500, {1500: "final"}),
    "reverse": ("reverse", None, 3000, {1000: "mid", 3000: "final"}),
}
# the reverse set trains the reverse-bussing policies' own estimator; it is zoo training data only (written with
# ``demos.write_episodes``: ``generate_demos``, the world-model data path, refuses reverse bussing)
DEMO_SETS = {"clean": dict(n=300, seed=1, task="bussing"), "reverse": dict(n=300, seed=3, task="reverse")}


def train_zoo(workdir: str | Path, out_dir: str | Path = ZOO_DIR, runs: list[str] | None = None,
              demo_scale: float = 1.0) -> dict:
    """Generate the demo sets (resumable) and train every run, saving its checkpoints as zoo weights."""
    workdir, out_dir = Path(workdir), Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    knobs = {"clean": ExpertKnobs(), "reverse": ExpertKnobs()}
    summary = {}
    runs = runs or list(RUNS)
    for name, cfg in DEMO_SETS.items():
        if not any(RUNS[r][0] == name for r in runs):
            continue
        summary[f"demos_{name}"] = write_episodes(
            workdir / f"demos_{name}", max(1, int(cfg["n"] * demo_scale)), cfg["seed"], _expert_runner(knobs[name]),
            {"knobs": dataclasses.asdict(knobs[name])}, cfg["task"])
    for run in runs:
        dset, max_eps, steps, ckpts = RUNS[run]
        data = load_training_data(workdir / f"demos_{dset}", max_eps)
        print(f"run {run}: {len(data[0])} frames from demos_{dset}", flush=True)
        t0 = time.time()
        train_net(data, steps, {s: out_dir / f"run_{run}_{suffix}.npz" for s, suffix in ckpts.items()})
        summary[f"run_{run}_seconds"] = time.time() - t0
    write_manifest(out_dir, {k: round(v) for k, v in summary.items() if k.endswith("seconds")})
    return summary


def write_manifest(out_dir: str | Path = ZOO_DIR, seconds: dict | None = None) -> Path:
    """``zoo.json``: every policy (estimator weights + control knobs + recipe), the training runs and demo sets.
    Training times measured earlier are kept unless ``seconds`` replaces them."""
    path = Path(out_dir) / "zoo.json"
    old = (atomic.read_json(path, "restore it with git, or delete it (the measured training times go with it)")
           if path.exists() else {})
    measured = {**old.get("training_seconds_measured", {}), **(seconds or {})}
    atomic.write_json(path, {
        "policies": {n: {**dataclasses.asdict(e), "knobs": {k: v for k, v in dataclasses.asdict(e.knobs).items()
                                                            if v != getattr(ControlKnobs(), k)}}
                     for n, e in ZOO.items()},
        "knob_defaults": {k: str(v) for k, v in dataclasses.asdict(ControlKnobs()).items()},
        "pick_x_max": PICK_X_MAX,
        "runs": {k: {"demo_set": v[0], "max_episodes": v[1], "steps": v[2], "checkpoints": v[3]}
                 for k, v in RUNS.items()},
        "demo_sets": DEMO_SETS,
        "command": "sc3 sim zoo-train --workdir /tmp/sc3_zoo",
        "dtype": "float16 (cast to float32 on load)",
        "training_seconds_measured": measured})
    return path


"""Policy zoo: pixel-input policies for bussing / reverse bussing, pure JAX, trained by cloning the expert's intent.

What is learned and what is scripted (honestly):
  * Learned: a small CNN (shared conv trunk over the three 64x64 views with coordinate channels, spatial-softmax
    keypoints + pooled features, then an MLP with the 7-D gripper state) that, from the pixels, estimates for each of
    the six object types where it is and whether it still has to be bussed, which container the demonstrator took
    objects of that type to (and the held object to), and where the two containers are. It is trained by supervised
    learning on the expert's demonstrations (``demos.py``): positions/presence are read from the simulator state of
    each demonstration frame, destinations are the demonstrator's own choices (so a biased demonstrator yields a
    biased policy). Pure pixel-to-action BC did not fit the CPU budget.
  * Scripted: a stateless controller in ``jnp`` (``jnp.where`` phase logic from the observation only: the held-object
    state is read from the finger gap) turns those estimates into a 25-step chunk of raw delta-EE actions
    (largest-x object first: hover -> descend -> close -> lift -> carry -> lower -> release; a failed grasp, seen as a
    fully closed empty gripper, is reopened and retried). For reverse bussing (``task == 1``) containers are swapped.
Policies differ only by learned quality: training checkpoint, amount of data and quality of the demonstrator
(a biased demonstrator that always takes some object types to the wrong container).

The policy sees only ``obs["images"]`` (uint8 [3, H, W, 3], resized to 64x64 inside), ``obs["state"]`` and
``obs["task"]``; ``apply(params, obs, rng)`` is pure, so it runs inside ``lax.scan`` and under ``vmap``.

Reproduce the shipped weights: ``python -m sc3_jax.sim.zoo train --workdir /tmp/sc3_zoo`` (see docs/sim.md).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from ..policies.base import JaxPolicy
from . import scene as S
from .convnet import dense_init, init_trunk, mlp, trunk_features
from .tasks import OBJECTS

ZOO_DIR = Path(__file__).parent / "zoo"
N_KP = 32
CHUNK = 25
# controller constants (shared with the expert's geometry)
HOVER_Z, CARRY_Z, GRASP_Z = 0.13, 0.17, 0.015
STEP, GAIN = 0.03, 0.6
RELEASE_Z = jnp.array([S.BIN_WALL_H + 0.06, S.CAN_WALL_H + 0.06])
HOLD_LO, HOLD_HI = 0.015, 0.083
N_OBJ = len(OBJECTS)
# per object type: xy (2), "to be bussed" logit, destination logit; then held-object destination logit, bin xy, can xy
OUT_DIM = 4 * N_OBJ + 5
XY_SCALE = 10.0


# -- network (trunk in convnet.py) ------------------------------------------------------------------------------
def init_net(key: jax.Array, n_views: int = 3) -> dict:
    ks = jax.random.split(key, 8)  # (the split the shipped weights were trained from)
    feat = n_views * (2 * N_KP + N_KP) + 7
    return {**init_trunk(ks[:4], N_KP), "d1": dense_init(ks[4], feat, 256), "d2": dense_init(ks[5], 256, 256),
            "out": dense_init(ks[6], 256, OUT_DIM, 0.1)}


def net_apply(net: dict, images: jax.Array, state: jax.Array) -> jax.Array:
    """images uint8 [B, V, H, W, 3], state [B, 7] -> raw outputs [B, OUT_DIM]."""
    f = trunk_features(net, images)
    return mlp(net, jnp.concatenate([f, state * jnp.array([5, 5, 5, 1, 1, 1, 10.0])], -1))


def decode(out: jax.Array) -> dict:
    n = N_OBJ
    return {"obj_xy": out[..., 0:2 * n].reshape(out.shape[:-1] + (n, 2)) / XY_SCALE,
            "present": out[..., 2 * n:3 * n], "dest": out[..., 3 * n:4 * n], "held_dest": out[..., 4 * n],
            "bin_xy": out[..., 4 * n + 1:4 * n + 3] / XY_SCALE, "can_xy": out[..., 4 * n + 3:4 * n + 5] / XY_SCALE}


# -- controller -----------------------------------------------------------------------------------------------
def controller(est: dict, state: jax.Array, task: jax.Array) -> jax.Array:
    """Stateless chunk planner: estimates (one sample) + state [7] + task -> actions [CHUNK, 7].

    Picks the still-to-be-bussed object with the largest x (the expert's order), hovers over it, descends, closes;
    when holding (finger gap strictly between closed and open), lifts, carries to the container chosen for it
    (swapped when ``task == 1``), lowers and releases; then goes on to the next object within the same chunk.
    A fully closed gripper means a failed grasp: reopen and rise for the rest of the chunk."""
    pos0, rv0, width = state[:3], state[3:6], state[6]
    holding0 = (width > HOLD_LO) & (width < HOLD_HI)
    empty0 = width <= HOLD_LO
    flip = task.astype(bool)
    held_c = ((est["held_dest"] > 0) ^ flip).astype(jnp.int32)
    obj_c = ((est["dest"] > 0) ^ flip).astype(jnp.int32)  # [N_OBJ]
    containers = jnp.stack([est["bin_xy"], est["can_xy"]])
    present = est["present"] > 0

    def step(carry, k):
        p, hold, empty, dest_c, done = carry
        todo = present & ~done
        left = jnp.any(todo)
        j = jnp.argmax(jnp.where(todo, est["obj_xy"][:, 0], -jnp.inf))
        g = est["obj_xy"][j]
        # holding: lift, carry, lower, release
        dxy = containers[dest_c]
        far = jnp.linalg.norm(p[:2] - dxy) > 0.01
        low = p[2] < CARRY_Z - 0.03
        rz = RELEASE_Z[dest_c]
        goal_hold = jnp.where(far, jnp.where(low, jnp.array([p[0], p[1], CARRY_Z]),
                                             jnp.array([dxy[0], dxy[1], CARRY_Z])), jnp.array([dxy[0], dxy[1], rz]))
        release = (~far) & (jnp.abs(p[2] - rz) < 0.008)
        # not holding: hover over the target, descend, close
        gerr = jnp.linalg.norm(p[:2] - g)
        gfar = gerr > 0.008
        # far: travel at hover height; close: hold the height while correcting xy (no bobbing up when the estimate
        # moves by a few mm between chunks); aligned: descend
        goal_z = jnp.where(gerr > 0.03, HOVER_Z, jnp.where(gfar, p[2], GRASP_Z))
        goal_pick = jnp.array([g[0], g[1], goal_z])
        close = (~gfar) & (p[2] < GRASP_Z + 0.006)
        goal_idle = jnp.array([p[0], p[1], HOVER_Z + 0.02])
        idle = empty | ~left
        goal = jnp.where(hold, goal_hold, jnp.where(idle, goal_idle, goal_pick))
        grip = jnp.where(hold, jnp.where(release, S.OPEN_WIDTH, 0.0),
                         jnp.where(idle, S.OPEN_WIDTH, jnp.where(close, 0.0, S.OPEN_WIDTH)))
        d = GAIN * (goal - p)
        n = jnp.linalg.norm(d)
        d = d * jnp.minimum(1.0, STEP / jnp.maximum(n, 1e-9))
        rot = -0.5 * rv0 * (0.5 ** k)
        a = jnp.concatenate([d, rot, grip[None]])
        grasp = (~hold) & (~idle) & close
        new_hold = jnp.where(hold, ~release, grasp)
        new_dest = jnp.where(hold, dest_c, obj_c[j])
        new_done = done | (grasp & (jnp.arange(N_OBJ) == j))
        return (p + d, new_hold, empty, new_dest, new_done), a

    init = (pos0, holding0, empty0, held_c, jnp.zeros(N_OBJ, bool))
    _, acts = jax.lax.scan(step, init, jnp.arange(CHUNK, dtype=jnp.float32))
    return acts.astype(jnp.float32)


def policy_apply(params: dict, obs: dict, rng: jax.Array) -> jax.Array:
    """The zoo policy: pixels + state + task -> [25, 7] raw delta-EE actions. ``rng`` is unused (deterministic)."""
    del rng
    images = jnp.asarray(obs["images"])[None]
    state = jnp.asarray(obs["state"], jnp.float32)
    est = decode(net_apply(params, images, state[None])[0])
    return controller(est, state, jnp.asarray(obs["task"], jnp.int32))


# -- registry -----------------------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class ZooEntry:
    name: str
    task: str  # the task the policy is meant for
    weights: str  # file under sc3_jax/sim/zoo/
    recipe: str  # how it was trained


ZOO: dict[str, ZooEntry] = {e.name: e for e in (
    ZooEntry("bus_bc_full", "bussing", "run_clean_final.npz", "300 clean demos, final checkpoint (5000 steps)"),
    ZooEntry("bus_bc_mid", "bussing", "run_clean_mid.npz", "300 clean demos, checkpoint at 1500 steps"),
    ZooEntry("bus_bc_small", "bussing", "run_small_final.npz", "30 clean demos, final checkpoint (1500 steps)"),
    ZooEntry("bus_bc_biased", "bussing", "run_biased_final.npz",
             "150 demos of a biased demonstrator (bags and cups to the wrong container), 3000 steps"),
    ZooEntry("rev_bc_full", "reverse", "run_clean_final.npz", "as bus_bc_full, task=1 routes to swapped containers"),
    ZooEntry("rev_bc_small", "reverse", "run_small_mid.npz", "30 clean demos, checkpoint at 600 steps; task=1"),
    ZooEntry("rev_bc_biased", "reverse", "run_biased_final.npz",
             "as bus_bc_biased, task=1 routes to swapped containers"),
)}


def zoo_names(task: str | None = None) -> list[str]:
    return [n for n, e in ZOO.items() if task is None or e.task == task]


def save_params(path: str | Path, net: dict) -> None:
    """Weights ship as float16 (about 0.3 MB per policy); ``load_params`` casts them back to float32."""
    flat = {f"{k}/{kk}": np.asarray(v, np.float16) for k, d in net.items() for kk, v in d.items()}
    np.savez_compressed(path, **flat)


def load_params(path: str | Path) -> dict:
    with np.load(path) as z:
        net: dict = {}
        for key in z.files:
            a, b = key.split("/")
            net.setdefault(a, {})[b] = jnp.asarray(z[key], jnp.float32)
    return net


def load_policy(name: str, zoo_dir: str | Path | None = None) -> JaxPolicy:
    if name not in ZOO:
        raise KeyError(f"unknown zoo policy {name!r}; known: {sorted(ZOO)}")
    path = Path(zoo_dir or ZOO_DIR) / ZOO[name].weights
    if not path.exists():
        raise FileNotFoundError(f"{path}: zoo weights missing; train them with `python -m sc3_jax.sim.zoo train`")
    return JaxPolicy(name, policy_apply, load_params(path), chunk=CHUNK)


# -- training -------------------------------------------------------------------------------------------------------
def load_training_data(store_root: str | Path, max_episodes: int | None = None, stride: int = 3):
    from ..data.episodes import EpisodeStore
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
    "small": ("clean", 30, 1500, {600: "mid", 1500: "final"}),
    "biased": ("biased", None, 3000, {3000: "final"}),
}
DEMO_SETS = {"clean": dict(n=300, seed=1), "biased": dict(n=150, seed=2)}


def train_zoo(workdir: str | Path, out_dir: str | Path = ZOO_DIR, runs: list[str] | None = None,
              demo_scale: float = 1.0) -> dict:
    """Generate the demo sets (resumable) and train every run, saving its checkpoints as zoo weights."""
    from .demos import generate_demos
    from .expert import ExpertKnobs
    workdir, out_dir = Path(workdir), Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    knobs = {"clean": ExpertKnobs(), "biased": ExpertKnobs(swap_types=("bag", "cup"))}
    summary = {}
    for name, cfg in DEMO_SETS.items():
        summary[f"demos_{name}"] = generate_demos(workdir / f"demos_{name}", max(1, int(cfg["n"] * demo_scale)),
                                                  seed=cfg["seed"], knobs=knobs[name])
    for run in runs or list(RUNS):
        dset, max_eps, steps, ckpts = RUNS[run]
        data = load_training_data(workdir / f"demos_{dset}", max_eps)
        print(f"run {run}: {len(data[0])} frames from demos_{dset}", flush=True)
        t0 = time.time()
        train_net(data, steps, {s: out_dir / f"run_{run}_{suffix}.npz" for s, suffix in ckpts.items()})
        summary[f"run_{run}_seconds"] = time.time() - t0
    (out_dir / "zoo.json").write_text(json.dumps({
        "policies": {n: dataclasses.asdict(e) for n, e in ZOO.items()},
        "runs": {k: {"demo_set": v[0], "max_episodes": v[1], "steps": v[2], "checkpoints": v[3]}
                 for k, v in RUNS.items()},
        "demo_sets": DEMO_SETS, "biased_demonstrator": {"swap_types": ["bag", "cup"]},
        "command": "python -m sc3_jax.sim.zoo train --workdir /tmp/sc3_zoo",
        "dtype": "float16 (cast to float32 on load)",
        "training_seconds_measured": {k: round(v) for k, v in summary.items() if k.endswith("seconds")}}, indent=1))
    return summary


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m sc3_jax.sim.zoo")
    sub = ap.add_subparsers(dest="cmd", required=True)
    t = sub.add_parser("train", help="generate demos and train the zoo's networks")
    t.add_argument("--workdir", default="/tmp/sc3_zoo")
    t.add_argument("--out", default=str(ZOO_DIR))
    t.add_argument("--runs", nargs="*", default=None)
    sub.add_parser("list", help="list the zoo")
    a = ap.parse_args(argv)
    if a.cmd == "train":
        print(json.dumps(train_zoo(a.workdir, a.out, a.runs), indent=1, default=str))
    else:
        for n, e in ZOO.items():
            print(f"{n:16s} {e.task:8s} {e.recipe}")


if __name__ == "__main__":
    main()

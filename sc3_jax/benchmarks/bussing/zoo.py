"""Policy zoo: pixel-input policies for bussing / reverse bussing, pure JAX: a learned estimator + a scripted
controller with per-policy failure knobs.

What is learned, what is scripted, what is a knob (honestly):
  * Learned: a small CNN (shared conv trunk over the three 64x64 views with coordinate channels, spatial-softmax
    keypoints + pooled features, then an MLP with the 7-D gripper state) that, from the pixels, estimates for each of
    the six object types where it is and whether it still has to be bussed, which container the demonstrator took
    objects of that type to (and the held object to), and where the two containers are. It is trained by supervised
    learning on scripted-expert demonstrations: positions/presence are read from the simulator state of each
    demonstration frame, destinations are the demonstrator's own choices (a biased demonstrator yields a biased
    estimator; reverse-bussing demonstrations yield an estimator of reverse destinations). Pure pixel-to-action BC
    did not fit the CPU budget.
  * Scripted: a stateless controller in ``jnp`` (``jnp.where`` phase logic from the observation only: the held-object
    state is read from the finger gap) turns those estimates into a 25-step chunk of raw delta-EE actions
    (largest-x object first: hover -> descend -> close -> lift -> carry -> lower -> release; a failed grasp, seen as a
    fully closed empty gripper, is reopened and retried; objects lying near the containers are not picked).
  * Knobs (``ControlKnobs``, per policy, stored in its params next to the estimator weights and listed in
    ``zoo/zoo.json``): grasp aim error and grasp height error (lifting), release point offset / noise / height
    (placing after a successful lift), "greedy" routing to the container on the object's side of the table whatever
    the instruction (language), and which task the estimator's destinations belong to. Per-chunk errors are drawn
    from the policy's ``rng`` (pure, so they run inside ``lax.scan``).
Policies differ by estimator (training data, amount, checkpoint, bussing or reverse demonstrations) and by knobs, so
language, lifting and placing vary independently across the zoo (see docs/sim.md for the measured table).

The policy sees only ``obs["images"]`` (uint8 [3, H, W, 3], resized to 64x64 inside), ``obs["state"]`` and
``obs["task"]``; ``apply(params, obs, rng)`` is pure, so it runs inside ``lax.scan`` and under ``vmap``.

This module is the registry (networks, controller, ``ZOO``, loading); ``zoo_train.py`` reproduces the shipped weights:
``sc3 sim zoo-train --workdir /tmp/sc3_zoo`` (see docs/sim.md).
"""
from __future__ import annotations

import dataclasses
from pathlib import Path

import jax
import jax.numpy as jnp

from sc3_jax.policies import convnet
from sc3_jax.policies.base import JaxPolicy
from sc3_jax.policies.convnet import dense_init, mlp
from . import scene as S
from .convnet import init_trunk, trunk_features
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


# -- controller knobs (per policy; part of its params, so they travel into jit / scan like the weights) ----------
@dataclasses.dataclass(frozen=True)
class ControlKnobs:
    """Scripted failure tendencies of one zoo policy. All distances in metres; 0 / ``inf`` = off.

    * ``dest_frame``: 0 if the estimator was trained on bussing demonstrations (routes flip for ``task == 1``),
      1 if on reverse-bussing demonstrations (routes flip for ``task == 0``).
    * ``grasp_sigma``: std of a horizontal aim error at the grasp, drawn afresh per chunk -> lifting failures
      (missed grasps are retried, so they mostly cost time and block the objects behind).
    * ``grasp_dz``: height error of the grasp point -> flat objects (lid, spoon, then bowl) are never gripped.
    * ``release_out``: the release point sits this far beyond the container centre, outwards (away from y = 0);
      ``release_sigma``: std of a per-chunk release xy error; ``release_dz``: release this much higher. All act only
      after a successful lift -> placing failures (an object that lands outside stays there: see ``PICK_X_MAX``).
    * ``greedy_y``: language failures -- an object picked (or held) more than this far from the table's midline
      (|y|) goes to the container on its own side, whatever the instruction says (the policy takes the short way).
      The rule is consistent across chunks because the gripper never crosses the midline while carrying.
    """
    dest_frame: int = 0
    grasp_sigma: float = 0.0
    grasp_dz: float = 0.0
    release_out: float = 0.0
    release_sigma: float = 0.0
    release_dz: float = 0.0
    greedy_y: float = float("inf")

    def arrays(self) -> dict:
        return {k: jnp.asarray(v, jnp.float32) for k, v in dataclasses.asdict(self).items()}


# objects whose estimate lies beyond this x (near the containers, outside the spawn area x <= 0.03) are not picked:
# a stateless controller would otherwise re-grasp a dropped object forever; a real checkpoint rarely does
PICK_X_MAX = 0.08


# -- controller -----------------------------------------------------------------------------------------------
def controller(est: dict, state: jax.Array, task: jax.Array, knobs: dict | None = None,
               rng: jax.Array | None = None) -> jax.Array:
    """Stateless chunk planner: estimates (one sample) + state [7] + task -> actions [CHUNK, 7].

    Picks the still-to-be-bussed object with the largest x (the expert's order), hovers over it, descends, closes;
    when holding (finger gap strictly between closed and open), lifts, carries to the container chosen for it
    (swapped when ``task`` differs from the estimator's ``dest_frame``), lowers and releases; then goes on to the
    next object within the same chunk. A fully closed gripper means a failed grasp: reopen and rise for the rest of
    the chunk. ``knobs`` (``ControlKnobs.arrays()``) add the policy's failure tendencies, drawn with ``rng``."""
    kn = knobs if knobs is not None else ControlKnobs().arrays()
    rng = rng if rng is not None else jax.random.key(0)
    k_grasp, k_rel = jax.random.split(rng)
    grasp_off = kn["grasp_sigma"] * jax.random.normal(k_grasp, (2,))
    rel_noise = kn["release_sigma"] * jax.random.normal(k_rel, (2,))
    grasp_z = GRASP_Z + kn["grasp_dz"]
    pos0, rv0, width = state[:3], state[3:6], state[6]
    holding0 = (width > HOLD_LO) & (width < HOLD_HI)
    empty0 = width <= HOLD_LO
    flip = task.astype(jnp.int32) != kn["dest_frame"].astype(jnp.int32)
    containers = jnp.stack([est["bin_xy"], est["can_xy"]])

    def route(c, y):  # instructed container c, unless the policy is greedy at this y
        near = jnp.argmin(jnp.abs(containers[:, 1] - y)).astype(jnp.int32)
        return jnp.where(jnp.abs(y) > kn["greedy_y"], near, c)

    held_c = route(((est["held_dest"] > 0) ^ flip).astype(jnp.int32), pos0[1])
    obj_c = ((est["dest"] > 0) ^ flip).astype(jnp.int32)  # [N_OBJ]
    present = (est["present"] > 0) & (est["obj_xy"][:, 0] < PICK_X_MAX)

    def step(carry, k):
        p, hold, empty, dest_c, done = carry
        todo = present & ~done
        left = jnp.any(todo)
        j = jnp.argmax(jnp.where(todo, est["obj_xy"][:, 0], -jnp.inf))
        g = est["obj_xy"][j] + grasp_off
        # holding: lift, carry, lower, release (release point pushed outwards by release_out, plus noise)
        cxy = containers[dest_c]
        dxy = cxy + jnp.array([0.0, 1.0]) * jnp.sign(cxy[1]) * kn["release_out"] + rel_noise
        far = jnp.linalg.norm(p[:2] - dxy) > 0.01
        low = p[2] < CARRY_Z - 0.03
        rz = RELEASE_Z[dest_c] + kn["release_dz"]
        goal_hold = jnp.where(far, jnp.where(low, jnp.array([p[0], p[1], CARRY_Z]),
                                             jnp.array([dxy[0], dxy[1], CARRY_Z])), jnp.array([dxy[0], dxy[1], rz]))
        release = (~far) & (jnp.abs(p[2] - rz) < 0.008)
        # not holding: hover over the target, descend, close
        gerr = jnp.linalg.norm(p[:2] - g)
        gfar = gerr > 0.008
        # far: travel at hover height; close: hold the height while correcting xy (no bobbing up when the estimate
        # moves by a few mm between chunks); aligned: descend
        goal_z = jnp.where(gerr > 0.03, HOVER_Z, jnp.where(gfar, p[2], grasp_z))
        goal_pick = jnp.array([g[0], g[1], goal_z])
        close = (~gfar) & (p[2] < grasp_z + 0.006)
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
        new_dest = jnp.where(hold, dest_c, route(obj_c[j], g[1]))
        new_done = done | (grasp & (jnp.arange(N_OBJ) == j))
        return (p + d, new_hold, empty, new_dest, new_done), a

    init = (pos0, holding0, empty0, held_c, jnp.zeros(N_OBJ, bool))
    _, acts = jax.lax.scan(step, init, jnp.arange(CHUNK, dtype=jnp.float32))
    return acts.astype(jnp.float32)


def policy_apply(params: dict, obs: dict, rng: jax.Array) -> jax.Array:
    """The zoo policy: pixels + state + task -> [25, 7] raw delta-EE actions.

    ``params = {"net": estimator weights, "knobs": ControlKnobs.arrays()}``; ``rng`` draws the knobs' per-chunk
    errors (a policy whose knobs are all off is deterministic)."""
    images = jnp.asarray(obs["images"])[None]
    state = jnp.asarray(obs["state"], jnp.float32)
    est = decode(net_apply(params["net"], images, state[None])[0])
    return controller(est, state, jnp.asarray(obs["task"], jnp.int32), params["knobs"], rng)


# -- registry -----------------------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class ZooEntry:
    name: str
    task: str  # the task the policy is meant for
    weights: str  # estimator file under sc3_jax/benchmarks/bussing/zoo/
    recipe: str  # how the estimator was trained and which knobs are set
    knobs: ControlKnobs = ControlKnobs()


_CLEAN = "300 clean bussing demos"
_REV = "300 clean reverse-bussing demos"
ZOO: dict[str, ZooEntry] = {e.name: e for e in (
    # bussing: estimator quality x scripted failure tendencies
    ZooEntry("bus_bc_full", "bussing", "run_clean_final.npz", f"{_CLEAN}, 5000 steps; no knobs"),
    ZooEntry("bus_grasp_sloppy", "bussing", "run_clean_mid.npz",
             f"{_CLEAN}, checkpoint at 1500 steps; grasp aim error 1.5 cm", ControlKnobs(grasp_sigma=0.015)),
    ZooEntry("bus_release_sloppy", "bussing", "run_clean_final.npz",
             f"{_CLEAN}, 5000 steps; releases 8 cm outwards (+-3 cm), 6 cm higher",
             ControlKnobs(release_out=0.08, release_sigma=0.03, release_dz=0.06)),
    ZooEntry("bus_confused", "bussing", "run_clean_final.npz", f"{_CLEAN}, 5000 steps; greedy routing (any abs(y))",
             ControlKnobs(greedy_y=0.0)),
    ZooEntry("bus_bc_small", "bussing", "run_small_final.npz", "30 clean bussing demos, 1500 steps; no knobs"),
    ZooEntry("bus_mid_confused", "bussing", "run_clean_mid.npz",
             f"{_CLEAN}, checkpoint at 1500 steps; greedy routing (abs(y) > 8 cm), releases 10 cm higher",
             ControlKnobs(greedy_y=0.08, release_dz=0.1)),
    ZooEntry("bus_grasp_high", "bussing", "run_clean_final.npz",
             f"{_CLEAN}, 5000 steps; grasps 1.5 cm high, greedy routing (abs(y) > 10 cm)",
             ControlKnobs(grasp_dz=0.015, greedy_y=0.1)),
    # reverse bussing: their own estimators (trained on reverse demos) and their own knobs
    ZooEntry("rev_bc_full", "reverse", "run_reverse_final.npz", f"{_REV}, 3000 steps; no knobs",
             ControlKnobs(dest_frame=1)),
    ZooEntry("rev_bc_small", "reverse", "run_reverse_mid.npz", f"{_REV}, checkpoint at 1000 steps; no knobs",
             ControlKnobs(dest_frame=1)),
    ZooEntry("rev_release_sloppy", "reverse", "run_reverse_final.npz",
             f"{_REV}, 3000 steps; releases 7 cm outwards (+-3 cm), greedy abs(y) > 12 cm",
             ControlKnobs(dest_frame=1, release_out=0.07, release_sigma=0.03, greedy_y=0.12)),
    ZooEntry("rev_grasp_sloppy", "reverse", "run_reverse_final.npz",
             f"{_REV}, 3000 steps; grasp aim error 2 cm, releases 4 cm outwards",
             ControlKnobs(dest_frame=1, grasp_sigma=0.02, release_out=0.04)),
    ZooEntry("rev_transfer", "reverse", "run_clean_final.npz",
             f"bussing estimator ({_CLEAN}, 5000 steps) flipped; greedy abs(y) > 14 cm", ControlKnobs(greedy_y=0.14)),
    ZooEntry("rev_confused", "reverse", "run_clean_final.npz",
             f"bussing estimator ({_CLEAN}, 5000 steps) flipped; greedy abs(y) > 2 cm, grasp aim error 1 cm",
             ControlKnobs(greedy_y=0.02, grasp_sigma=0.01)),
)}


def zoo_names(task: str | None = None) -> list[str]:
    return [n for n, e in ZOO.items() if task is None or e.task == task]


save_params = convnet.save_params  # float16 weights (zoo_train writes them)


def load_params(path: str | Path) -> dict:
    return convnet.load_params(path, "train them again (`sc3 sim zoo-train`), or restore the shipped ones with git")


def load_policy(name: str, zoo_dir: str | Path | None = None) -> JaxPolicy:
    """The zoo policy ``name``: its estimator weights (``sc3_jax/benchmarks/bussing/zoo/<weights>``) and its control knobs."""
    if name not in ZOO:
        raise KeyError(f"unknown zoo policy {name!r}; known: {sorted(ZOO)}")
    path = Path(zoo_dir or ZOO_DIR) / ZOO[name].weights
    if not path.exists():
        raise FileNotFoundError(f"{path}: zoo weights missing; train them with `sc3 sim zoo-train`")
    return JaxPolicy(name, policy_apply, {"net": load_params(path), "knobs": ZOO[name].knobs.arrays()}, chunk=CHUNK)

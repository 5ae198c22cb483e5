"""The SO-101 policy zoo: policies that see only the front camera and the robot's 14-D state, pure JAX, so they run
inside the world model's ``lax.scan`` as they run in the simulator.

What is learned, what is scripted, what is a knob (as in the bussing zoo, and for the same reason: pure pixel-to-
action behaviour cloning does not train to a useful policy on a 2-core budget):
  * Learned: a small CNN (``estimator``) that reads the frame (and the end-effector position) and estimates where
    the block is (x, y, z) and where the goal disc is (x, y). It is trained by regression on frames of the
    collected dataset, labelled by the dataset's own ``observation.environment_state``. Estimators differ by
    training budget and data.
  * Scripted: a stateless chunk planner in ``jnp`` (``controller``): from the estimates and the state (the gripper
    command, state[10]: 1 open, -1 closed; the end-effector, state[11:14]) it decides what the arm is doing --
    hovering over the block, descending, closing, lifting, carrying, lowering, opening -- and plans ``CHUNK`` 4-D
    actions (dx, dy, dz in [-1, 1] of ``ACTION_SCALE`` metres, gripper 1 open / 0 closed) on a kinematic model of
    the arm (the grasp point moves by the commanded step), phases following one another inside the chunk.
  * Knobs (``Knobs``, per policy, carried in its params): a horizontal aim error at the grasp and at the release,
    drawn afresh per chunk, and Gaussian noise on every position action, all from the policy's ``rng``.
Policies differ by estimator and knobs, so their success rates in the simulator spread (docs/so101.md).
"""
from __future__ import annotations

import dataclasses
from pathlib import Path

import jax
import jax.numpy as jnp

from sc3_jax.policies import convnet
from sc3_jax.policies.convnet import conv, conv_init, dense_init, mlp
from sc3_jax.policies.base import JaxPolicy
from .env import ACTION_SCALE  # metres per unit position action (no simulator import: env loads it lazily)

ZOO_DIR = Path(__file__).parent / "zoo"
CHUNK = 10  # actions per inference: 1 s at the env's 10 Hz
STATE_DIM, ACTION_DIM = 14, 4
GRIP, EE = 10, slice(11, 14)  # in the 14-D agent_pos: the gripper command, the end-effector (gripperframe) xyz
# the grasp point between the jaws sits this far from the reported end-effector once the gripper points down
# (measured on the scripted controller's episodes: (0.000, 0.026, 0.001) within 1 mm)
GRASP_OFFSET = jnp.array([0.0, 0.026, 0.001])
BLOCK_Z = 0.02  # the block's centre resting on the table
GRASP_Z = BLOCK_Z + 0.015  # the grasp point when gripping (the pads pinch the block's upper part)
HOVER_Z = BLOCK_Z + 0.07
LIFT_Z = GRASP_Z + 0.06
CLOSE_STEPS, OPEN_STEPS = 10, 8  # the jaw needs this many control steps to close / open
CAREFUL = 0.4  # action magnitude near the block
N_KP = 16
# estimator targets, scaled to about unit spread: block (x, y, z), goal (x, y)
CENTRE = jnp.array([0.225, 0.0, BLOCK_Z, 0.225, 0.0])
SCALE = 10.0


# -- the estimator ----------------------------------------------------------------------------------------------
def init_estimator(key: jax.Array, widths: tuple[int, int, int] = (16, 32, 32)) -> dict:
    ks = jax.random.split(key, 7)
    w1, w2, w3 = widths
    return {"c1": conv_init(ks[0], 3, 5, w1), "c2": conv_init(ks[1], 3, w1, w2), "c3": conv_init(ks[2], 3, w2, w3),
            "c4": conv_init(ks[3], 3, w3, N_KP), "d1": dense_init(ks[4], 3 * N_KP + 4, 128),
            "d2": dense_init(ks[5], 128, 128), "out": dense_init(ks[6], 128, 5, 0.1)}


def estimate(net: dict, images: jax.Array, state: jax.Array) -> jax.Array:
    """images uint8 [B, H, W, 3] (the camera at its own size: the block is a few pixels wide, so nothing is
    resized), state [B, 14] -> [B, 5] block xyz, goal xy in metres."""
    b, h, w, _ = images.shape
    x = images.astype(jnp.float32) / 255.0 - 0.5
    ys, xs = jnp.meshgrid(jnp.linspace(-1, 1, h), jnp.linspace(-1, 1, w), indexing="ij")
    x = jnp.concatenate([x, jnp.broadcast_to(jnp.stack([xs, ys], -1), (b, h, w, 2))], -1)
    x = jax.nn.relu(conv(x, net["c1"], 2))
    x = jax.nn.relu(conv(x, net["c2"], 2))
    x = jax.nn.relu(conv(x, net["c3"], 1))
    x = conv(x, net["c4"], 1)  # [B, h/4, w/4, K]
    hh, ww = x.shape[1:3]
    logits = x.reshape(b, hh * ww, N_KP)
    gy, gx = jnp.meshgrid(jnp.linspace(-1, 1, hh), jnp.linspace(-1, 1, ww), indexing="ij")
    kp = jnp.einsum("bsk,sc->bkc", jax.nn.softmax(logits, axis=1), jnp.stack([gx.reshape(-1), gy.reshape(-1)], -1))
    f = jnp.concatenate([kp.reshape(b, -1), jnp.tanh(0.1 * logits.max(1)), (state[:, EE] - CENTRE[:3]) * SCALE,
                         state[:, GRIP:GRIP + 1]], -1)
    return CENTRE + mlp(net, f) / SCALE


def estimator_loss(net: dict, images, state, labels) -> jax.Array:
    """Mean squared error in centimetres-ish units (targets scaled by ``SCALE``)."""
    return jnp.mean(jnp.sum(((estimate(net, images, state) - labels) * SCALE) ** 2, -1))


# -- the controller ---------------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class Knobs:
    """One policy's failure tendencies (metres; action units for ``action_sigma``); 0 = off. ``grasp_sigma``: std
    of the aim error at the grasp, ``release_sigma``: at the release, both drawn per chunk (missed grasps are
    retried, so they cost time; a release beside the goal disc is a placing failure); ``action_sigma``: std of the
    noise on every position action."""
    grasp_sigma: float = 0.0
    release_sigma: float = 0.0
    action_sigma: float = 0.0

    def arrays(self) -> dict:
        return {k: jnp.asarray(v, jnp.float32) for k, v in dataclasses.asdict(self).items()}


def controller(est: jax.Array, state: jax.Array, knobs: dict, rng: jax.Array) -> jax.Array:
    """Estimates [5] (block xyz, goal xy) + state [14] -> actions [CHUNK, 4]. The phase is read from the start of
    the chunk (gripper command; whether the block sits between the jaws) and followed on the kinematic model."""
    k_g, k_r, k_a = jax.random.split(rng, 3)
    block = est[:3].at[:2].add(knobs["grasp_sigma"] * jax.random.normal(k_g, (2,)))
    goal = est[3:5] + knobs["release_sigma"] * jax.random.normal(k_r, (2,))
    noise = knobs["action_sigma"] * jax.random.normal(k_a, (CHUNK, 3))
    g0 = state[EE] + GRASP_OFFSET
    closed0 = state[GRIP] < 0
    between = (jnp.linalg.norm(est[:2] - g0[:2]) < 0.02) & (est[2] > g0[2] - 0.03)
    # carry: grasp point, jaw command (1.0 open, 0.0 closed), holding the block, steps left while the jaw moves.
    # A closed jaw with the block between the jaws is holding it; with none (a missed grasp, a dropped block) it
    # opens and the approach starts again.
    init = (g0, jnp.where(closed0 & between, 0.0, 1.0), closed0 & between, jnp.int32(0))

    def step(carry, eps):
        g, jaw, holding, wait = carry
        b = jnp.where(holding, g - jnp.array([0.0, 0.0, GRASP_Z - BLOCK_Z]), block)  # a held block moves with us
        to_goal = goal - b[:2]
        near_goal = jnp.linalg.norm(to_goal) < 0.004
        over_block = jnp.linalg.norm(b[:2] - g[:2]) < 0.006
        low = g[2] < GRASP_Z + 0.006

        def at(xy, z):
            return jnp.concatenate([xy, jnp.array([z])])
        carry_t = jnp.where(g[2] < LIFT_Z - 0.005, at(g[:2], LIFT_Z), at(g[:2] + to_goal, LIFT_Z))
        hover_t = jnp.where((g[2] < HOVER_Z - 0.02) & (jnp.linalg.norm(b[:2] - g[:2]) > 0.03),
                            at(g[:2], HOVER_Z), at(b[:2], HOVER_Z))
        target = jnp.where(holding, jnp.where(near_goal, at(g[:2] + to_goal, GRASP_Z + 0.002), carry_t),
                           jnp.where(over_block, at(b[:2], GRASP_Z), hover_t))
        release = (wait == 0) & holding & near_goal & low
        grasp = (wait == 0) & ~holding & over_block & low
        still = (wait > 0) | release | grasp  # the jaw moves; the arm waits
        speed = jnp.where(holding | over_block, CAREFUL, 1.0)
        a = jnp.clip(jnp.clip((target - g) / ACTION_SCALE, -speed, speed) + eps, -1.0, 1.0)
        a = jnp.where(still, 0.0, a)
        jaw = jnp.where(grasp, 0.0, jnp.where(release, 1.0, jaw))
        wait = jnp.where(grasp, CLOSE_STEPS, jnp.where(release, OPEN_STEPS, jnp.maximum(wait - 1, 0)))
        holding = jnp.where(release, False, holding | ((jaw == 0.0) & (wait == 1)))  # closed: the block is held
        return (g + a * ACTION_SCALE, jaw, holding, wait), jnp.concatenate([a, jaw[None]])

    _, actions = jax.lax.scan(step, init, noise)
    return actions


def policy_apply(params: dict, obs: dict, rng: jax.Array) -> jax.Array:
    """The zoo's ``JaxPolicy.apply``: one observation (images uint8 [1, H, W, 3], state [14]) -> [CHUNK, 4]."""
    state = jnp.asarray(obs["state"], jnp.float32)
    est = estimate(params["net"], jnp.asarray(obs["images"])[:1], state[None])[0]
    return controller(est, state, params["knobs"], rng)


# -- the registry -----------------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class ZooEntry:
    weights: str  # estimator file in ZOO_DIR
    knobs: Knobs = Knobs()
    note: str = ""


ZOO: dict[str, ZooEntry] = {
    "so_full": ZooEntry("est_full.npz", note="the full estimator, no knobs"),
    "so_aim1": ZooEntry("est_full.npz", Knobs(grasp_sigma=0.008), "grasp aim error 8 mm"),
    "so_aim2": ZooEntry("est_full.npz", Knobs(grasp_sigma=0.015), "grasp aim error 15 mm"),
    "so_place": ZooEntry("est_full.npz", Knobs(release_sigma=0.02), "release aim error 20 mm"),
    "so_noise2": ZooEntry("est_full.npz", Knobs(action_sigma=0.2), "noise of 0.2 on every position action"),
    "so_noise3": ZooEntry("est_full.npz", Knobs(action_sigma=0.3), "noise of 0.3 on every position action"),
    "so_shaky": ZooEntry("est_full.npz", Knobs(action_sigma=0.5), "noise of 0.5 on every position action"),
    "so_small": ZooEntry("est_small.npz", note="an estimator of a tenth of the budget and data"),
}


save_params = convnet.save_params  # float16 weights (zoo_train writes them)


def load_params(path: str | Path) -> dict:
    return convnet.load_params(path, "train them again (`sc3 so101 zoo-train`), or restore the shipped ones with git")


def load_policy(name: str, zoo_dir: str | Path | None = None) -> JaxPolicy:
    if name not in ZOO:
        raise KeyError(f"unknown SO-101 zoo policy {name!r}; known: {sorted(ZOO)}")
    path = Path(zoo_dir or ZOO_DIR) / ZOO[name].weights
    if not path.exists():
        raise FileNotFoundError(f"{path}: zoo weights missing; train them with `sc3 so101 zoo-train`")
    return JaxPolicy(name, policy_apply, {"net": load_params(path), "knobs": ZOO[name].knobs.arrays()}, chunk=CHUNK,
                     action_dim=ACTION_DIM, state_dim=STATE_DIM)


def named_policy(name: str):
    """A zoo policy by its name, with its task (one task here): ``policies.resolve``'s ``named``."""
    from sc3_jax.policies.resolve import SPELLINGS
    if name not in ZOO:
        raise ValueError(f"unknown policy {name!r}: expected {SPELLINGS}; SO-101 zoo policies are {sorted(ZOO)}")
    return load_policy(name), None

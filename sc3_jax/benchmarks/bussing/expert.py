"""Scripted expert with quality knobs, and the episode runner shared by demos and tests.

The expert reads privileged simulator state (object and container positions) and busses the objects one at a time
in a fixed order (largest x first, i.e. closest to the containers), with phases
hover -> descend -> close -> lift -> carry -> lower -> release -> retreat. It makes one grasp attempt per object.

Quality knobs (``ExpertKnobs``), each producing its failure category on purpose:
  * ``grasp_noise`` (m, std of a per-object horizontal offset of the grasp point) -> lifting failures;
  * ``release_noise`` (m, std of a per-object horizontal offset of the release point) -> placing failures;
  * ``wrong_destination_prob`` (probability per object of taking it to the other container) -> language failures;
    ``swap_types`` (object names always taken to the other container: a *biased* demonstrator);
  * ``action_noise`` (m, std of Gaussian noise on the translation deltas; 3x that in rad on rotations).
The expert also reports its *intent* every step (where it aims to pick, which container it chose), which the policy
zoo clones.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from . import scene as S
from .criteria import ObjectOutcome, evaluate_episode, inside_container
from .env import BussingEnv
from .tasks import CONTAINERS, OBJECT_BY_NAME, OBJECTS, destination

HOVER_Z = 0.13
CARRY_Z = 0.17
EXPERT_STEP = 0.03
GAIN = 0.6
RELEASE_ABOVE_RIM = 0.06
SETTLE_STEPS = 20
SLOTS = np.array([[-0.03, -0.03], [0.03, 0.03], [-0.03, 0.03], [0.03, -0.03]])  # drop spots in a container
MAX_STEPS_20HZ = 400  # 20 s


@dataclasses.dataclass(frozen=True)
class ExpertKnobs:
    grasp_noise: float = 0.0
    release_noise: float = 0.0
    wrong_destination_prob: float = 0.0
    action_noise: float = 0.0
    swap_types: tuple[str, ...] = ()
    # an episode whose every object goes to the other container *is* a reverse-bussing episode; world-model data
    # must not contain one (the OOD split's claim), so one object drawn wrong by chance is set right again
    never_swap_all: bool = True


@dataclasses.dataclass
class _Plan:
    name: str
    grasp_offset: np.ndarray
    release_offset: np.ndarray
    container: str  # where the expert will take it (may be wrong on purpose)


class ScriptedExpert:
    def __init__(self, knobs: ExpertKnobs = ExpertKnobs(), seed: int = 0):
        self.knobs, self.seed = knobs, int(seed)

    def reset(self, env: BussingEnv) -> None:
        k, ic = self.knobs, env.ic
        self.rng = np.random.default_rng([self.seed, 104729])
        order = sorted(range(len(ic.objects)), key=lambda i: -ic.object_xy[i, 0])
        self.plans = []
        used = {"bin": 0, "can": 0}
        for i in order:
            name = ic.objects[i]
            dest = destination(OBJECT_BY_NAME[name].cls, ic.task)
            wrong = (name in k.swap_types) or (self.rng.random() < k.wrong_destination_prob)
            if wrong:
                dest = "can" if dest == "bin" else "bin"
            slot = SLOTS[used[dest] % len(SLOTS)] * (S.CONTAINER_GEOM[dest][0] / S.BIN_INNER)
            used[dest] += 1
            release = slot + (self.rng.normal(0, k.release_noise, 2) if k.release_noise else np.zeros(2))
            self.plans.append(_Plan(name, self.rng.normal(0, k.grasp_noise, 2) if k.grasp_noise else np.zeros(2),
                                    release, dest))
        if k.never_swap_all:
            self._unswap_one(ic)
        self.k, self.phase, self.count = 0, "hover", 0
        self.done = False

    def _unswap_one(self, ic) -> None:
        """If every object was drawn for the wrong container, send one chance-drawn one (not a ``swap_types`` one)
        to its instructed container, at that container's next free drop spot. Uses its own rng, so episodes that
        need no change are bit-identical to ``never_swap_all=False``."""
        right = {p.name: destination(OBJECT_BY_NAME[p.name].cls, ic.task) for p in self.plans}
        if any(p.container == right[p.name] for p in self.plans):
            return
        chance = [i for i, p in enumerate(self.plans) if p.name not in self.knobs.swap_types]
        if not chance:
            return  # every object is of a swap type: the demonstrator's bias itself, nothing drawn by chance
        i = chance[int(np.random.default_rng([self.seed, 15485863]).integers(len(chance)))]
        p = self.plans[i]

        def slot(container, index):
            return SLOTS[index % len(SLOTS)] * (S.CONTAINER_GEOM[container][0] / S.BIN_INNER)

        old = slot(p.container, sum(q.container == p.container for q in self.plans[:i]))
        new = slot(right[p.name], sum(q.container == right[p.name] for q in self.plans))  # the next free spot
        p.release_offset = p.release_offset - old + new  # keeps the drawn release noise
        p.container = right[p.name]

    # -- intent (what the zoo clones) ------------------------------------------------------------------------
    def intent(self, env: BussingEnv) -> dict:
        """pick_xy / pick_dest: the object to pick next (current one until grasped); held_dest: container chosen for
        the held object (-1 if none); any_left: an object remains to be picked."""
        holding = env.held is not None
        nxt = self.k + (1 if (holding or self.phase in ("carry", "lower", "release", "retreat")) else 0)
        if nxt < len(self.plans):
            p = self.plans[nxt]
            pick_xy = env.object_pos(p.name)[:2] + p.grasp_offset
            pick_dest = CONTAINERS.index(p.container)
            any_left = 1.0
        else:
            pick_xy, pick_dest, any_left = env.ee_pose()[:2].astype(np.float64), 0, 0.0
        held_dest = -1
        if holding and self.k < len(self.plans):
            held_dest = CONTAINERS.index(self.plans[self.k].container)
        # per object type (tasks.OBJECTS order): position, "still to be bussed" (on the table, not held, not in a
        # container), and the container the expert chose for it (-1 if not in the episode)
        obj_xy = np.zeros((len(OBJECTS), 2))
        obj_present = np.zeros(len(OBJECTS))
        obj_dest = -np.ones(len(OBJECTS))
        chosen = {p.name: CONTAINERS.index(p.container) for p in self.plans}
        for j, o in enumerate(OBJECTS):
            if o.name not in chosen:
                continue
            pos = env.object_pos(o.name)
            obj_xy[j] = pos[:2]
            obj_dest[j] = chosen[o.name]
            placed = any(bool(inside_container(pos, env.container_xy(c), c)) for c in CONTAINERS)
            obj_present[j] = float(env.held != o.name and not placed and pos[2] > -0.05)
        return {"pick_xy": pick_xy, "pick_dest": pick_dest, "held_dest": held_dest, "any_left": any_left,
                "bin_xy": env.container_xy("bin"), "can_xy": env.container_xy("can"),
                "obj_xy": obj_xy, "obj_present": obj_present, "obj_dest": obj_dest}

    # -- control -----------------------------------------------------------------------------------------------
    def act(self, env: BussingEnv) -> np.ndarray:
        ee = env.ee_pose()
        pos, rv = ee[:3].astype(np.float64), ee[3:6].astype(np.float64)
        grip = S.OPEN_WIDTH
        goal = pos.copy()
        if self.k >= len(self.plans):
            self.done = True
        else:
            p = self.plans[self.k]
            obj = env.object_pos(p.name)
            aim = obj[:2] + p.grasp_offset
            grasp_z = float(np.clip(obj[2], 0.01, 0.03))
            cxy = env.container_xy(p.container) + p.release_offset
            release_z = S.CONTAINER_GEOM[p.container][1] + RELEASE_ABOVE_RIM
            ph = self.phase
            if ph == "hover":
                goal = np.array([aim[0], aim[1], HOVER_Z])
                if np.linalg.norm(pos[:2] - aim) < 0.006:
                    self._next("descend")
                elif self.count > 60 or obj[2] < -0.05:  # unreachable (e.g. knocked off the table): skip it
                    self._advance()
                    return self.act(env)
            elif ph == "descend":
                goal = np.array([aim[0], aim[1], grasp_z])
                if abs(pos[2] - grasp_z) < 0.004:
                    self._next("close")
            elif ph == "close":
                goal, grip = pos, 0.0
                if self.count >= 2:
                    self._next("lift")
            elif ph == "lift":
                goal, grip = np.array([pos[0], pos[1], CARRY_Z]), 0.0
                if pos[2] > CARRY_Z - 0.02:
                    if env.held == p.name:
                        self._next("carry")
                    else:  # failed grasp: one attempt only, move on
                        grip = S.OPEN_WIDTH
                        self._advance()
            elif ph == "carry":
                goal, grip = np.array([cxy[0], cxy[1], CARRY_Z]), 0.0
                if np.linalg.norm(pos[:2] - cxy) < 0.008:
                    self._next("lower")
            elif ph == "lower":
                goal, grip = np.array([cxy[0], cxy[1], release_z]), 0.0
                if abs(pos[2] - release_z) < 0.005:
                    self._next("release")
            elif ph == "release":
                goal = pos
                if self.count >= 2:
                    self._next("retreat")
            elif ph == "retreat":
                goal = np.array([pos[0], pos[1], HOVER_Z + 0.02])
                if pos[2] > HOVER_Z:
                    self._advance()
            self.count += 1
        d = GAIN * (goal - pos)
        n = np.linalg.norm(d)
        if n > EXPERT_STEP:
            d *= EXPERT_STEP / n
        rot = -0.5 * rv
        a = np.concatenate([d, rot, [grip]])
        if self.knobs.action_noise:
            a[:3] += self.rng.normal(0, self.knobs.action_noise, 3)
            a[3:6] += self.rng.normal(0, 3 * self.knobs.action_noise, 3)
        return a.astype(np.float32)

    def _next(self, phase: str) -> None:
        self.phase, self.count = phase, 0

    def _advance(self) -> None:
        self.k += 1
        self._next("hover")


@dataclasses.dataclass
class EpisodeResult:
    ic: object
    frames: dict[str, np.ndarray] | None  # view -> uint8 [T, H, W, 3]
    actions: np.ndarray  # [T, 7]
    ee_pose: np.ndarray  # [T, 7]
    outcomes: list[ObjectOutcome]
    intents: dict[str, np.ndarray] | None = None  # per-step expert intent (expert episodes only)
    # object centres [T + 1, n, 3] (ic.objects order): row t is the state seen in frame t, the last row the final one
    object_pos: np.ndarray | None = None

    @property
    def length(self) -> int:
        return int(self.actions.shape[0])


def finish(env: BussingEnv, traj: list[np.ndarray]) -> list[ObjectOutcome]:
    speeds = np.array([env.object_speed(n) for n in env.ic.objects])
    return evaluate_episode(env.ic, np.stack(traj), speeds, env.held)


def run_expert_episode(env: BussingEnv, seed: int, task: str = "bussing", knobs: ExpertKnobs = ExpertKnobs(),
                       record: bool = True, max_steps: int | None = None,
                       expert: ScriptedExpert | None = None) -> EpisodeResult:
    """Reset ``env`` to ``(seed, task)`` and let the expert bus it. Frame t is observed before action t.
    ``expert``: another expert of the same interface (``benchmarks/bussing/mixture.py``'s data-collection variants) in place of
    ``ScriptedExpert(knobs, seed)``."""
    max_steps = max_steps or MAX_STEPS_20HZ * env.control_hz // 20
    env.reset(seed, task)
    expert = expert if expert is not None else ScriptedExpert(knobs, seed)
    expert.reset(env)
    frames = {v: [] for v in env.views} if record else None
    actions, poses, traj = [], [], [env.object_positions()]
    intents = {k: [] for k in ("pick_xy", "pick_dest", "held_dest", "any_left", "bin_xy", "can_xy", "obj_xy",
                               "obj_present", "obj_dest")}
    settle = 0
    for _ in range(max_steps):
        if record:
            f = env.render()
            for v in env.views:
                frames[v].append(f[v])
        poses.append(env.ee_pose())
        it = expert.intent(env)
        for key in intents:
            intents[key].append(it[key])
        a = expert.act(env)
        actions.append(a)
        env.step(a)
        traj.append(env.object_positions())
        if expert.done:
            settle += 1
            if settle >= SETTLE_STEPS:
                break
    return EpisodeResult(env.ic, {v: np.stack(x) for v, x in frames.items()} if record else None,
                         np.stack(actions).astype(np.float32), np.stack(poses).astype(np.float32),
                         finish(env, traj), {k: np.asarray(v, np.float32) for k, v in intents.items()},
                         np.stack(traj).astype(np.float32))

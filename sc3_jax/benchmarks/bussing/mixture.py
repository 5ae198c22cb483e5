"""Failure-rich world-model data: rollouts of *data-collection* policies, mixed with the scripted expert's clean
demonstrations.

A world model learns what its data shows. The clean expert never misses a grasp, never drops an object and never
carries one to the other container, so a model trained on it imagines success where the evaluated policies fail.
Real robot datasets hold autonomous rollouts with their failures; here that role is played by data-collection
policies that are *not* the evaluated zoo (``zoo.py``): no zoo estimator checkpoint, no zoo knob setting, their
own seeds and per-episode knob draws.

Sources (``SOURCES``; a recipe in ``RECIPES`` weighs them):
  * ``expert_clean``: the scripted expert, no knobs (exactly ``sc3 sim demos``'s clean episodes);
  * ``expert_noisy``: the scripted expert with seeded draws of its failure knobs (grasp, release and action noise):
    missed grasps, releases off target;
  * ``dc_expert``: the expert with retries after a missed grasp, objects slipping from a weak grasp while carried
    (drops), releases off target, and at most one object of the episode taken to the other container;
  * ``dc_controller``: the zoo's scripted chunk controller (25-action chunks, 16 executed, then re-observe; retries,
    re-aiming, hovering) driven by the simulator's state seen through a per-episode estimation error instead of a
    learned estimator, with drawn grasp / release knobs, and at most one object to the other container.

What never enters: the reverse-bussing instruction (every episode has task ``bussing`` and a bussing prompt) and an
episode in which every object ends up in the other container (reverse bussing in all but the prompt): a wrong
container is planned for one object at most, and an episode whose objects all entered the other container anyway
is refused (not written; ``rejected`` counts it). So the out-of-distribution split stays out of distribution: its
instruction and its every-object mapping are never in the data, while single wrong-container carries, which the
evaluated bussing policies make, are.

Episode ``i`` of a mixture with ``seed`` uses simulator seed ``seed * 100_000 + i`` (named ``ep{sim_seed:07d}``);
its source and knob draws depend on ``(seed, i)`` only, so shards and workers write the same episodes. Each
episode's ``meta`` records ``source``, ``recipe``, the drawn ``knobs``, ``events`` (retries, drops, the object sent
to the other container) and ``outcome`` (per-object categories, ``outcome_counts``) next to the usual labels.
"""
from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from sc3_jax.core import atomic

from .expert import ExpertKnobs, ScriptedExpert
from .tasks import CONTAINERS, OBJECTS, destination

MIXTURE_SEED = 40  # disjoint from the demo (1, 3, 10-14, 20-35), held-out (18, 19) and scorer (50-79) seeds
SOURCES = {
    "expert_clean": "scripted expert, no knobs (the clean demonstrations)",
    "expert_noisy": "scripted expert, drawn grasp / release / action noise",
    "dc_expert": "expert with retries, drops from a weak grasp, releases off target, one wrong container at most",
    "dc_controller": "zoo-style chunk controller on noisy simulator state, drawn knobs, one wrong container at most",
}
RECIPES: dict[str, dict[str, float]] = {
    # a quarter clean; the rest show the failures the zoo makes (measured mix: docs/sim.md, `sc3 sim demos-stats`)
    "failure_rich": {"expert_clean": 0.25, "expert_noisy": 0.25, "dc_expert": 0.25, "dc_controller": 0.25},
    "clean": {"expert_clean": 1.0},
}
CATEGORIES = ("lifted", "placed", "wrong_container", "dropped", "missed")
CATEGORY_MEANING = {
    "lifted": "raised at least 3 cm above the table at some step (any outcome)",
    "placed": "at rest in its instructed container at the end (no failure)",
    "wrong_container": "entered the container not instructed (language failure)",
    "dropped": "lifted, never in the wrong container, not placed: dropped on the way or released off target",
    "missed": "never lifted (missed or no grasp), never in the wrong container",
}
CONTROLLER_SECONDS = 12.0  # the sweep's horizon; a failing controller retries until the limit


# -- outcome categories (mixture stores, any demo store and sweep records alike) ----------------------------------
def object_category(o: dict) -> str:
    """The outcome category of one object record (``criteria.ObjectOutcome.to_json`` or a sweep record's object)."""
    if not o["language"]:
        return "wrong_container"
    if not o["lifting"]:
        return "missed"
    return "placed" if o["placing"] else "dropped"


def outcome_counts(objects: list[dict]) -> dict[str, int]:
    """Objects per category (``placed + wrong_container + dropped + missed == objects``) and how many were lifted."""
    c = {k: 0 for k in CATEGORIES}
    for o in objects:
        c[object_category(o)] += 1
        c["lifted"] += bool(o["lifting"])
    c["objects"] = len(objects)
    return c


def _add(total: dict, counts: dict) -> None:
    for k, v in counts.items():
        total[k] = total.get(k, 0) + v


def rates(counts: dict) -> dict[str, float]:
    """Shares of objects per category (``counts`` from ``outcome_counts``)."""
    n = max(counts.get("objects", 0), 1)
    return {k: counts.get(k, 0) / n for k in CATEGORIES}


# -- data-collection policies ---------------------------------------------------------------------------------
class DataCollectionExpert(ScriptedExpert):
    """The scripted expert as a data-collection policy: after a missed grasp it re-aims and tries again (up to
    ``attempts`` per object, a fresh aim error of ``retry_sigma`` each time); objects named in ``drops`` slip from
    the gripper ``drop_after`` steps into their carry (a weak grasp: it falls where it is). Everything else, the
    wrong-container object (``knobs.swap_types``) included, is the expert's."""

    def __init__(self, knobs: ExpertKnobs, seed: int, attempts: int = 1, retry_sigma: float = 0.0,
                 drops: tuple[str, ...] = (), drop_after: int = 4):
        super().__init__(knobs, seed)
        self.attempts, self.retry_sigma, self.drops, self.drop_after = attempts, retry_sigma, drops, drop_after

    def reset(self, env) -> None:
        super().reset(env)
        self._rng = np.random.default_rng([self.seed, 31337])  # its own draws: the expert's stay the expert's
        self.tries, self.events, self._env = 1, {"retries": 0, "drops": 0}, env

    def act(self, env) -> np.ndarray:
        self._env = env
        if self.phase == "carry" and self.k < len(self.plans) and self.count == self.drop_after:
            name = self.plans[self.k].name
            if name in self.drops and env.held == name:
                self.events["drops"] += 1
                self._next("retreat")  # the retreat phase moves on to the next object
                rv = env.ee_pose()[3:6].astype(np.float64)
                return np.concatenate([np.zeros(3), -0.5 * rv, [0.09]]).astype(np.float32)
        return super().act(env)

    def _advance(self) -> None:
        p = self.plans[self.k] if self.k < len(self.plans) else None
        if p is not None and self.phase == "lift" and self._env.held != p.name and self.tries < self.attempts:
            self.tries += 1
            self.events["retries"] += 1
            p.grasp_offset = self._rng.normal(0, self.retry_sigma, 2) if self.retry_sigma else np.zeros(2)
            self._next("hover")
            return
        self.tries = 1
        super()._advance()


class StateController:
    """A host policy (``infer(obs) -> [25, 7]``) running the zoo's chunk controller (``zoo.controller``) on the
    simulator's own state seen through an estimation error: a per-episode bias per object (``bias``, m) plus a
    per-chunk jitter (``jitter``, m). No learned estimator; ``wrong`` names the one object routed to the other
    container (or None). The destinations are the bussing task's."""

    def __init__(self, env, knobs, seed: int, bias: float, jitter: float, wrong: str | None):
        import jax

        from .zoo import controller
        self.env, self.knobs, self.bias, self.jitter, self.wrong = env, knobs.arrays(), bias, jitter, wrong
        self._controller = _jitted(controller)
        self._rng = np.random.default_rng([seed, 7919])
        self._key = jax.random.fold_in(jax.random.key(1), seed)
        self._bias = {o.name: self._rng.normal(0, bias, 2) for o in OBJECTS}
        self.chunks = 0

    def estimates(self) -> dict:
        from .criteria import inside_container
        env = self.env
        xy, present, dest = np.zeros((len(OBJECTS), 2)), np.full(len(OBJECTS), -5.0), np.zeros(len(OBJECTS))
        held_dest = 0.0
        for j, o in enumerate(OBJECTS):
            if o.name not in env.ic.objects:
                continue
            pos = env.object_pos(o.name)
            xy[j] = pos[:2] + self._bias[o.name] + self._rng.normal(0, self.jitter, 2)
            placed = any(bool(inside_container(pos, env.container_xy(c), c)) for c in CONTAINERS)
            present[j] = 5.0 if (env.held != o.name and not placed and pos[2] > -0.05) else -5.0
            c = destination(o.cls, "bussing")
            if o.name == self.wrong:
                c = CONTAINERS[1 - CONTAINERS.index(c)]
            dest[j] = 5.0 if c == CONTAINERS[1] else -5.0  # the controller's logit: > 0 -> container 1
            if env.held == o.name:
                held_dest = dest[j]
        return {"obj_xy": xy, "present": present, "dest": dest, "held_dest": held_dest,
                "bin_xy": env.container_xy("bin"), "can_xy": env.container_xy("can")}

    def infer(self, obs: dict) -> np.ndarray:
        import jax
        import jax.numpy as jnp
        est = {k: jnp.asarray(v, jnp.float32) for k, v in self.estimates().items()}
        self._key, k = jax.random.split(self._key)
        self.chunks += 1
        return np.asarray(self._controller(est, jnp.asarray(obs["state"], jnp.float32), jnp.int32(0), self.knobs, k))


_JIT: dict = {}


def _jitted(fn):
    if fn not in _JIT:  # compiled once per process, reused for every episode
        import jax
        _JIT[fn] = jax.jit(fn)
    return _JIT[fn]


# -- per-episode draws ----------------------------------------------------------------------------------------
def _maybe(rng, p: float, lo: float, hi: float) -> float:
    return round(float(rng.uniform(lo, hi)), 4) if rng.random() < p else 0.0


def _one_wrong(rng, objects: tuple[str, ...], p: float) -> str | None:
    """One object (never every object: none when the episode has a single one) for the other container."""
    return str(objects[rng.integers(len(objects))]) if len(objects) > 1 and rng.random() < p else None


def draw(source: str, rng: np.random.Generator, objects: tuple[str, ...]) -> dict:
    """The knobs of one episode of ``source`` (JSON-able), drawn with ``rng`` for the episode's ``objects``."""
    if source == "expert_clean":
        return {}
    if source == "expert_noisy":
        k = {"grasp_noise": _maybe(rng, 0.5, 0.01, 0.05), "release_noise": _maybe(rng, 0.4, 0.02, 0.1),
             "action_noise": _maybe(rng, 0.4, 0.004, 0.015)}
        if not any(k.values()):
            k["grasp_noise"] = round(float(rng.uniform(0.01, 0.05)), 4)
        return k
    if source == "dc_expert":
        wrong = _one_wrong(rng, objects, 0.5)
        return {"grasp_noise": _maybe(rng, 0.7, 0.01, 0.04), "release_noise": _maybe(rng, 0.3, 0.02, 0.08),
                "action_noise": _maybe(rng, 0.3, 0.002, 0.01), "wrong": wrong,
                "attempts": int(rng.integers(1, 4)), "retry_sigma": round(float(rng.uniform(0.0, 0.02)), 4),
                "drops": [o for o in objects if rng.random() < 0.15], "drop_after": int(rng.integers(1, 9))}
    if source == "dc_controller":
        wrong = _one_wrong(rng, objects, 0.5)
        # an estimate off by more than the 3-cm grasp tolerance misses every retry, as a weak estimator does
        return {"grasp_sigma": _maybe(rng, 0.6, 0.003, 0.02), "grasp_dz": _maybe(rng, 0.25, 0.008, 0.018),
                "release_out": _maybe(rng, 0.3, 0.05, 0.11), "release_sigma": _maybe(rng, 0.3, 0.005, 0.03),
                "release_dz": _maybe(rng, 0.3, 0.02, 0.1), "bias": round(float(rng.uniform(0.004, 0.03)), 4),
                "jitter": round(float(rng.uniform(0.0, 0.006)), 4), "wrong": wrong}
    raise KeyError(f"unknown data-collection source {source!r}; known: {sorted(SOURCES)}")


def choose_source(recipe: str, seed: int, i: int) -> tuple[str, np.random.Generator]:
    """Episode ``i``'s source under ``recipe``, and the rng its knobs are drawn with (a function of (seed, i))."""
    weights = RECIPES[recipe]
    rng = np.random.default_rng([int(seed), int(i), 2718281])
    names = list(weights)
    p = np.array([weights[n] for n in names], np.float64)
    return names[int(rng.choice(len(names), p=p / p.sum()))], rng


def run_source(env, source: str, knobs: dict, sim_seed: int, record: bool = True):
    """One bussing episode of ``source`` with the drawn ``knobs`` -> (EpisodeResult, events)."""
    from .expert import run_expert_episode
    if source in ("expert_clean", "expert_noisy"):
        ek = ExpertKnobs(**{k: knobs.get(k, 0.0) for k in ("grasp_noise", "release_noise", "action_noise")})
        return run_expert_episode(env, sim_seed, "bussing", ek, record=record), {}
    if source == "dc_expert":
        ek = ExpertKnobs(knobs["grasp_noise"], knobs["release_noise"], 0.0, knobs["action_noise"],
                         swap_types=(knobs["wrong"],) if knobs["wrong"] else ())
        expert = DataCollectionExpert(ek, sim_seed, knobs["attempts"], knobs["retry_sigma"], tuple(knobs["drops"]),
                                      knobs["drop_after"])
        r = run_expert_episode(env, sim_seed, "bussing", ek, record=record, expert=expert)
        return r, {**expert.events, "wrong": knobs["wrong"]}
    if source == "dc_controller":
        from .policy_eval import run_policy_episode
        from .zoo import ControlKnobs
        ck = ControlKnobs(**{k: knobs[k] for k in ("grasp_sigma", "grasp_dz", "release_out", "release_sigma",
                                                   "release_dz")})
        host = StateController(env, ck, sim_seed, knobs["bias"], knobs["jitter"], knobs["wrong"])
        r = run_policy_episode(env, host, sim_seed, "bussing", record=record,
                               max_steps=int(round(CONTROLLER_SECONDS * env.control_hz)))
        return r, {"chunks": host.chunks, "wrong": knobs["wrong"]}
    raise KeyError(f"unknown data-collection source {source!r}; known: {sorted(SOURCES)}")


# -- the store ------------------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class MixtureSpec:
    """What ``generate_mixture`` writes: the store, how many episodes, from which seed and recipe, at what size."""

    out: str
    episodes: int
    seed: int = MIXTURE_SEED
    recipe: str = "failure_rich"
    image_size: tuple[int, int] = (64, 64)
    control_hz: int = 20
    n_objects: int = 3


def generate_mixture(out: str | Path, episodes: int, seed: int = MIXTURE_SEED, recipe: str = "failure_rich",
                     image_size: tuple[int, int] = (64, 64), control_hz: int = 20, n_objects: int = 3,
                     shard: tuple[int, int] = (0, 1), workers: int = 1, seconds: float | None = None,
                     progress: bool = True) -> dict:
    """Write episodes ``shard[0], shard[0] + shard[1], ...`` (< ``episodes``) of the mixture to the episode store at
    ``out``; resumable (episodes already there are skipped), deterministic by ``(seed, i)``. ``workers`` > 1 runs
    that many processes, each its own share. ``seconds``: start no episode after this much wall time (the store
    keeps what was written; rerun to go on). Returns a summary: written / skipped / rejected, per source, outcome
    counts of the episodes written now."""
    spec = MixtureSpec(str(out), int(episodes), int(seed), recipe, tuple(image_size), int(control_hz), int(n_objects))
    _check(spec, shard, workers)
    deadline = None if seconds is None else time.time() + float(seconds)
    _open_store(spec)  # the header, written once before any worker starts
    t0 = time.time()
    if workers > 1:
        import concurrent.futures as cf
        import multiprocessing as mp
        i, n = shard
        with cf.ProcessPoolExecutor(workers, mp_context=mp.get_context("spawn")) as pool:
            parts = list(pool.map(_shard_worker, [(spec, (i + k * n, n * workers), deadline) for k in
                                                  range(workers)]))
    else:
        parts = [_write_shard(spec, shard, deadline, progress)]
    res = _merge(parts)
    res.update(out=spec.out, recipe=recipe, seed=seed, episodes=episodes, seconds=time.time() - t0)
    res["episodes_per_hour"] = res["written"] / res["seconds"] * 3600 if res["written"] and res["seconds"] else None
    return res


def _check(spec: MixtureSpec, shard: tuple[int, int], workers: int) -> None:
    if spec.recipe not in RECIPES:
        raise KeyError(f"unknown recipe {spec.recipe!r}; known: {sorted(RECIPES)}")
    if not 0 <= spec.episodes < 100_000:
        raise ValueError(f"episodes {spec.episodes}: 0 to 99,999 (episode i has simulator seed seed*100000+i)")
    if not 0 <= spec.seed < 100:
        raise ValueError(f"seed {spec.seed}: keep below 100 (the sweep evaluates on simulator seeds from 10^7)")
    if not (shard[1] >= 1 and 0 <= shard[0] < shard[1]) or workers < 1:
        raise ValueError(f"shard {shard}, workers {workers}: need 0 <= I < N and workers >= 1")


def _open_store(spec: MixtureSpec):
    from sc3_jax.data.episodes import EpisodeStore
    from .scene import VIEWS
    return EpisodeStore(spec.out, views=list(VIEWS), fps=spec.control_hz, image_size=spec.image_size, create=True)


def _shard_worker(args) -> dict:
    spec, shard, deadline = args
    return _write_shard(spec, shard, deadline, progress=False)


def _write_shard(spec: MixtureSpec, shard: tuple[int, int], deadline: float | None, progress: bool) -> dict:
    from tqdm import tqdm

    from sc3_jax.data.episodes import Episode
    from .demos import episode_meta, episode_seed
    from .env import BussingEnv
    from .tasks import make_initial_condition
    store = _open_store(spec)
    env = BussingEnv(image_size=spec.image_size, control_hz=spec.control_hz, n_objects=spec.n_objects)
    res = {"written": 0, "skipped": 0, "rejected": 0, "rejected_episodes": [], "unstarted": 0, "steps": 0,
           "sources": {}, "counts": {}}
    ids = range(shard[0], spec.episodes, shard[1])
    for n, i in enumerate(tqdm(ids, desc="mixture", disable=not progress)):
        sim_seed = episode_seed(spec.seed, i)
        eid = f"ep{sim_seed:07d}"
        if eid in store:
            res["skipped"] += 1
            continue
        if deadline is not None and time.time() > deadline:
            res["unstarted"] = sum(f"ep{episode_seed(spec.seed, j):07d}" not in store for j in ids[n:])
            break
        source, rng = choose_source(spec.recipe, spec.seed, i)
        objects = make_initial_condition(sim_seed, "bussing", spec.n_objects).objects
        knobs = draw(source, rng, tuple(objects))
        r, events = run_source(env, source, knobs, sim_seed)
        counts = outcome_counts([o.to_json() for o in r.outcomes])
        if counts["objects"] > 1 and counts["wrong_container"] == counts["objects"]:
            res["rejected"] += 1  # reverse bussing in all but the prompt: never in world-model data
            res["rejected_episodes"].append(eid)
            continue
        meta = episode_meta(r, "bussing", sim_seed, {"source": source, "recipe": spec.recipe, "knobs": knobs,
                                                    "events": events, "outcome": counts}, spec.control_hz)
        store.write(Episode(eid, r.frames, r.actions, r.ee_pose, r.ic.prompt, meta))
        res["written"] += 1
        res["steps"] += r.length
        res["sources"][source] = res["sources"].get(source, 0) + 1
        _add(res["counts"].setdefault(source, {}), counts)
    env.close()
    return res


def _merge(parts: list[dict]) -> dict:
    out = {"written": 0, "skipped": 0, "rejected": 0, "rejected_episodes": [], "unstarted": 0, "steps": 0,
           "sources": {}, "counts": {}}
    for p in parts:
        for k in ("written", "skipped", "rejected", "unstarted", "steps"):
            out[k] += p[k]
        out["rejected_episodes"] += p["rejected_episodes"]
        for s, v in p["sources"].items():
            out["sources"][s] = out["sources"].get(s, 0) + v
        for s, c in p["counts"].items():
            _add(out["counts"].setdefault(s, {}), c)
    total: dict = {}
    for c in out["counts"].values():
        _add(total, c)
    out["counts"]["all"] = total
    return out


# -- what a store holds, against the zoo's real outcomes --------------------------------------------------------
def _source_label(m: dict) -> str:
    if m.get("source"):
        return m["source"]
    if m.get("policy"):
        return f"zoo policy {m['policy']}"
    knobs = ",".join(f"{k}={v}" for k, v in sorted((m.get("knobs") or {}).items()) if v and k != "never_swap_all")
    return f"expert {knobs}" if knobs else "expert_clean"


def store_outcomes(*roots: str | Path) -> dict:
    """Outcome counts of every object in the episode stores ``roots`` (from ``meta.json``), per source (a mixture's
    ``source``; older stores: the expert's knobs or the zoo policy recorded), overall (``all``) and per object type
    (``objects``)."""
    per_source: dict[str, dict] = {}
    per_object: dict[str, dict] = {}
    for root in roots:
        for d in sorted(Path(root).iterdir()):
            if not (d / "meta.json").exists():
                continue
            m = json.loads((d / "meta.json").read_text())
            objs = m["labels"]["objects"]
            c = outcome_counts(objs)
            c["episodes"] = 1
            _add(per_source.setdefault(_source_label(m), {}), c)
            for o in objs:
                _add(per_object.setdefault(o["name"], {}), outcome_counts([o]))
    total: dict = {}
    for c in per_source.values():
        _add(total, c)
    return {"sources": dict(sorted(per_source.items())), "all": total,
            "objects": {o.name: per_object[o.name] for o in OBJECTS if o.name in per_object}}


def default_zoo_real() -> Path:
    """The archived 72-condition sweep of the zoo (``docs/stores/sweep72_gpu``): its real rollouts are the zoo's
    measured outcomes (physics) on the evaluation conditions."""
    return Path(__file__).resolve().parents[3] / "docs" / "stores" / "sweep72_gpu"


def zoo_real_outcomes(path: str | Path | None = None) -> dict:
    """Outcome counts of the zoo's real (physics) rollouts in a sweep results store (``path``: its directory or its
    ``results.jsonl``; default ``default_zoo_real()``), evaluation conditions only (``seed`` < 20,000,000: not the
    calibration or ceiling sets), per policy and per task (``bussing`` = in distribution)."""
    p = Path(path) if path is not None else default_zoo_real()
    p = p.parent if p.name in ("results.jsonl", "results.jsonl.gz") else p
    # a store's records, or an archived store's gzipped ones (results.py's layout, read without the evaluate layer)
    f = next((p / n for n in ("results.jsonl", "results.jsonl.gz") if (p / n).exists()), None)
    if f is None:
        raise FileNotFoundError(f"{p}: no sweep results store there")
    policies: dict[str, dict] = {}
    tasks: dict[str, dict] = {}
    seeds: set[int] = set()
    for r in atomic.read_jsonl(f, "a rollout record", "restore the file"):
        if r.get("mode") != "real" or int(r["seed"]) >= 20_000_000:
            continue
        c = outcome_counts(r["objects"])
        c["episodes"] = 1
        _add(policies.setdefault(r["policy"], {"task": r["task"]}), c)
        _add(tasks.setdefault(r["task"], {}), c)
        seeds.add(int(r["seed"]))
    return {"path": str(p), "conditions": len(seeds), "policies": policies, "tasks": tasks}

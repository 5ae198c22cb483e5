"""Demonstration generator: scripted-expert episodes of *bussing* written in the training pipeline's episode format.

Each episode: 3 views (left, right, wrist) uint8 [T, H, W, 3], actions [T, 7] (delta EE), ee_pose [T, 7], the
prompt, and in ``meta``: ``labels`` (per-object ground-truth criteria and outcome category), ``initial_condition``,
``knobs``, ``sim_seed`` and ``intent`` (per-step expert intent, used to train the policy zoo).

Deterministic by seed: episode ``i`` of a run with ``seed`` uses simulator seed ``seed * 100_000 + i`` and is named
``ep{sim_seed:07d}``. Resumable: episodes already in the store are skipped. Reverse bussing is refused here: it
never enters world-model training data.

``policy=NAME`` records a *bussing* zoo policy instead of the expert (its retries, hovering and misses: the
on-policy failures a world model must reproduce, which the expert's failure knobs only approximate). Use training
seeds only: the sweep evaluates on simulator seeds from 10,000,000 (``SweepConfig.seed0``), far above
``seed * 100_000 + i`` for any seed < 100.
"""
from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from sc3_jax.data.episodes import Episode, EpisodeStore
from .criteria import success_rates
from .env import BussingEnv
from .expert import ExpertKnobs, run_expert_episode


def episode_seed(seed: int, i: int) -> int:
    return int(seed) * 100_000 + int(i)


def generate_demos(out: str | Path, n_episodes: int, seed: int = 0, knobs: ExpertKnobs = ExpertKnobs(),
                   image_size: tuple[int, int] = (64, 64), control_hz: int = 20, n_objects: int = 3,
                   task: str = "bussing", progress: bool = True, policy: str | None = None) -> dict:
    """Write ``n_episodes`` expert (or zoo ``policy``) episodes to the episode store at ``out``. Returns a summary."""
    if task != "bussing":
        raise ValueError("demonstrations cover bussing only (reverse bussing never enters training data)")
    if policy is not None:
        from .zoo import ZOO
        if policy not in ZOO or ZOO[policy].task != "bussing":
            raise ValueError(f"policy {policy!r}: choose a bussing zoo policy "
                             f"{sorted(n for n, e in ZOO.items() if e.task == 'bussing')}")
    runner = _expert_runner(knobs) if policy is None else _policy_runner(policy)
    source = {"knobs": dataclasses.asdict(knobs)} if policy is None else {"policy": policy}
    return write_episodes(out, n_episodes, seed, runner, source, task, image_size, control_hz, n_objects, progress)


def write_episodes(out: str | Path, n_episodes: int, seed: int, runner, source: dict, task: str,
                   image_size: tuple[int, int] = (64, 64), control_hz: int = 20, n_objects: int = 3,
                   progress: bool = True) -> dict:
    """The store writer behind ``generate_demos`` (no task check: the zoo's reverse-bussing training demos use it
    directly; world-model data goes through ``generate_demos``, which refuses reverse bussing)."""
    env = BussingEnv(image_size=image_size, control_hz=control_hz, n_objects=n_objects)
    store = EpisodeStore(out, views=list(env.views), fps=control_hz, image_size=tuple(image_size), create=True)
    outcomes, written, skipped, steps = [], 0, 0, 0
    t0 = time.time()
    for i in tqdm(range(n_episodes), desc="demos", disable=not progress):
        sim_seed = episode_seed(seed, i)
        eid = f"ep{sim_seed:07d}"
        if eid in store:
            skipped += 1
            continue
        r = runner(env, sim_seed, task)
        store.write(Episode(eid, r.frames, r.actions, r.ee_pose, r.ic.prompt,
                            episode_meta(r, task, sim_seed, source, control_hz)))
        outcomes += r.outcomes
        written += 1
        steps += r.length
    env.close()
    dt = time.time() - t0
    return {"out": str(out), "written": written, "skipped": skipped, "steps": steps, "seconds": dt,
            "demos_per_hour": written / dt * 3600 if written and dt > 0 else None,
            "success": success_rates(outcomes) if outcomes else None}


def episode_meta(r, task: str, sim_seed: int, source: dict, control_hz: int) -> dict:
    """An episode's ``meta``: what generated it (``source``), its initial condition, ground-truth labels, the expert's
    intent (expert episodes) and the objects' positions per frame."""
    return {"task": task, "sim_seed": sim_seed, **source,
            "initial_condition": r.ic.to_json(), "control_hz": control_hz,
            "labels": {"objects": [o.to_json() for o in r.outcomes],
                       "success": success_rates(r.outcomes)},
            "intent": {k: np.round(v, 5).tolist() for k, v in (r.intents or {}).items()},
            "object_pos": np.round(r.object_pos, 4).tolist()}


def _expert_runner(knobs: ExpertKnobs):
    return lambda env, seed, task: run_expert_episode(env, seed, task, knobs, record=True)


def _policy_runner(name: str):
    from sc3_jax.policies.base import as_host
    from .policy_eval import run_policy_episode
    from .zoo import load_policy
    host = as_host(load_policy(name))  # jitted once, reused for every episode
    return lambda env, seed, task: run_policy_episode(env, host, seed, task, record=True)


def store_contents(*roots: str | Path) -> dict:
    """What an episode store holds, read from each episode's ``meta.json`` (no frames loaded): episodes per task and
    per source (a mixture's data-collection source, expert knobs or zoo policy), and how many of each episode's
    objects were carried into the *other* container (ground-truth language failures). An episode with every object
    in the other container is a reverse-bussing episode in all but name; ``all_objects_swapped`` counts them."""
    import collections
    import json
    tasks, sources, swapped, n_obj = collections.Counter(), collections.Counter(), collections.Counter(), 0
    all_swapped: list[str] = []
    for root in roots:
        for d in sorted(Path(root).iterdir()):
            if not (d / "meta.json").exists():
                continue
            m = json.loads((d / "meta.json").read_text())
            tasks[m.get("task", "?")] += 1
            src = m.get("source") or m.get("policy") or ",".join(
                f"{k}={v}" for k, v in sorted((m.get("knobs") or {}).items()) if v and k != "never_swap_all"
            ) or "clean expert"
            sources[src] += 1
            objs = m["labels"]["objects"]
            w = sum(not o["language"] for o in objs)
            swapped[f"{w} of {len(objs)}"] += 1
            n_obj += len(objs)
            if objs and w == len(objs):
                all_swapped.append(d.name)
    return {"episodes": sum(tasks.values()), "objects": n_obj, "tasks": dict(tasks), "sources": dict(sources),
            "objects_in_other_container": dict(sorted(swapped.items())), "all_objects_swapped": len(all_swapped),
            "all_objects_swapped_episodes": all_swapped}

"""Run a policy in the simulator ("real" rollouts) and score it with the physics ground truth.

A policy (``JaxPolicy`` or any host policy with ``infer(obs)``) gets ``{"images": uint8 [3, H, W, 3], "state": [7],
"task": int32}`` and returns a chunk of 25 raw delta-EE actions; the first ``execute`` (16) are applied at 20 Hz,
then the policy re-observes. An episode ends after 20 s (400 control steps) or once every object has come to rest
in a container or off the table with the gripper empty (``SETTLE_STEPS`` steps in a row).

Evaluation initial conditions use simulator seeds ``EVAL_SEED0 + i`` (disjoint from demonstration seeds).
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import jax
import numpy as np

from sc3_jax.core import atomic
from sc3_jax.policies.base import JaxAsHost, JaxPolicy, as_host
from sc3_jax.core.video import write_mp4
from .criteria import ObjectOutcome, inside_container, success_rates
from .env import BussingEnv
from .expert import MAX_STEPS_20HZ, EpisodeResult, finish

EVAL_SEED0 = 10_000_000
EXECUTE = 16
SETTLE_STEPS = 20


def make_env(image_size: tuple[int, int] = (64, 64), control_hz: int = 20, n_objects: int = 3,
             render: bool = True) -> BussingEnv:
    return BussingEnv(image_size=image_size, control_hz=control_hz, n_objects=n_objects, render=render)


def _all_settled(env: BussingEnv) -> bool:
    if env.held is not None:
        return False
    for n in env.ic.objects:
        p = env.object_pos(n)
        placed = any(bool(inside_container(p, env.container_xy(c), c)) for c in ("bin", "can"))
        if not (placed or p[2] < -0.05) or env.object_speed(n) > 0.05:
            return False
    return True


def run_policy_episode(env: BussingEnv, policy, seed: int, task: str = "bussing", execute: int = EXECUTE,
                       max_steps: int | None = None, record: bool = True) -> EpisodeResult:
    """Closed-loop rollout of ``policy`` from initial condition ``(seed, task)``. Deterministic: a JaxPolicy's rng
    is ``fold_in(key(0), seed)``, split once per chunk. ``policy``: a JaxPolicy (jitted via ``as_host``) or a host
    policy."""
    host = as_host(policy) if isinstance(policy, JaxPolicy) else policy
    if isinstance(host, JaxAsHost):
        # the policy's per-chunk draws come from a key of this initial condition: an episode's result does not
        # depend on which episodes ran before it with the same host
        host._rng = jax.random.fold_in(jax.random.key(0), seed)
    max_steps = max_steps or MAX_STEPS_20HZ * env.control_hz // 20
    env.reset(seed, task)
    frames = {v: [] for v in env.views} if record else None
    actions, poses, traj = [], [], [env.object_positions()]
    chunk, k, settled = None, 0, 0
    for t in range(max_steps):
        need_obs = chunk is None or k >= execute
        f = env.render() if (record or need_obs) else None
        if record:
            for v in env.views:
                frames[v].append(f[v])
        pose = env.ee_pose()
        poses.append(pose)
        if need_obs:
            obs = {"images": np.stack([f[v] for v in env.views]), "state": pose, "task": np.int32(env.task_id)}
            chunk, k = np.asarray(host.infer(obs), np.float32), 0
        a = chunk[k]
        k += 1
        actions.append(a)
        env.step(a)
        traj.append(env.object_positions())
        settled = settled + 1 if _all_settled(env) else 0
        if settled >= SETTLE_STEPS:
            break
    return EpisodeResult(env.ic, {v: np.stack(x) for v, x in frames.items()} if record else None,
                         np.stack(actions), np.stack(poses), finish(env, traj), None,
                         np.stack(traj).astype(np.float32))


def evaluate_policy(policy, task: str = "bussing", episodes: int = 36, out: str | Path | None = None,
                    seed0: int = EVAL_SEED0, image_size: tuple[int, int] = (64, 64), videos: bool = True,
                    progress: bool = True) -> dict:
    """Evaluate ``policy`` (a JaxPolicy or a host policy; ``commands/sim.py`` resolves names, so the simulator never
    imports ``policies/resolve.py``, which imports the zoo) on ``episodes`` initial conditions.

    Writes (if ``out``): ``episodes.jsonl`` (per-episode, per-object outcomes), ``summary.json`` (per-criterion
    success rates and outcome distribution), ``videos/ep<seed>_<view>.mp4`` (every view, if ``videos``)."""
    from tqdm import tqdm
    name = getattr(policy, "name", type(policy).__name__)
    env = make_env(image_size)
    out = Path(out) if out is not None else None
    if out is not None:
        (out / "videos").mkdir(parents=True, exist_ok=True)
    rows, all_outcomes = [], []
    t0 = time.time()
    host = as_host(policy) if isinstance(policy, JaxPolicy) else policy
    for i in tqdm(range(episodes), desc=f"eval {name}/{task}", disable=not progress):
        seed = seed0 + i
        r = run_policy_episode(env, host, seed, task, record=videos and out is not None)
        all_outcomes += r.outcomes
        row = {"episode": i, "seed": seed, "task": task, "prompt": r.ic.prompt, "length": r.length,
               "objects": [o.to_json() for o in r.outcomes]}
        rows.append(row)
        if out is not None and r.frames is not None:
            for v, fr in r.frames.items():
                write_mp4(out / "videos" / f"ep{seed}_{v}.mp4", fr, env.control_hz)
    env.close()
    summary = {"policy": name, "task": task, "episodes": episodes, "seed0": seed0,
               "success": success_rates(all_outcomes), "seconds": time.time() - t0}
    if out is not None:
        # summary.json last: evaluate_zoo reads a policy with one as done
        atomic.write_text(out / "episodes.jsonl", "".join(json.dumps(row) + "\n" for row in rows))
        atomic.write_json(out / "summary.json", summary)
    return summary


def evaluate_zoo(out: str | Path, episodes: int = 36, videos: bool = True, names: list[str] | None = None,
                 progress: bool = True) -> str:
    """Evaluate every zoo policy (or ``names``) on its own task; write ``out/<name>/...`` and ``out/zoo_table.md``;
    return the markdown table (per-criterion success rates over all objects of ``episodes`` initial conditions,
    then each criterion's spread per task). Resumable: a policy whose ``summary.json`` in ``out`` has the same
    number of episodes is read back, not re-run."""
    from .zoo import ZOO, load_policy
    out = Path(out)
    rows, rates = [], {}
    for name in names or list(ZOO):
        done = out / name / "summary.json"
        s = atomic.read_json(done, "delete it (this policy is then evaluated again)") if done.exists() else None
        if s is None or s.get("episodes") != episodes:
            s = evaluate_policy(load_policy(name), ZOO[name].task, episodes, out / name, videos=videos,
                                progress=progress)
        r = s["success"]
        rates.setdefault(ZOO[name].task, []).append(r)
        rows.append(f"| {name} | {ZOO[name].task} | {r['language']:.2f} | {r['lifting']:.2f} | {r['placing']:.2f} | "
                    f"{r['outcome/language']:.2f} / {r['outcome/lifting']:.2f} / {r['outcome/placing']:.2f} / "
                    f"{r['outcome/no failure']:.2f} | {r['n_objects']} | {s['seconds']:.0f} | {ZOO[name].recipe} |")
    table = ("| policy | task | language | lifting | placing | outcomes (lang / lift / place / none) | objects | "
             "seconds | estimator and knobs |\n|---|---|---|---|---|---|---|---|---|\n" + "\n".join(rows) + "\n")
    spread = ["", "| task | policies | language spread | lifting spread | placing spread |", "|---|---|---|---|---|"]
    for task, rs in rates.items():
        sp = [max(r[c] for r in rs) - min(r[c] for r in rs) for c in ("language", "lifting", "placing")]
        spread.append(f"| {task} | {len(rs)} | " + " | ".join(f"{v:.2f}" for v in sp) + " |")
    table += "\n".join(spread) + "\n"
    atomic.write_text(out / "zoo_table.md", table)
    return table


__all__ = ["evaluate_zoo", "make_env", "run_policy_episode", "evaluate_policy", "ObjectOutcome"]

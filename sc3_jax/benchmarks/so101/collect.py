"""Collect SO-101 episodes of the scripted controller as LeRobot v3.0 datasets: ``OUT/train`` and ``OUT/heldout``.

Each episode's controller recipe is drawn uniformly from ``controllers.MIX`` (clean, action noise 0.20 and 0.30,
block error 2 and 4 cm): about half the episodes fail, in several ways (missed grasps, drops, misplacements), which
is what a world model judging policies must see. Episode ``i`` of the training split uses simulator seed
``seed * 100_000 + i``, held-out episode ``j`` seed ``10_000_000 + seed * 100_000 + j`` (disjoint for seed < 100); the
recipe is drawn from the simulator seed, the controller's draws from (``seed``, simulator seed). An episode is recorded
until the simulator ends it (success, or the block out of the workspace) or for ``max_steps`` (150 = 15 s); a failed
episode usually runs them all, the controller nearly idle once its script is done.

Features: ``observation.images.<view>`` (a video per camera: ``workspace`` and ``wrist`` unless told), ``observation.state`` (agent_pos [14]),
``observation.environment_state`` (block xyz, goal xyz [6]), ``action`` [4] (dx, dy, dz, gripper), ``next.success``
(bool [1]); fps 10, robot_type ``so101``, one task. ``meta/info.json`` declares the action space
(``sc3_action_space``: velocity, the gripper a position target), so ``sc3 data import-lerobot --data OUT/train --out
STORE`` needs no other flag. ``OUT/collect.json`` lists every episode's seed, recipe, outcome and length.
"""
from __future__ import annotations

import collections
import itertools
import time
from pathlib import Path

import numpy as np

from sc3_jax.core import atomic
from sc3_jax.core.errors import UserError
from .controllers import MIX, RECIPES
from .env import (ACTION_NAMES, ACTION_SCALE, ENV_ID, ENV_STATE_NAMES, STATE_NAMES, VIEWS, check_views,
                  import_simulator)
from .rollouts import MAX_STEPS, EpisodeRecord, Job, Setup, run_episodes

TASK = "pick the block and place it on the goal"
FPS = 10
ROBOT_TYPE = "so101"
CAMERA = "observation.images."  # + the view's name
HELDOUT_SEED0 = 10_000_000
RECIPE_STREAM = 101  # the recipe draw's own stream, apart from the controller's draws
SPLITS = ("train", "heldout")


def episode_seed(seed: int, i: int) -> int:
    return int(seed) * 100_000 + int(i)


def heldout_seed(seed: int, j: int) -> int:
    return HELDOUT_SEED0 + episode_seed(seed, j)


def recipe_of(sim_seed: int) -> str:
    """The controller recipe of an episode, drawn uniformly from its simulator seed."""
    return MIX[int(np.random.default_rng([RECIPE_STREAM, int(sim_seed)]).integers(len(MIX)))]


def action_space() -> dict:
    """The ``sc3_action_space`` declaration: dx, dy, dz commanded displacements (rates, ``ACTION_SCALE`` m per unit
    per step), the gripper an absolute target."""
    from sc3_jax.data.action_space import ActionSpace

    return ActionSpace("velocity", 4, tuple(ACTION_NAMES), (3,)).to_dict()


def to_raw(r: EpisodeRecord, views: tuple[str, ...]):
    from sc3_jax.data.lerobot_write import RawEpisode

    return RawEpisode({CAMERA + v: r.frames[:, i] for i, v in enumerate(views)}, r.actions, TASK, r.states,
                      {"observation.environment_state": r.env_state, "next.success": r.success[:, None]})


NAMES = {"action": ACTION_NAMES, "observation.state": STATE_NAMES, "observation.environment_state": ENV_STATE_NAMES,
         "next.success": ["success"]}


def collect(out: str | Path, episodes: int, heldout: int = 0, seed: int = 0, image_size: tuple[int, int] = (80, 80),
            max_steps: int = MAX_STEPS, workers: int = 1, progress: bool = True,
            views: tuple[str, ...] = VIEWS, image_dtype: str = "video") -> dict:
    """Write ``OUT/train`` (``episodes``) and ``OUT/heldout`` (``heldout``, if any) and ``OUT/collect.json``.
    ``image_dtype``: "video" (h264, PyAV) or "image" (lossless PNG in the parquet: cv2 and pyarrow, no PyAV).
    Returns the summary written there."""
    from tqdm import tqdm

    from sc3_jax.data.lerobot import INFO_ACTION_SPACE
    from sc3_jax.data.lerobot_write import write_lerobot

    out = Path(out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise UserError(f"--out {out} exists and is not empty: choose a new directory, or delete it (a collection "
                        "is not resumed: an interrupted one starts again)")
    if not 0 <= seed < 100:
        raise UserError(f"--seed {seed}: use 0-99 (simulator seeds seed*100000+i stay apart from the held-out ones)")
    if episodes < 1 or heldout < 0 or episodes + heldout > 100_000:
        raise UserError(f"--episodes {episodes} --heldout {heldout}: at least 1 training episode, and at most "
                        "100000 in all")
    if max_steps < 2 or any(s % 2 for s in image_size):
        raise UserError(f"--max-steps {max_steps} --image-size {image_size[0]} {image_size[1]}: at least 2 steps, "
                        "even image sizes (the videos are yuv420p)")
    check_views(views)  # a camera we do not render: one line now, before --out is made
    import_simulator()  # a missing extra: one line now, not from a worker
    seeds = {"train": [episode_seed(seed, i) for i in range(episodes)],
             "heldout": [heldout_seed(seed, j) for j in range(heldout)]}
    jobs = [Job(s, recipe_of(s), controller_seed=seed) for split in SPLITS for s in seeds[split]]
    t0 = time.time()
    setup = Setup(tuple(image_size), tuple(views), max_steps)
    records = iter(tqdm(run_episodes(jobs, setup, workers), total=len(jobs),
                        desc="so101 episodes", disable=not progress))  # one iterator, the splits take their share
    rows: dict[str, list[dict]] = {s: [] for s in SPLITS}

    def split_episodes(split: str):
        for i, r in enumerate(itertools.islice(records, len(seeds[split]))):
            rows[split].append({"episode_index": i, "sim_seed": r.seed, "recipe": r.source,
                                "succeeded": r.succeeded, "steps": r.steps})
            yield to_raw(r, tuple(views))

    summary = {"env": ENV_ID, "seed": seed, "image_size": list(image_size), "views": list(views), "max_steps": max_steps, "fps": FPS,
               "recipes": list(MIX), "splits": {}}
    for split in SPLITS:
        if not seeds[split]:
            continue
        info = {INFO_ACTION_SPACE: action_space(),
                "sc3_so101": {"env": ENV_ID, "split": split, "seed": seed, "action_scale_m": ACTION_SCALE}}
        write_lerobot(out / split, split_episodes(split), FPS, names=NAMES, robot_type=ROBOT_TYPE, info=info,
                      image_dtype=image_dtype)
        summary["splits"][split] = {"path": str(out / split), **_rates(rows[split]), "episodes": rows[split]}
    summary["seconds"] = round(time.time() - t0, 1)
    atomic.write_json(out / "collect.json", summary, indent=1)
    return summary


def horizon_seconds(rows: list[dict], quantile: float = 0.9, chunk_s: float = 1.0) -> float | None:
    """The task's horizon from its episodes' success times: the ``quantile`` of the successful episodes' lengths
    plus one policy chunk, in whole chunks (seconds at ``FPS``); None without a success. A rollout longer than the
    task only gives a fading model time to fool a scorer; shorter would cut real successes."""
    done = [r["steps"] for r in rows if r["succeeded"]]
    if not done:
        return None
    return float(chunk_s * np.ceil((np.quantile(done, quantile) / FPS + chunk_s) / chunk_s))


def _rates(rows: list[dict]) -> dict:
    by = collections.defaultdict(list)
    for r in rows:
        by[r["recipe"]].append(r["succeeded"])
    return {"n": len(rows), "success_rate": float(np.mean([r["succeeded"] for r in rows])),
            "frames": int(sum(r["steps"] for r in rows)), "horizon_seconds": horizon_seconds(rows),
            "per_recipe": {k: {"n": len(v), "success_rate": float(np.mean(v))} for k, v in sorted(by.items())}}


def measure_controllers(episodes: int = 30, seed: int = 0, max_steps: int = MAX_STEPS, workers: int = 1,
                        progress: bool = True) -> list[dict]:
    """Every recipe on the same ``episodes`` training seeds, no rendering: [{recipe, knobs, success_rate, ...}]."""
    from tqdm import tqdm

    import_simulator()
    jobs = [Job(episode_seed(seed, i), r.name, controller_seed=seed) for r in RECIPES for i in range(episodes)]
    it = run_episodes(jobs, Setup(record=False, max_steps=max_steps), workers)
    recs = list(tqdm(it, total=len(jobs), desc="so101 controllers", disable=not progress))
    out = []
    for k, r in enumerate(RECIPES):
        mine = recs[k * episodes:(k + 1) * episodes]
        ok = [x.steps for x in mine if x.succeeded]
        out.append({"recipe": r.name, "action_noise": r.action_noise, "block_error": r.block_error,
                    "episodes": episodes, "success_rate": len(ok) / episodes,
                    "mean_steps_to_success": float(np.mean(ok)) if ok else None})
    return out

"""``sc3 so101 SUBCOMMAND ...``: the SO-101 pick-and-place benchmark in the simulator lerobot-env-so101 (docs/so101.md).

    sc3 so101 collect --out DIR --episodes N [--heldout M] [--seed S] [--image-size H W]   LeRobot v3.0 datasets
    sc3 so101 controllers [--episodes 30]                                                  the controllers' table
    sc3 so101 zoo-train --data DIR/train [--heldout DIR/heldout]                           the zoo's estimators
    sc3 so101 zoo-eval [--episodes 36] [--policies NAME ...]                               the zoo's real rates
"""
from __future__ import annotations

import dataclasses
import json
from typing import Annotated, Literal

import tyro

from sc3_jax.commands import run_group

SUMMARY = "the SO-101 pick-and-place benchmark (simulator lerobot-env-so101)"  # the line `sc3 --help` shows


@dataclasses.dataclass(frozen=True)
class Collect:
    """Write scripted SO-101 episodes (perturbed controllers) as LeRobot v3.0 datasets OUT/train and OUT/heldout."""

    out: str
    """new (or empty) directory for the datasets OUT/train and OUT/heldout and the episode list OUT/collect.json"""
    episodes: int = 100
    """training episodes (episode i: simulator seed SEED*100000+i)"""
    heldout: int = 20
    """held-out episodes, written as a second dataset (episode j: simulator seed 10000000+SEED*100000+j)"""
    seed: int = 0
    """collection seed, 0-99: simulator seeds, recipes and the controllers' draws follow from it"""
    image_size: Annotated[tuple[int, int], tyro.conf.arg(metavar="H W")] = (80, 80)
    """every camera's height and width (even)"""
    views: tuple[str, ...] | None = None
    """cameras to record: workspace (arm, block and goal fill the frame), wrist (follows the gripper), front (the
    simulator's whole-room view); None: the benchmark's (sc3_jax/benchmarks/so101/env.py VIEWS: workspace wrist)"""
    image_dtype: Literal["video", "image"] = "video"
    """how frames are stored: video (h264 mp4 files, needs PyAV) or image (lossless PNG inside the parquet files:
    no PyAV, larger)"""
    max_steps: int = 150
    """steps (at 10 Hz) after which an episode that has not succeeded is cut"""
    workers: int = 1
    """processes simulating at once (the datasets do not depend on it)"""
    progress: bool = True
    """progress bar"""


@dataclasses.dataclass(frozen=True)
class Controllers:
    """Measure every controller recipe's success rate on the same seeds (docs/results.md, "SO-101")."""

    episodes: int = 30
    """episodes per recipe (simulator seeds SEED*100000+i, shared by the recipes)"""
    seed: int = 0
    """measurement seed, 0-99"""
    max_steps: int = 150
    """steps (at 10 Hz) after which an episode that has not succeeded counts as failed"""
    workers: int = 1
    """processes simulating at once (the rates do not depend on it)"""


@dataclasses.dataclass(frozen=True)
class ZooTrain:
    """Train the zoo's estimators on a collected dataset (frames labelled by its observation.environment_state)."""

    data: tuple[str, ...]
    """LeRobot datasets to train on (`sc3 so101 collect`'s OUT/train; several: the same share of each)"""
    heldout: str | None = None
    """LeRobot dataset the estimators' errors are measured on (OUT/heldout)"""
    out: str | None = None
    """where the weights and zoo.json go (None: the package's sc3_jax/benchmarks/so101/zoo, which the zoo loads)"""


@dataclasses.dataclass(frozen=True)
class ZooEval:
    """Every zoo policy's real success rate in the simulator, on the same seeds (docs/results.md, "SO-101")."""

    episodes: int = 36
    """episodes per policy (simulator seeds 20000000+i: neither the collection's training nor held-out seeds)"""
    policies: tuple[str, ...] = ()
    """the policies (none named: the whole zoo); any spelling `sc3 sweep` takes"""
    max_steps: int = 120
    """steps (at 10 Hz) after which an episode that has not succeeded counts as failed"""
    workers: int = 1
    """processes simulating at once (the rates do not depend on it)"""


SUBCOMMANDS: dict[str, type] = {"collect": Collect, "controllers": Controllers, "zoo-train": ZooTrain,
                                "zoo-eval": ZooEval}


def main(argv: list[str]) -> int:
    return run_group("so101", "The SO-101 pick-and-place benchmark (docs/so101.md).", SUBCOMMANDS, _RUN, argv)


def _collect(a: Collect) -> int:
    from sc3_jax.benchmarks.so101.collect import collect
    from sc3_jax.benchmarks.so101.env import VIEWS

    s = collect(a.out, a.episodes, a.heldout, a.seed, a.image_size, a.max_steps, a.workers, a.progress,
                VIEWS if a.views is None else a.views, a.image_dtype)
    for split, d in s["splits"].items():
        recipes = ", ".join(f"{k} {v['success_rate']:.2f} of {v['n']}" for k, v in d["per_recipe"].items())
        print(f"{split}: {d['n']} episodes, {d['frames']} frames, success rate {d['success_rate']:.2f} "
              f"({recipes}); the task's horizon: {d['horizon_seconds']} s (90% of successes + a chunk) -> "
              f"{d['path']}")
    print(f"episode list: {a.out}/collect.json ({s['seconds']:.0f} s). Import (the action space is declared in "
          f"info.json): sc3 data import-lerobot --data {a.out}/train --out STORE"
          + (f"; sc3 data import-lerobot --data {a.out}/heldout --out HELDOUT_STORE" if "heldout" in s["splits"]
             else ""))
    return 0


def _controllers(a: Controllers) -> int:
    from sc3_jax.benchmarks.so101.collect import measure_controllers
    from sc3_jax.core.errors import UserError

    if a.episodes < 1 or not 0 <= a.seed < 100:
        raise UserError(f"--episodes {a.episodes} --seed {a.seed}: at least 1 episode, a seed of 0-99")
    rows = measure_controllers(a.episodes, a.seed, a.max_steps, a.workers)
    print(json.dumps(rows, indent=1))
    print("\n| recipe | action noise | block error (m) | success rate | mean steps to success |\n|---|---|---|---|---|")
    for r in rows:
        steps = "-" if r["mean_steps_to_success"] is None else f"{r['mean_steps_to_success']:.0f}"
        print(f"| {r['recipe']} | {r['action_noise']:.2f} | {r['block_error']:.2f} | {r['success_rate']:.2f} | "
              f"{steps} |")
    first = a.seed * 100_000
    print(f"\neach recipe on the same {a.episodes} simulator seeds {first}-{first + a.episodes - 1}, at most "
          f"{a.max_steps} steps (10 Hz), no rendering")
    return 0


def _zoo_train(a: ZooTrain) -> int:
    from sc3_jax.benchmarks.so101.zoo import ZOO_DIR
    from sc3_jax.benchmarks.so101.zoo_train import train_zoo

    from sc3_jax.core.errors import UserError

    out = a.out or ZOO_DIR
    try:
        s = train_zoo(list(a.data), a.heldout, out)
    except ValueError as e:  # a dataset that is not one (LeRobotError), or of another robot: one line
        raise UserError(str(e)) from None
    print(json.dumps(s, indent=1))
    print(f"weights and zoo.json: {out}")
    return 0


EVAL_SEED0 = 20_000_000  # zoo-eval's simulator seeds: apart from collect's (SEED*100000+i, 10000000+SEED*100000+j)


def _zoo_eval(a: ZooEval) -> int:
    import time

    import numpy as np
    from tqdm import tqdm

    from sc3_jax.benchmarks.so101.rollouts import Job, Setup, run_episodes
    from sc3_jax.benchmarks.so101.zoo import ZOO

    from sc3_jax.benchmarks.so101.zoo import named_policy
    from sc3_jax.core.errors import UserError
    from sc3_jax.policies.resolve import resolve

    names = list(a.policies or ZOO)
    for n in names:  # a wrong name: one line here, not a traceback from a worker
        try:
            resolve(n, named=named_policy)
        except (ValueError, KeyError, FileNotFoundError, ConnectionError, TimeoutError) as e:  # a server not there
            raise UserError(f"--policies {n}: {e}") from None
    jobs = [Job(EVAL_SEED0 + i, policy=n) for n in names for i in range(a.episodes)]
    t0, ok = time.time(), {n: [] for n in names}
    for job, r in zip(jobs, tqdm(run_episodes(jobs, Setup(max_steps=a.max_steps, record=False), a.workers),
                                  total=len(jobs), desc="zoo-eval", unit="episode")):
        ok[job.policy].append(r.succeeded)
    print("| policy | success rate | episodes |\n|---|---|---|")
    for n in names:
        print(f"| {n} | {np.mean(ok[n]):.2f} | {len(ok[n])} |")
    rates = [np.mean(v) for v in ok.values()]
    print(f"spread {max(rates) - min(rates):.2f}; simulator seeds {EVAL_SEED0}-{EVAL_SEED0 + a.episodes - 1}, at most "
          f"{a.max_steps} steps; {time.time() - t0:.0f} s")
    return 0


_RUN = {"collect": _collect, "controllers": _controllers, "zoo-train": _zoo_train, "zoo-eval": _zoo_eval}

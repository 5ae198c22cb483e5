"""``sc3 sim SUBCOMMAND ...``: the simulated table-bussing benchmark (docs/sim.md).

    sc3 sim demos --out DIR --episodes N [--seed S] [knobs] [--policy NAME]   expert / zoo demonstrations
    sc3 sim mixture --out DIR --episodes N [--recipe failure_rich] [--workers 16]   failure-rich world-model data
    sc3 sim demos-stats --data DIR [DIR ...] [--zoo-real STORE]               what demo stores hold, vs the zoo
    sc3 sim eval --policy NAME --task bussing|reverse --episodes 36 [--out DIR]
    sc3 sim zoo-train [--workdir /tmp/sc3_zoo] [--runs clean small reverse]   the zoo's demos and weights
    sc3 sim zoo-eval --out DIR [--episodes 36] [--policies NAME ...]          every zoo policy, the table
    sc3 sim zoo-list | zoo-manifest                                           the registry; rewrite zoo.json
    sc3 sim measure [--episodes 20]                                           render speed, pixels, expert rates
"""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Annotated, Literal

import tyro

from sc3_jax.commands import run_group
from sc3_jax.core.errors import UserError

SUMMARY = "the simulated table-bussing benchmark"  # the line `sc3 --help` shows
# the line Ctrl-C ends with (cli.py; every writer is atomic)
RESUME = "the same command resumes it where it writes a store (finished parts are kept)"

SIZE = tyro.conf.arg(metavar="H W")


@dataclasses.dataclass(frozen=True, kw_only=True)
class Scene:
    """What every episode writer renders (the options `demos` and `mixture` share)."""

    image_size: Annotated[tuple[int, int], SIZE] = (64, 64)
    """rendered views' height and width"""
    control_hz: Literal[10, 20] | None = None
    """control (and frame) rate (None: the simulator's own, benchmarks/bussing/env.py CONTROL_HZ, 20)"""
    n_objects: int = 3
    """objects on the table per episode"""


@dataclasses.dataclass(frozen=True, kw_only=True)
class Demos(Scene):
    """Write scripted-expert (or zoo-policy) bussing demonstrations to an episode store; resumable."""

    out: str
    """episode store to write (created if missing; episodes already in it are skipped)"""
    episodes: int = 100
    """episodes to write"""
    seed: int = 0
    """episode i uses simulator seed SEED*100000+i; keep below 100 (the sweep evaluates from seed 10,000,000)"""
    grasp_noise: float = 0.0
    """expert knob: grasp aim error in metres (lifting failures)"""
    release_noise: float = 0.0
    """expert knob: release point error in metres (placing failures)"""
    wrong_destination_prob: float = 0.0
    """expert knob: probability that an object goes to the other container (language failures)"""
    action_noise: float = 0.0
    """expert knob: Gaussian noise on every action, in metres"""
    policy: str | None = None
    """record this bussing zoo policy (`sc3 sim zoo-list`) instead of the scripted expert"""
    allow_swap_all: bool = False
    """let --wrong-destination-prob swap every object of an episode (reverse bussing, kept out of world-model data)"""


@dataclasses.dataclass(frozen=True, kw_only=True)
class Mixture(Scene):
    """Write failure-rich world-model data: data-collection policies (not the zoo) mixed with clean expert demos."""

    out: str
    """episode store to write (created if missing; episodes already in it are skipped)"""
    episodes: int = 1000
    """episodes in the mixture (episode i uses simulator seed SEED*100000+i; its source is drawn from (SEED, i))"""
    seed: int = 40
    """mixture seed, below 100 (40: disjoint from every demo, held-out and scorer seed of docs/sim.md)"""
    recipe: Literal["failure_rich", "clean"] = "failure_rich"
    """weights of the sources (benchmarks/bussing/mixture.py RECIPES): failure_rich = a quarter each of the clean expert, the noisy
    expert, the expert with retries / drops / one wrong container, and the chunk controller on noisy state;
    clean = the clean expert only"""
    workers: int = 1
    """processes writing at once (each its share of the episodes; records do not depend on it)"""
    seconds: float | None = None
    """start no episode after this many seconds (None: write them all); rerun to go on"""
    shard: str | None = None
    """write only the share I/N of the episodes (i = I mod N), e.g. one machine of several (None: all)"""
    progress: bool = True
    """progress bar (one process only)"""


@dataclasses.dataclass(frozen=True)
class DemosStats:
    """What demo stores hold: tasks, sources, per-object outcomes against the zoo's real ones (meta.json only)."""

    data: tuple[str, ...]
    """episode stores (`sc3 sim demos|mixture --out` directories), counted together"""
    zoo_real: str | None = "docs/stores/sweep72_gpu"
    """a sweep results store whose real rollouts give the zoo's measured outcome mix to compare with (relative
    paths: from the repository root if not found here; None: no comparison)"""


@dataclasses.dataclass(frozen=True)
class Eval:
    """Evaluate one policy in the simulator: per-criterion success rates over its episodes."""

    policy: str
    """a zoo name (`sc3 sim zoo-list`), module:factory, or another spelling of policies/resolve.py"""
    task: Literal["bussing", "reverse"] = "bussing"
    """the task the policy is evaluated on"""
    episodes: int = 36
    """initial conditions (simulator seeds from 10,000,000, as in the sweep)"""
    out: str | None = None
    """directory for summary.json, episodes.jsonl and videos/ (None: nothing written)"""
    videos: bool = True
    """write every view of every episode as mp4 under OUT/videos (--no-videos: skip them)"""
    image_size: Annotated[tuple[int, int], SIZE] = (64, 64)
    """rendered views' height and width"""


@dataclasses.dataclass(frozen=True)
class ZooTrain:
    """Regenerate the zoo's demo sets and train its estimators' weights (minutes to an hour on a CPU)."""

    workdir: str = "/tmp/sc3_zoo"
    """where the training demo sets are written (resumable)"""
    out: str | None = None
    """where the weights and zoo.json go (None: the shipped sc3_jax/benchmarks/bussing/zoo/)"""
    runs: tuple[str, ...] | None = None
    """training runs to do, of clean, small, reverse (None: all)"""


@dataclasses.dataclass(frozen=True)
class ZooEval:
    """Evaluate every zoo policy on its own task and write the zoo table; resumable."""

    out: str
    """directory for OUT/NAME/{summary.json,episodes.jsonl,videos} and OUT/zoo_table.md"""
    episodes: int = 36
    """initial conditions per policy (simulator seeds from 10,000,000)"""
    videos: bool = True
    """write mp4s of every episode (--no-videos: skip them)"""
    policies: tuple[str, ...] | None = None
    """zoo policies to evaluate (None: all)"""


@dataclasses.dataclass(frozen=True)
class ZooList:
    """List the zoo's policies: task, weights file, recipe."""


@dataclasses.dataclass(frozen=True)
class ZooManifest:
    """Rewrite zoo.json from the registry (no training; measured training times are kept)."""

    out: str | None = None
    """directory whose zoo.json is rewritten (None: the shipped sc3_jax/benchmarks/bussing/zoo/)"""


@dataclasses.dataclass(frozen=True)
class Measure:
    """Measure the simulator as quoted in docs/sim.md: render time, demos/hour, changing pixels, expert rates."""

    episodes: int = 20
    """expert episodes per task and per failure knob"""


SUBCOMMANDS: dict[str, type] = {"demos": Demos, "mixture": Mixture, "demos-stats": DemosStats, "eval": Eval,
                                "zoo-train": ZooTrain, "zoo-eval": ZooEval, "zoo-list": ZooList,
                                "zoo-manifest": ZooManifest, "measure": Measure}


def main(argv: list[str]) -> int:
    return run_group("sim", "The simulated table-bussing benchmark (docs/sim.md).", SUBCOMMANDS, _RUN, argv)


def _rates(s: dict) -> list[str]:
    """What the per-object success rates of benchmarks/bussing/criteria.py mean, each next to its value."""
    from sc3_jax.benchmarks.bussing.criteria import LIFT_CLEARANCE

    out = " / ".join(f"{s[f'outcome/{k}']:.2f}" for k in ("language", "lifting", "placing", "no failure"))
    return [f"  language {s['language']:.2f}  share of objects never brought into the wrong container",
            f"  lifting  {s['lifting']:.2f}  share of objects the gripper raised at least "
            f"{LIFT_CLEARANCE * 100:.0f} cm above the table",
            f"  placing  {s['placing']:.2f}  share of objects at rest, released, inside their instructed container "
            "at the end",
            f"  outcomes {out}  (language / lifting / placing / no failure): share of objects whose first failed "
            "criterion, in that order, is this one",
            "  (each criterion is scored on its own, per object)"]


def _hz(a: Scene) -> int:
    """--control-hz, or the bussing simulator's own rate (the benchmark's fact, not this command's)."""
    from sc3_jax.benchmarks.bussing.env import CONTROL_HZ

    return CONTROL_HZ if a.control_hz is None else a.control_hz


def _demos(a: Demos) -> int:
    from sc3_jax.benchmarks.bussing.demos import generate_demos
    from sc3_jax.benchmarks.bussing.expert import ExpertKnobs

    if a.policy is not None:
        from sc3_jax.benchmarks.bussing.zoo import ZOO

        bussing = sorted(n for n, e in ZOO.items() if e.task == "bussing")
        if a.policy not in bussing:
            raise UserError(f"--policy {a.policy}: not a bussing zoo policy; choose one of {bussing}")
    knobs = ExpertKnobs(a.grasp_noise, a.release_noise, a.wrong_destination_prob, a.action_noise,
                        never_swap_all=not a.allow_swap_all)
    res = generate_demos(a.out, a.episodes, a.seed, knobs, tuple(a.image_size), _hz(a), a.n_objects,
                         policy=a.policy)
    print(json.dumps(res, indent=1, default=str))
    source = f"zoo policy {a.policy}" if a.policy else "scripted expert"
    print(f"\nwrote {res['written']} {source} episodes to the episode store {res['out']} "
          f"({res['skipped']} already there, skipped); `sc3 sim demos-stats --data {res['out']}` counts the store")
    if res["success"]:
        s = res["success"]
        print(f"outcomes of the {s['n_objects']} objects of the episodes written now:")
        print("\n".join(_rates(s)))
    return 0


def _mixture(a: Mixture) -> int:
    from sc3_jax.benchmarks.bussing.mixture import CATEGORIES, SOURCES, generate_mixture, rates

    shard = _shard(a.shard)
    try:
        res = generate_mixture(a.out, a.episodes, a.seed, a.recipe, a.image_size, _hz(a), a.n_objects,
                               shard=shard, workers=a.workers, seconds=a.seconds,
                               progress=a.progress and a.workers == 1)
    except ValueError as e:  # episodes / seed / shard out of range
        raise UserError(f"sc3 sim mixture: {e}") from None
    print(json.dumps(res, indent=1, default=str))
    print(f"\nwrote {res['written']} episodes of the {a.recipe} mixture to the episode store {res['out']} "
          f"({res['skipped']} already there, skipped; {res['unstarted']} left for a rerun; {res['rejected']} refused: "
          "every object in the other container, i.e. reverse bussing in all but the prompt) in "
          f"{res['seconds']:.0f} s. Every episode has the bussing task and prompt.")
    if res["written"]:
        print("per source, the objects of the episodes written now (share of objects: "
              + " / ".join(CATEGORIES) + "):")
        for src, c in res["counts"].items():
            r = rates(c)
            print(f"  {src:14s} {res['sources'].get(src, res['written']):5d} ep  "
                  + " / ".join(f"{r[k]:.2f}" for k in CATEGORIES) + f"  {SOURCES.get(src, 'all sources')}")
    print(f"`sc3 sim demos-stats --data {res['out']}` puts the whole store next to the zoo's real outcome mix")
    return 0


def _shard(spec: str | None) -> tuple[int, int]:
    if spec is None:
        return 0, 1
    try:
        i, n = (int(x) for x in spec.split("/"))
        if not 0 <= i < n:
            raise ValueError
    except ValueError:
        raise UserError(f"--shard {spec}: write I/N with 0 <= I < N, e.g. 0/4") from None
    return i, n


def _resolve_store(path: str) -> Path:
    """A relative path that does not exist here is read from the repository root (the archived stores live there)."""
    p = Path(path)
    root = Path(__file__).resolve().parents[2]
    return p if p.exists() or p.is_absolute() else root / p


def _demos_stats(a: DemosStats) -> int:
    from sc3_jax.benchmarks.bussing.demos import store_contents
    from sc3_jax.benchmarks.bussing.mixture import CATEGORIES, CATEGORY_MEANING, rates, store_outcomes, zoo_real_outcomes

    if not a.data:
        raise UserError("--data: give at least one episode store")
    if missing := [s for s in a.data if not Path(s).is_dir()]:
        raise UserError(f"--data {missing[0]}: no such directory (an `sc3 sim demos|mixture --out` store)")
    res = store_contents(*a.data)
    mix = store_outcomes(*a.data)
    zoo = None
    if a.zoo_real is not None:
        try:
            zoo = zoo_real_outcomes(_resolve_store(a.zoo_real))
        except FileNotFoundError as e:
            raise UserError(f"--zoo-real: {e} (give a sweep results store, or None for no comparison)") from None
    print(json.dumps({**res, "outcomes": mix, "zoo_real": zoo}, indent=1, default=str))
    print(f"\n{res['episodes']} episodes ({res['objects']} objects) in {', '.join(a.data)}:\n"
          "  tasks: episodes per task id\n"
          "  sources: episodes per generator (a mixture's data-collection source, expert failure knobs, 'clean "
          "expert', or the zoo policy recorded)\n"
          "  objects_in_other_container: 'k of n' -> episodes in which k of their n objects were carried into the "
          "container not instructed (ground-truth language failures)\n"
          f"  all_objects_swapped: {res['all_objects_swapped']} episodes with every object in the other container "
          "(reverse bussing in all but the prompt; world-model data should have none)")
    head = f"  {'':30s} {'episodes':>8s} {'objects':>7s}  " + "  ".join(f"{k:>6s}" for k in CATEGORIES)

    def row(name, c):
        r = rates(c)
        return f"  {name:30s} {c.get('episodes', ''):>8} {c['objects']:7d}  " + "  ".join(
            f"{r[k]:{max(len(k), 6)}.2f}" for k in CATEGORIES)
    print("\nPer-object outcomes, share of objects (placed + wrong_container + dropped + missed = 1):")
    for k in CATEGORIES:
        print(f"  {k}: {CATEGORY_MEANING[k]}")
    print("\nthe data:\n" + head)
    for src, c in mix["sources"].items():
        print(row(src, c))
    if mix["all"]:
        print(row("all", mix["all"]))
    print("per object type (all sources):")
    for name, c in mix["objects"].items():
        print(row(name, c))
    if zoo is not None:
        print(f"\nthe evaluated zoo, real rollouts scored by physics ({zoo['path']}: {zoo['conditions']} evaluation "
              "conditions per policy):\n" + head)
        for task, label in (("bussing", "in distribution (bussing)"), ("reverse", "out of distribution (reverse)")):
            for name, c in zoo["policies"].items():
                if c["task"] == task:
                    print(row(name, c))
            if task in zoo["tasks"]:
                print(row(label, zoo["tasks"][task]))
        print("How failure-rich the data is: compare its rows with the zoo's in-distribution rows; a world model "
              "learns the outcomes its data shows. A reverse policy's placed object rests in the container bussing "
              "does not use for it; the data's wrong_container objects are the nearest it comes (single objects, "
              "under a bussing prompt): the reverse instruction and the every-object mapping are never in it "
              "(all_objects_swapped above), which keeps the reverse split out of distribution.")
    return 0


def evaluate(policy: str, task: str = "bussing", episodes: int = 36, out: str | None = None, videos: bool = True,
             image_size: tuple[int, int] = (64, 64), progress: bool = True) -> dict:
    """``policy`` (any ``policies/resolve.py`` spelling; here, not in the simulator's modules, which must not import
    the resolver) evaluated in the simulator: ``policy_eval.evaluate_policy``'s summary."""
    from sc3_jax.benchmarks.bussing.hooks import named_policy
    from sc3_jax.benchmarks.bussing.policy_eval import evaluate_policy
    from sc3_jax.policies.resolve import resolve
    try:
        resolved = resolve(policy, named=named_policy)
    except (ValueError, ConnectionError, TimeoutError) as e:  # a misspelt name (the message lists the spellings
        raise UserError(f"--policy: {e}") from None  # and the zoo), a ws:// server not there
    return evaluate_policy(resolved.policy, task, episodes, out, image_size=tuple(image_size), videos=videos,
                           progress=progress)


def _eval(a: Eval) -> int:
    res = evaluate(a.policy, a.task, a.episodes, a.out, a.videos, a.image_size)
    print(json.dumps(res, indent=1, default=str))
    s = res["success"]
    print(f"\n{res['policy']} on {res['task']}: {res['episodes']} episodes (simulator seeds {res['seed0']}-"
          f"{res['seed0'] + res['episodes'] - 1}), {s['n_objects']} objects, {res['seconds']:.0f} s; success rates "
          "(ground truth from physics, docs/sim.md):")
    print("\n".join(_rates(s)))
    print(f"written to {a.out} (summary.json, episodes.jsonl{', videos/' if a.videos else ''})" if a.out
          else "nothing written (--out DIR keeps summary.json, episodes.jsonl and videos)")
    return 0


def _zoo_train(a: ZooTrain) -> int:
    from sc3_jax.benchmarks.bussing.zoo import ZOO_DIR
    from sc3_jax.benchmarks.bussing.zoo_train import RUNS, train_zoo

    if unknown := sorted(set(a.runs or ()) - set(RUNS)):
        raise UserError(f"--runs: unknown {unknown}; choose from {list(RUNS)}")
    out = a.out or str(ZOO_DIR)
    res = train_zoo(a.workdir, out, list(a.runs) if a.runs else None)
    print(json.dumps(res, indent=1, default=str))
    print(f"\ntrained {', '.join(a.runs or RUNS)}: weights (run_NAME_mid|final.npz) and zoo.json in {out}; demo sets "
          f"in {a.workdir}/demos_*; seconds are wall time per run. `sc3 sim zoo-eval --out DIR` measures the policies")
    return 0


def _zoo_eval(a: ZooEval) -> int:
    from sc3_jax.benchmarks.bussing.policy_eval import evaluate_zoo

    print(evaluate_zoo(a.out, a.episodes, a.videos, list(a.policies) if a.policies else None))
    print(f"each policy on its own task over {a.episodes} episodes (simulator seeds from 10,000,000). language / "
          "lifting / placing: share of all its objects meeting that criterion on its own (ground truth from "
          "physics); outcomes: share whose first failed criterion is that one; spread: max - min over the task's "
          f"policies. Table in {a.out}/zoo_table.md; per policy {a.out}/NAME/summary.json and episodes.jsonl")
    return 0


def _zoo_list(a: ZooList) -> int:
    from sc3_jax.benchmarks.bussing.zoo import ZOO, ZOO_DIR

    for n, e in ZOO.items():
        print(f"{n:20s} {e.task:8s} {e.weights:22s} {e.recipe}")
    tasks = {t: sum(e.task == t for e in ZOO.values()) for t in dict.fromkeys(e.task for e in ZOO.values())}
    print(f"\n{len(ZOO)} zoo policies ({', '.join(f'{k} {t}' for t, k in tasks.items())}): name, the task it "
          f"was made for, its estimator's weights in {ZOO_DIR}, recipe. `sc3 sim eval --policy NAME` evaluates one")
    return 0


def _zoo_manifest(a: ZooManifest) -> int:
    from sc3_jax.benchmarks.bussing.zoo import ZOO_DIR
    from sc3_jax.benchmarks.bussing.zoo_train import write_manifest

    if a.out:
        Path(a.out).mkdir(parents=True, exist_ok=True)
    path = write_manifest(a.out or ZOO_DIR)
    print(f"wrote {path}: the registry's policies (weights, non-default control knobs, recipe), knob defaults, "
          "training runs and demo sets; training times measured earlier are kept")
    return 0


def _measure(a: Measure) -> int:
    from sc3_jax.benchmarks.bussing.measure import measure_all

    res = measure_all(a.episodes)
    print(json.dumps(res, indent=1))
    print("\nrender_ms_*: milliseconds to render all three views once; changed_pixel_fraction, per view, pixels "
          "differing from an expert episode's first frame: ever (at some step), per_frame (mean share), step (between "
          "consecutive frames); demos_per_hour: 64x64 demos rendered and written; expert/TASK: the clean expert's "
          f"success rates over {a.episodes} episodes, knob/KNOB: the bussing expert with that failure knob "
          "(language / lifting / placing: share of objects meeting the criterion; outcome/*: first criterion "
          "failed). docs/sim.md quotes them")
    return 0


_RUN = {"demos": _demos, "mixture": _mixture, "demos-stats": _demos_stats, "eval": _eval, "zoo-train": _zoo_train,
        "zoo-eval": _zoo_eval, "zoo-list": _zoo_list, "zoo-manifest": _zoo_manifest, "measure": _measure}

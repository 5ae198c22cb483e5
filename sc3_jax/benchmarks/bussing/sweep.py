"""The bussing benchmark's sweep: policies x initial conditions x {real, offline, online}, into a resumable results
store. This module says what runs (the seed blocks, the policies, the modes, the options below); the sweep engine
(``evaluation/engine.py``) runs it, with this benchmark's ``Source`` (``source.py``: the simulator's reset frames, its
real rollouts and the perception scorer).

    real     the policy acts in the simulator; scored by physics (ground truth) and by the perception scorer
             (their agreement validates the scorer the imagined rollouts are judged by)
    offline  the world model replays the real rollout's actions open loop from the same first frame; PSNR against
             the real frames, outcomes by the perception scorer
    online   the policy acts inside the world model (closed loop, ``rollout.Rollout``), U_chunk per chunk, outcomes
             by the perception scorer for every possible termination point

Seeds come in three disjoint blocks (``seed_blocks``): evaluation (all three modes), calibration (real + online:
tau is chosen there, ``calibrate.py``) and ceiling (real only: a second independent set for the noise ceiling).

Early termination is swept after the fact: each online rollout runs once untruncated (tau = inf) and stores the
outcomes of the rollout cut after every chunk; a threshold tau keeps the chunks before the first one with
U_chunk > tau, which are exactly the frames a rollout run with that tau would have produced.

Results go to a results store (``results.py``: ``sweep.json``, ``results.jsonl``, one npz per rollout);
``sweep.json`` records the world model's content hash and step (``evaluation/engine.py``'s ``with_identity``: a
resume against a changed model is refused, a store from before the hash resumes with a note). A killed
sweep restarted with the same config skips every rollout whose line exists and redoes only the work in flight: one
real rollout, or one world-model batch (``batch`` initial conditions are rolled out together, and a batch is always
the same set, so results do not depend on where a sweep was killed).

Policies are named as ``policies/resolve.py`` reads them (a zoo name, or e.g. NAME=ws://HOST:PORT@TASK); every
policy needs a task (a zoo policy has its own).
"""
from __future__ import annotations

import dataclasses
import errno
import json
import math
import os
import shutil
from pathlib import Path
from typing import Annotated

import numpy as np
import tyro

from sc3_jax.core.errors import UserError
from sc3_jax.evaluation.world_model_defaults import Sampler
from sc3_jax.evaluation.results import (EVAL_MODES, REAL_ONLY_STRIDE, ResultsStore, rollout_id, score_strides,
                                      seed_blocks)

# the best shipped world model (docs/results.md's headline): README command 1 evaluates the zoo inside it
SHIPPED_WORLD_MODEL = Path(__file__).resolve().parent / "shipped" / "bussing_latent_gpu"  # the benchmark's own model
# a world model may ship the gripper-state reader its published sweeps used (see default_state_reader)
STATE_READER_FILE = "state_reader.npz"


@dataclasses.dataclass(frozen=True, kw_only=True)
class SweepConfig(Sampler):
    """The benchmark's policies in its simulator and inside the world model, then the report; resumable (rerun
    the same command). Ends with OUT/report/report.md. Every field is an option of `sc3 sweep bench`."""

    out: str = "runs/sweep"
    """the results store: results.jsonl, rollouts/, sweep.json, timing.json and report/ (rerun to resume)"""
    # the help names it, not the path it has on this machine
    world_model: Annotated[str, tyro.conf.arg(help_behavior_hint="(default: the shipped bussing_latent_gpu)")] = \
        str(SHIPPED_WORLD_MODEL)
    """a training run dir (checkpoints/) or an exported dir (params.npz)"""
    perception: str | None = None
    """perception weights (None: the shipped ones)"""
    state_reader: str | None = None
    """perception weights whose finger-gap head reads the gripper state the policy sees inside imagined rollouts
    (None: the world model's own state_reader.npz if it ships one, else the scorer's). Part of the rollouts, not
    of their scoring: `sc3 rescore` leaves it as it was"""
    policies: tuple[str, ...] = ()
    """policies/resolve.py spellings with a task: zoo names, NAME=ws://HOST:PORT@TASK (openpi server),
    NAME=package.module:attr@TASK, ...; () = the zoo policies of `tasks`"""
    tasks: tuple[str, ...] | None = ("bussing",)
    """with no --policies: the zoo's policies of these tasks ("bussing": in distribution, "reverse": out of
    distribution). The quick protocol sweeps the in-distribution split only: on 2 cores its budget buys enough
    conditions to tell a model from a guess there, or too few for anything on both splits. None: every task (how
    stores written before this field read)"""
    episodes: int = 18
    """evaluation initial conditions per policy (simulator seeds seed0 + i). The defaults are the quick protocol:
    the 7 in-distribution policies x 18 evaluation + 3 calibration + 18 ceiling conditions, real and online
    (docs/sweep.md#the-quick-protocol: the fewest conditions at which the shipped model's paired difference to
    the policy-blind floor excludes 0 on r and MMRV). The full protocol: --tasks bussing reverse --episodes 36
    --calibration-episodes 6 --ceiling-episodes 36 (--modes real offline online)"""
    seed0: int = 10_000_000
    """first evaluation seed (the simulator's initial condition)"""
    calibration_episodes: int = 3
    """held-out conditions per policy for choosing tau (real + online; never evaluated)"""
    calibration_seed0: int = 20_000_000
    """first calibration seed (disjoint from every other block)"""
    ceiling_episodes: int = 18
    """second independent real set per policy, the noise ceiling (0: split-half estimate)"""
    ceiling_seed0: int = 30_000_000
    """first ceiling seed"""
    modes: tuple[str, ...] = ("real", "online")
    """evaluation modes (results.EVAL_MODES); offline replay (PSNR, open-loop faithfulness) is not in the quick
    protocol: it would cost as much again as online"""
    degradations: str = "calibration"
    """which real rollouts the perception scorer also reads blurred / patch-noised / colour-shifted (its robustness
    to generated-looking frames: the report's "Perception scorer vs physics"): "calibration" (the calibration
    conditions' only), "all" or "none". Each degraded reading costs as much as the clean one: on every real
    rollout they were half of the real rollouts' time (bench/sweep.py), while the check needs only a sample of
    objects. Stores written before this choice hold a boolean: true reads as "all", false as "none"."""
    episode_seconds: float | None = 12.0
    """real and imagined horizon (None: the world model's rollout.episode_seconds). The benchmark's: a successful
    zoo episode ends well before 12 s, a failing one retries until the limit"""
    taus: tuple[float, ...] = (math.inf, 0.1, 0.07, 0.05, 0.02, 0.01)
    """candidate U_chunk thresholds in the benchmark's raw action units (m, rad, gripper m); the calibration
    conditions choose one and the report's post-hoc table lists them all"""
    real_from: str | None = None
    """start from another store's real rollouts (hard links; same protocol and scorer): world models compared on
    one real set, which is paid for once (e.g. the checkpoints of a compute curve, docs/results.md)"""
    shard: str | None = None
    """run a disjoint share "I/N" of the (policy, initial-condition batch) work into OUT/shard-I-of-N (None: all of
    it; under jax.distributed with several processes, the process's own share). `sc3 report OUT` reads the
    shards of OUT as one store; merged shards hold exactly the records of one unsharded sweep"""
    workers: int = 0
    """processes running the rollouts (0: one per core): the real (simulated) ones, and the world model's batches
    when it runs on the CPU (single-threaded processes use the cores better than one process on all of them; on
    an accelerator the batches run in this process). Records do not depend on it"""
    progress: bool = True
    """progress bar over rollouts"""

    def to_json(self) -> dict:
        d = dataclasses.asdict(self)
        d["taus"] = [str(t) for t in self.taus]  # JSON has no inf
        d.pop("workers")  # how the work was spread, not what it computed: a store resumes under any count
        return json.loads(json.dumps(d))  # tuples -> lists, as read back from sweep.json


# ================================================================================================================
# The sweep: this benchmark's work and its Source, run by the engine (evaluation/engine.py)
# ================================================================================================================
def run_sweep(cfg: SweepConfig) -> Path:
    """Run (or resume) the sweep; returns the results directory. See the module docstring."""
    import functools

    from sc3_jax.model import checkpoint
    from sc3_jax.rollout import rollout as ro_mod
    from sc3_jax.evaluation import engine

    from . import perception
    from .hooks import named_policy
    from .policy_eval import make_env
    from .rescore import weights_digest
    from .source import BussingSource, state_reader
    from .tasks import CRITERIA, SPLITS, TASKS

    cfg = dataclasses.replace(cfg, degradations=degradations_choice(cfg.degradations))
    bad = [m for m in cfg.modes if m not in EVAL_MODES]
    if bad or not cfg.modes:
        raise UserError(f"modes {list(cfg.modes)}: choose from {list(EVAL_MODES)}")
    if "offline" in cfg.modes and "real" not in cfg.modes:
        raise UserError("offline rollouts replay the real rollouts' actions: include 'real' in modes")
    if cfg.tau_units not in ("normalised", "raw"):
        raise UserError(f"tau_units {cfg.tau_units!r}: 'normalised' or 'raw'")
    if cfg.real_from and ("real" not in cfg.modes or not cfg.episode_seconds):
        raise UserError("--real-from copies real rollouts: it needs 'real' in modes and an explicit "
                         "--episode-seconds (the length both stores' real rollouts ran for)")
    cfg = dataclasses.replace(cfg, state_reader=default_state_reader(cfg), shard=engine.shard_of(cfg.shard))
    index, count = engine.parse_shard(cfg.shard)
    out = engine.shard_dir(cfg.out, cfg.shard)
    blocks = seed_blocks(cfg)
    weights = cfg.perception or perception.DEFAULT_WEIGHTS
    # the benchmark's splits, in-distribution first (the report's order; tau is chosen on the first), and criteria
    config = {**cfg.to_json(), "perception_sha256": weights_digest(weights),
              "splits": list(dict.fromkeys(SPLITS.values())), "criteria": list(CRITERIA)}
    policies = engine.resolve_policies(cfg.policies or _zoo_names(cfg.tasks), named_policy, need_task=True,
                                       tasks=TASKS)
    wm_modes = [m for m in cfg.modes if m != "real"]
    spec = None
    if wm_modes:
        from sc3_jax.evaluation.world_model_defaults import evaluation_config, warn_if_student_off_its_step
        wcfg = evaluation_config(checkpoint.read_config(cfg.world_model), cfg)
        warn_if_student_off_its_step(wcfg)
        robot = checkpoint.read_robot(cfg.world_model, wcfg)  # the model's data's frame rate and action space
        spec = ro_mod.make_spec(wcfg, robot.fps, action_space=robot.action_space)
    image_size, score_stride = (tuple(spec.image_size), spec.stride) if spec else ((64, 64), REAL_ONLY_STRIDE)
    env = make_env(image_size)
    seconds = cfg.episode_seconds or (wcfg.rollout.episode_seconds if spec else 20.0)
    max_steps = int(round(seconds * env.control_hz))
    units = engine.work_units(len(policies), blocks, cfg.modes, cfg.batch)[index::count]
    real_seeds = sorted({(u.policy, s) for u in units if u.real for s in u.seeds})
    # a refused --real-from source is refused before the store is created or written
    copies = real_to_copy(cfg.real_from, config, {p.name: p.task for p in policies},
                          [(policies[p].name, s) for p, s in real_seeds], image_size, score_stride,
                          ResultsStore(out).done()) if cfg.real_from else []
    # what the rollouts come from (engine.with_identity): a resume against a changed model is refused; the model
    # is hashed whenever it is there to read, so a real-only resume cannot re-stamp another model's online rollouts
    reads_model = bool(wm_modes) or (Path(cfg.world_model) / "config.json").is_file()
    config = engine.with_identity(out, config, engine.identity(cfg.world_model if reads_model else None, None,
                                                               [(p.name, p.spec) for p in policies]))
    make_source = functools.partial(BussingSource, {p.name: p.task for p in policies}, image_size, str(weights),
                                    max_steps, score_stride)
    setup = engine.Setup(str(out), cfg.world_model if wm_modes else None, cfg, make_source, named_policy,
                         functools.partial(state_reader, cfg.state_reader or str(weights)))
    source = make_source(env=env)
    source.scorer  # noqa: B018  (unreadable perception weights are refused before the store is written)
    return engine.run(setup, config, policies, units, source=source, progress=cfg.progress,
                      workers=cfg.workers or engine.default_workers(),
                      degraded=functools.partial(degraded_block, cfg.degradations),
                      before=lambda store: link_real(store, cfg.real_from, copies))


DEGRADATIONS = ("calibration", "all", "none")


def degradations_choice(value) -> str:
    """SweepConfig.degradations, with a store's legacy boolean read as it was meant (true: every real rollout)."""
    value = {True: "all", False: "none"}.get(value, value) if isinstance(value, bool) else value
    if value not in DEGRADATIONS:
        raise UserError(f"--degradations {value!r}: choose from {', '.join(DEGRADATIONS)}")
    return value


def degraded_block(choice: str, block: str) -> bool:
    """Whether the real rollouts of seed ``block`` are also scored on degraded frames."""
    return choice == "all" or (choice == "calibration" and block == "calibration")


def default_state_reader(cfg: SweepConfig) -> str | None:
    """The state reader a sweep uses: ``cfg.state_reader`` if given, else the world model's own
    ``state_reader.npz`` if its directory ships one, else None (the scorer's weights).

    Why a world model carries one: the reader is part of its imagined rollouts (the policy acts on the gripper state
    it reads), so a sweep reproduces a model's published numbers only with the reader they were made with, even
    after the shipped scorer is retrained. Resolved whatever the modes, so a store started with real rollouts only
    resumes with world-model modes added."""
    if cfg.state_reader:
        return cfg.state_reader
    own = Path(cfg.world_model) / STATE_READER_FILE
    return str(own) if own.is_file() else None


def real_to_copy(source: str | Path, config: dict, tasks: dict[str, str], pairs: list[tuple[str, int]],
                 image_size: tuple[int, int], score_stride: int, have: set[str]) -> list[dict]:
    """The real records of the results store ``source`` for the (policy name, seed) ``pairs`` (``tasks``: name ->
    task) that are not in ``have``, checked to be the rollouts the sweep of ``config`` would have run (the simulator is
    deterministic per seed): the same task, episode length, degradations, perception weights, frame size and scoring
    stride; raises otherwise. Reads the source without writing to it (its own sweep may be running)."""
    want = {rollout_id(p, s, "real") for p, s in pairs} - have
    if not want:
        return []  # nothing left to copy: the source is not read (it may have moved since)
    src = ResultsStore(source)
    if not (src.root / "sweep.json").exists():
        raise UserError(f"--real-from {source}: not a results store (no sweep.json)")
    theirs = src.config()
    keys = ("episode_seconds", "degradations", "perception_sha256")
    theirs = dict(theirs, degradations=degradations_choice(theirs.get("degradations", True)))
    diff = {k: (theirs.get(k), config.get(k)) for k in keys if theirs.get(k) != config.get(k)}
    if diff:
        raise UserError(f"--real-from {source}: its real rollouts were run or scored otherwise (source, this "
                         f"sweep): {diff}")
    every = src.records()
    recs = [r for r in every if r["id"] in want]
    if not recs:
        return []
    strides = score_strides(every)
    for what, bad in (("task", {r["id"]: r["task"] for r in recs if r["task"] != tasks[r["policy"]]}),
                      ("scoring stride", {r["id"]: strides[r["id"]] for r in recs
                                          if strides[r["id"]] != score_stride})):
        if bad:
            rid = next(iter(bad))
            raise UserError(f"--real-from {source}: {len(bad)} real rollouts differ in {what} from this sweep's "
                             f"(e.g. {rid}: {bad[rid]})")
    if not src.array_path(recs[0]["id"]).exists():
        # a records-only store (e.g. an archived one, docs/stores/): its outcomes serve online evaluation; offline
        # replay needs the real actions, videos and `sc3 rescore` the frames
        if "offline" in config.get("modes", ()):
            raise UserError(f"--real-from {source}: it holds records without their arrays, and offline replay "
                            "needs the real rollouts' actions: drop 'offline' from --modes")
        return recs
    with np.load(src.array_path(recs[0]["id"])) as z:
        size = tuple(z["frames"].shape[-3:-1])
    if size != tuple(image_size):
        raise UserError(f"--real-from {source}: its frames are {size}, this world model's {tuple(image_size)}")
    return recs


def link_real(store: ResultsStore, source: str | Path, recs: list[dict]) -> None:
    """Hard-link the arrays of ``recs`` (records of the store ``source``, from :func:`real_to_copy`) into
    ``store``, where the source has them, and append the records."""
    src = ResultsStore(source) if recs else None
    for r in recs:
        if not src.array_path(r["id"]).exists():
            continue  # a records-only source (real_to_copy): the record is what is copied
        dst = store.array_path(r["id"])
        dst.parent.mkdir(parents=True, exist_ok=True)
        if dst.exists():
            dst.unlink()  # arrays of a copy cut by a kill before its record was appended
        try:
            os.link(src.array_path(r["id"]), dst)
        except OSError as e:
            if e.errno != errno.EXDEV:
                raise
            shutil.copy2(src.array_path(r["id"]), dst)  # another file system
    if recs:
        store.append(recs)


def _zoo_names(tasks=None):
    from sc3_jax.benchmarks.bussing.zoo import zoo_names
    return [n for n in zoo_names() if tasks is None or any(n in zoo_names(t) for t in tasks)]

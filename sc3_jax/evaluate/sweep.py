"""Evaluation sweep: policies x initial conditions x {real, offline, online}, into a resumable results store.

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

Results go to a results store (``results.py``: ``sweep.json``, ``results.jsonl``, one npz per rollout). A killed
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
import time
from pathlib import Path

import numpy as np

from sc3_jax.evaluate.results import (EVAL_MODES, REAL_ONLY_STRIDE, SPLITS, ResultsStore, rollout_id,
                                     score_strides, seed_blocks)

# the best shipped world model (docs/results.md's headline): README command 1 evaluates the zoo inside it
SHIPPED_WORLD_MODEL = Path(__file__).resolve().parent / "shipped" / "bussing_latent_gpu"
# a world model may ship the gripper-state reader its published sweeps used (see default_state_reader)
STATE_READER_FILE = "state_reader.npz"


@dataclasses.dataclass(frozen=True)
class SweepConfig:
    out: str = "runs/sweep"
    world_model: str = str(SHIPPED_WORLD_MODEL)  # a training run dir (checkpoints/) or an exported dir (params.npz)
    perception: str | None = None  # perception weights (None: the shipped ones)
    # perception weights whose finger-gap head reads the gripper state the policy sees inside imagined rollouts
    # (None: the world model's own state_reader.npz if it ships one, else the scorer's). Part of the rollouts, not
    # of their scoring: `sc3 rescore` leaves it as it was
    state_reader: str | None = None
    # policies/resolve.py spellings with a task: zoo names, NAME=ws://HOST:PORT@TASK (openpi server),
    # NAME=package.module:attr@TASK, ...; () = the whole zoo
    policies: tuple[str, ...] = ()
    # quick protocol by default (46 min on 2 cores with the shipped model, docs/sweep.md); the full one: --episodes 36
    # --calibration-episodes 6 --ceiling-episodes 36 --batch 6
    episodes: int = 4  # evaluation initial conditions per policy (simulator seeds seed0 + i)
    seed0: int = 10_000_000
    calibration_episodes: int = 2  # held-out conditions per policy for choosing tau (real + online; never evaluated)
    calibration_seed0: int = 20_000_000  # first calibration seed (disjoint from every other block)
    ceiling_episodes: int = 4  # second independent real set per policy, the noise ceiling (0: split-half estimate)
    ceiling_seed0: int = 30_000_000  # first ceiling seed
    modes: tuple[str, ...] = EVAL_MODES  # evaluation modes (results.EVAL_MODES)
    # candidate U_chunk thresholds (the calibration picks one; the report's post-hoc table lists them all). In raw
    # units (m, rad, gripper m) the paper's 0.02-0.05 is in the range our models' U takes; in normalised units
    # (per-dimension unit variance) it would stop every rollout at once
    taus: tuple[float, ...] = (math.inf, 0.1, 0.07, 0.05, 0.02, 0.01)
    # U_chunk's units: written into the world model's rollout.tau_units, so the sweep, the report and `sc3 rollout`
    # with the same config share one convention ("raw" or "normalised")
    tau_units: str = "raw"
    batch: int = 4  # initial conditions per world-model batch (the resume unit for offline/online)
    rollout_seed: int = 0
    degradations: bool = True  # also score real frames blurred / patch-noised / colour-shifted (scorer robustness)
    # real and imagined horizon (None: the world model's rollout config). 12 s: a successful zoo episode takes 6.5-7.5 s,
    # a failing one retries until the limit; 12 s keeps every success and costs 60% of the 20 s default
    episode_seconds: float | None = 12.0
    sample_steps: int | None = None  # None: the world model's config
    # Euler steps of the inverse-dynamics re-read (None: the world model's config). It yields U_chunk only, never the
    # frames or the outcomes; 2 instead of 8 makes an online rollout ~35% cheaper (docs/sweep.md#cost-and-scale),
    # and 2 is what the published sweeps used (tau is calibrated on U read the same way)
    inverse_steps: int | None = 2
    # start from another store's real rollouts (hard links; same protocol and scorer): world models compared on one
    # real set, which is paid for once (e.g. the checkpoints of a compute curve, docs/results.md)
    real_from: str | None = None
    progress: bool = True  # progress bar over rollouts

    def to_json(self) -> dict:
        d = dataclasses.asdict(self)
        d["taus"] = [str(t) for t in self.taus]  # JSON has no inf
        return json.loads(json.dumps(d))  # tuples -> lists, as read back from sweep.json


# ================================================================================================================
# The three evaluation modes
# ================================================================================================================
def initial_observation(env, seed: int, task: str):
    """Frames uint8 [V, H, W, 3] and end-effector pose [7] right after reset: where real and imagined start."""
    env.reset(seed, task)
    f = env.render()
    return np.stack([f[v] for v in env.views]), env.ee_pose().astype(np.float32)


def run_real(env, name, task, policy, seed, scorer, max_steps: int, score_stride: int,
             degradations: bool = False) -> tuple[dict, dict]:
    """One simulated rollout, scored by physics and by perception (on every ``score_stride``-th frame and the last:
    the world model's frame rate, so real and imagined rollouts are read alike); with ``degradations`` also by
    perception on degraded copies of the frames (``degrade.py``: how the scorer reads generated-looking frames)."""
    from sc3_jax.evaluate.scorers import RolloutView, SimScorer
    from sc3_jax.sim.policy_eval import run_policy_episode
    r = run_policy_episode(env, policy, seed, task, record=True, max_steps=max_steps)
    frames = np.stack([r.frames[v] for v in env.views])  # [V, T, H, W, 3] at 20 Hz
    view = RolloutView(rollout_id(name, seed, "real"), frames, r.ic.objects, r.ic.destinations(),
                       [o.to_json() for o in r.outcomes])
    clean, degraded = scorer.score_real(view, seed, score_stride, degradations)
    rec = {"objects": SimScorer().score(view), "perception": clean, "length": int(r.length), "prompt": r.ic.prompt,
           "score_stride": score_stride}
    if degradations:
        rec["perception_degraded"] = degraded
    return rec, {"frames": frames, "actions": r.actions.astype(np.float32), "ee_pose": r.ee_pose.astype(np.float32),
                 "object_pos": r.object_pos}


# ================================================================================================================
# The sweep
# ================================================================================================================
def run_sweep(cfg: SweepConfig) -> Path:
    """Run (or resume) the sweep; returns the results directory. See the module docstring."""
    import jax
    from tqdm import tqdm

    from sc3_jax import checkpoint
    from sc3_jax import rollout as ro_mod
    from sc3_jax.evaluate import perception
    from sc3_jax.evaluate.rescore import weights_digest
    from sc3_jax.evaluate.scorers import PerceptionScorer
    from sc3_jax.policies.base import JaxPolicy
    from sc3_jax.sim.policy_eval import make_env

    bad = [m for m in cfg.modes if m not in EVAL_MODES]
    if bad or not cfg.modes:
        raise ValueError(f"modes {list(cfg.modes)}: choose from {list(EVAL_MODES)}")
    if "offline" in cfg.modes and "real" not in cfg.modes:
        raise ValueError("offline rollouts replay the real rollouts' actions: include 'real' in modes")
    if cfg.tau_units not in ("normalised", "raw"):
        raise ValueError(f"tau_units {cfg.tau_units!r}: 'normalised' or 'raw'")
    if cfg.real_from and ("real" not in cfg.modes or not cfg.episode_seconds):
        raise ValueError("--real-from copies real rollouts: it needs 'real' in modes and an explicit "
                         "--episode-seconds (the length both stores' real rollouts ran for)")
    cfg = dataclasses.replace(cfg, state_reader=default_state_reader(cfg))  # sweep.json records the one used
    blocks = seed_blocks(cfg)
    weights = cfg.perception or perception.DEFAULT_WEIGHTS
    config = {**cfg.to_json(), "perception_sha256": weights_digest(weights)}
    p_params = perception.load(weights)
    scorer = PerceptionScorer(p_params)
    policies = [_resolve(p) for p in (cfg.policies or _zoo_names())]
    seeds = blocks["evaluation"]
    real_seeds = seeds + blocks["calibration"] + blocks["ceiling"]
    # world-model rollouts per mode: (seed block, fold-in offset of its episode keys: blocks never share noise)
    wm_blocks = {"offline": [(seeds, 0)], "online": [(seeds, 0), (blocks["calibration"], 1 << 20)]}
    wm_modes = [m for m in cfg.modes if m != "real"]
    ro = params = None
    if wm_modes:
        wcfg, stats, params = checkpoint.load(cfg.world_model)
        from sc3_jax.config import replace
        wcfg = replace(wcfg, sample={k: v for k, v in (("steps", cfg.sample_steps),
                                                       ("inverse_steps", cfg.inverse_steps)) if v})
        if cfg.episode_seconds:
            wcfg = replace(wcfg, rollout=dict(episode_seconds=cfg.episode_seconds))
        wcfg = replace(wcfg, rollout=dict(tau_units=cfg.tau_units))  # one unit convention
        reader = perception.load(cfg.state_reader) if cfg.state_reader else p_params
        ro = ro_mod.Rollout(wcfg, stats, state_reader=perception.state_reader(reader))
    image_size, score_stride = (tuple(ro.spec.image_size), ro.spec.stride) if ro else ((64, 64), REAL_ONLY_STRIDE)
    env = make_env(image_size)
    seconds = cfg.episode_seconds or (wcfg.rollout.episode_seconds if ro else 20.0)
    max_steps = int(round(seconds * env.control_hz))
    # a refused --real-from source is refused before the store is created or written
    copies = real_to_copy(cfg.real_from, config, {n: t for n, t, _ in policies}, real_seeds, image_size, score_stride,
                          ResultsStore(cfg.out).done()) if cfg.real_from else []
    store = ResultsStore(cfg.out, config)
    link_real(store, cfg.real_from, copies)
    done = store.done()
    total = len(policies) * sum(len(real_seeds) if m == "real" else sum(len(b) for b, _ in wm_blocks[m])
                                for m in cfg.modes)
    bar = tqdm(total=total, initial=len(done), desc="sweep", unit="rollout", disable=not cfg.progress)
    t0 = time.time()
    for name, task, policy in policies:
        base = {"policy": name, "task": task, "split": SPLITS[task]}
        if "real" in cfg.modes:
            for seed in real_seeds:
                rid = rollout_id(name, seed, "real")
                if rid in done:
                    continue
                rec, arrays = run_real(env, name, task, policy, seed, scorer, max_steps, score_stride,
                                       cfg.degradations)
                store.save_arrays(rid, **arrays)
                store.append([{"id": rid, "mode": "real", "seed": seed, **base, **rec}])
                bar.update(1)
        for mode in wm_modes:
            for block, offset in wm_blocks[mode]:
                for g in range(0, len(block), cfg.batch):
                    group = block[g:g + cfg.batch]
                    ids = [rollout_id(name, s, mode) for s in group]
                    if all(i in done for i in ids):
                        continue
                    recs = _world_model_batch(mode, ro, params, env, name, task, policy, group,
                                              list(range(offset + g, offset + g + len(group))), cfg, store, scorer,
                                              isinstance(policy, JaxPolicy))
                    store.append([{"id": i, "mode": mode, "seed": s, **base, **r}
                                  for i, s, r in zip(ids, group, recs)])
                    bar.update(len(group))
    bar.close()
    env.close()
    (store.root / "timing.json").write_text(json.dumps({"seconds_last_run": time.time() - t0,
                                                        "devices": [str(d) for d in jax.devices()]}))
    return store.root


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


def real_to_copy(source: str | Path, config: dict, tasks: dict[str, str], seeds: list[int],
                 image_size: tuple[int, int], score_stride: int, have: set[str]) -> list[dict]:
    """The real records of the results store ``source`` for the policies of ``tasks`` (name -> task) x ``seeds``
    that are not in ``have``, checked to be the rollouts the sweep of ``config`` would have run (the simulator is
    deterministic per seed): the same task, episode length, degradations, perception weights, frame size and scoring
    stride; raises otherwise. Reads the source without writing to it (its own sweep may be running)."""
    want = {rollout_id(p, s, "real") for p in tasks for s in seeds} - have
    if not want:
        return []  # nothing left to copy: the source is not read (it may have moved since)
    src = ResultsStore(source)
    if not (src.root / "sweep.json").exists():
        raise ValueError(f"--real-from {source}: not a results store (no sweep.json)")
    theirs = src.config()
    keys = ("episode_seconds", "degradations", "perception_sha256")
    diff = {k: (theirs.get(k), config.get(k)) for k in keys if theirs.get(k) != config.get(k)}
    if diff:
        raise ValueError(f"--real-from {source}: its real rollouts were run or scored otherwise (source, this "
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
            raise ValueError(f"--real-from {source}: {len(bad)} real rollouts differ in {what} from this sweep's "
                             f"(e.g. {rid}: {bad[rid]})")
    with np.load(src.array_path(recs[0]["id"])) as z:
        size = tuple(z["frames"].shape[-3:-1])
    if size != tuple(image_size):
        raise ValueError(f"--real-from {source}: its frames are {size}, this world model's {tuple(image_size)}")
    return recs


def link_real(store: ResultsStore, source: str | Path, recs: list[dict]) -> None:
    """Hard-link the arrays of ``recs`` (records of the store ``source``, from :func:`real_to_copy`) into
    ``store`` and append the records."""
    src = ResultsStore(source) if recs else None
    for r in recs:
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


def _resolve(spec: str):
    """(name, task, policy) of a sweep policy: any spelling of ``policies.resolve``, with a task."""
    from sc3_jax.policies.resolve import TASKS, resolve
    r = resolve(spec)
    if r.task is None:
        raise ValueError(f"policy {spec!r}: the sweep needs its task; expected NAME=SPEC@TASK (e.g. "
                         f"NAME=ws://HOST:PORT@TASK) with TASK in {list(TASKS)}")
    return r.name, r.task, r.policy


def _zoo_names():
    from sc3_jax.sim.zoo import zoo_names
    return zoo_names()


def _world_model_batch(mode, ro, params, env, name, task, policy, seeds, indices, cfg, store, scorer, is_jax):
    """Offline or online rollouts of one batch of initial conditions -> one record per rollout."""
    from sc3_jax import rollout as ro_mod
    from sc3_jax.evaluate.metrics import psnr_by_view
    from sc3_jax.sim.tasks import make_initial_condition, task_id
    s = ro.spec
    obs = [initial_observation(env, seed, task) for seed in seeds]
    frames0 = np.stack([np.repeat(f[:, None], s.context, 1) for f, _ in obs])  # [B, V, K, H, W, 3]: at rest
    ics = ro_mod.InitialConditions(frames0, np.stack([p for _, p in obs]), np.full(len(seeds), task_id(task)))
    # episode i's noise depends only on (rollout_seed, i): every policy meets the same draws (common random numbers)
    keys = np.asarray(ro_mod.episode_keys(cfg.rollout_seed, len(seeds), start=indices[0]))
    if mode == "offline":
        real = [store.load_arrays(rollout_id(name, seed, "real")) for seed in seeds]
        actions = np.stack([ro_mod.chunk_actions(r["actions"], s) for r in real])
        out = ro.run_offline(params, ics, actions, keys, math.inf)
    elif is_jax:
        out = ro.run(params, policy, ics, keys, math.inf)
    else:
        out = ro.run_host(params, policy, ics, keys, math.inf)
    recs = []
    for b, seed in enumerate(seeds):
        ic = make_initial_condition(seed, task)
        frames = np.concatenate([out["initial_frames"][b][:, -1:], out["frames"][b]], 1)  # [V, 1 + N*l, ...]
        cuts = scorer.score_cuts(frames, ic.objects, ic.destinations(), s.keep, s.num_chunks, prefix=1)
        rec = {"objects": cuts[-1], "u": out["u"][b].tolist(), "u_raw": out["u_raw"][b].tolist(),
               "num_chunks": s.num_chunks, "frames_per_chunk": s.keep, "stride": s.stride}
        if mode == "online":
            rec["objects_by_cut"] = cuts
        else:
            targets, valid = ro_mod.recorded_targets(real[b]["frames"], s)
            rec["psnr_view"] = psnr_by_view(out["frames"][b], targets, valid)[1].tolist()  # per view
        store.save_arrays(rollout_id(name, seed, mode), frames=frames, actions=out["actions"][b],
                          reread=out["reread"][b], u=out["u"][b], u_raw=out["u_raw"][b])
        recs.append(rec)
    return recs

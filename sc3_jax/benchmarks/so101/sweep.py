"""``sc3 sweep so101``: the SO-101 benchmark's protocol, one command. Policies act in the simulator and inside the
world model from the same initial conditions; the imagined outcomes, scored by a success detector trained on the
collected data's own labels or by any scorer (``--scorer``, e.g. ``sc3_jax.benchmarks.so101.scorer:block_at_goal``,
which reads where the block and the goal are), are compared with the simulator's (r and MMRV with intervals, against the policy-blind
floor and a split-half real-vs-real ceiling: ``report_episodes.py``).

    OUT/initial_conditions/   an episode store: per evaluation seed, the frame at the simulator's reset and the frame
                              after one HOLD step (the world model's two context frames) with the 14-D state
    OUT/real.csv              per policy and seed, the simulator's success (``info["succeed"]``) within the horizon
                              (a policy given by --lerobot-eval: lerobot-eval's, its eval_info.json kept in
                              OUT/lerobot_eval/NAME/)
    OUT/scorer_check.json     the scorer's verdict on those real episodes' frames against the simulator's
    OUT/real_frames/          per policy and seed, the real frames at the times the report's "objects kept" row
                              reads (measures/permanence.py), so that it compares them with the imagined ones
    OUT/results.jsonl ...     the imagined rollouts (``evaluation/ic_sweep.py``'s store), OUT/report/

Initial conditions are identical: the simulator is reset at seed ``EVAL_SEED0 + i`` and stepped once with ``HOLD``;
the real episode starts there, and those two frames are the imagined one's context. Both run ``episode_seconds``
(the world model's rollout horizon, 12 s = 120 steps); a real episode ends early when the simulator says done, an
imagined one is done when the detector sees the task done (``success_detector.decide``). Every step resumes what
exists (conditions, real outcomes, rollouts).
"""
from __future__ import annotations

import csv
import dataclasses
import math
from pathlib import Path

import numpy as np

from sc3_jax.core import atomic
from sc3_jax.core.errors import UserError
from sc3_jax.evaluation.world_model_defaults import SamplerSteps

from . import lerobot_outcomes

EVAL_SEED0 = 20_000_000  # as `sc3 so101 zoo-eval`: neither the collection's training nor held-out seeds
HOLD_STEPS = 1  # one step from the reset gives the world model's second context frame (and opens the gripper)
REAL_FILE, CHECK_FILE, IC_DIR = "real.csv", "scorer_check.json", "initial_conditions"
BENCHMARK = "so101"  # whose scene measure `sc3 report` reads the kept real frames with (REAL_FRAMES/scene.json)


@dataclasses.dataclass(frozen=True, kw_only=True)
class So101SweepConfig(SamplerSteps):
    """The SO-101 policies in the simulator and inside the world model from the same seeds, then the report
    (docs/so101.md). Resumable: rerun the same command. Sampled as every sweep samples (--sample-steps,
    --inverse-steps: sc3_jax/evaluation/world_model_defaults.py)."""

    world_model: str
    """an SO-101 world model: a `sc3 train --config so101_latent` run or its export"""
    out: str
    """results: initial_conditions/, real.csv, scorer_check.json, results.jsonl, rollouts/, report/"""
    detector: str | None = None
    """the success detector that scores imagined rollouts (`sc3 train-detector` on the imported collection)"""
    scorer: str | None = None
    """instead of --detector, any scorer spelling (package.module:attr), e.g.
    sc3_jax.benchmarks.so101.placed:block_placed (the simulator's rule on the zoo estimator's block and goal and
    the state's jaw: 0.98 agreement on real episodes) or sc3_jax.benchmarks.so101.scorer:block_at_goal (the block's
    colour at rest on the goal disc)"""
    policies: tuple[str, ...] = ()
    """the policies, any spelling `sc3 sweep` takes (an SO-101 zoo name, lerobot:PATH, module:attr; none: the zoo)"""
    lerobot_eval: tuple[str, ...] = ()
    """NAME=EVAL_INFO: policy NAME's real outcomes read from the real `lerobot-eval --env.type=sc3_so101 --seed=0`
    (its eval_info.json; episode i is this sweep's condition i) instead of run here; kept as
    OUT/lerobot_eval/NAME/eval_info.json beside report/ (benchmarks/so101/lerobot_outcomes.py)"""
    episodes: int = 36
    """initial conditions (simulator seeds 20000000+i) per policy"""
    episode_seconds: float | None = None
    """horizon of both rollouts (None: the world model's rollout.episode_seconds)"""
    batch: int = 6
    """initial conditions per world-model call"""
    workers: int = 1
    """simulator processes for the real rollouts"""
    learned_state: bool = True
    """hand the policies the world model's learned 14-D state (state_head.npz)"""
    progress: bool = True
    """progress bars on stderr (--no-progress: none, for batch logs)"""


def run(cfg: So101SweepConfig) -> Path:
    """Every stage (see the module docstring); returns OUT."""
    from sc3_jax.model import checkpoint
    from sc3_jax.evaluation import engine, ic_sweep
    from sc3_jax.evaluation.scorers import DETECTOR_PREFIX, load_outcome_scorer

    from .zoo import ZOO, named_policy

    if cfg.episodes < 1 or cfg.batch < 1 or cfg.workers < 1:
        raise UserError(f"--episodes {cfg.episodes} --batch {cfg.batch} --workers {cfg.workers}: each at least 1")
    if (cfg.detector is None) == (cfg.scorer is None):
        raise UserError("name what scores the imagined rollouts: --detector DET or --scorer package.module:attr")
    out = Path(cfg.out)
    spec = f"{DETECTOR_PREFIX}{cfg.detector}" if cfg.detector else cfg.scorer
    scorer = load_outcome_scorer(spec)  # a bad path or name: one line before anything runs
    wcfg = checkpoint.read_config(cfg.world_model)
    check_model(cfg.world_model, wcfg)  # before anything is written: a refused sweep left initial_conditions/ behind
    seconds = cfg.episode_seconds or wcfg.rollout.episode_seconds
    steps = int(round(seconds * wcfg.rollout.control_hz))
    names = list(cfg.policies or ZOO)
    # a wrong name: one line here, not a traceback from a simulator worker; each name a folder of real_frames/ and
    # rollouts/ (the sweep engine's one resolution)
    engine.resolve_policies(names, named_policy)
    given = lerobot_real(cfg.lerobot_eval, names, cfg.episodes)  # read and checked before anything runs
    seeds = [EVAL_SEED0 + i for i in range(cfg.episodes)]
    out.mkdir(parents=True, exist_ok=True)
    views, size = tuple(wcfg.data.views), tuple(wcfg.data.image_size)  # the world model's cameras, as it saw them
    write_conditions(out / IC_DIR, seeds, size, views)
    real_outcomes(out, names, seeds, steps, size, views, scorer, cfg.workers, cfg.progress,
                  wcfg.rollout.control_hz, given={n: done for n, (done, _) in given.items()})
    for name, (_, info) in given.items():  # once real.csv holds its outcomes (a store's other evaluation: refused)
        lerobot_outcomes.keep(out, name, info)
    ic_cfg = ic_sweep.ICSweepConfig(
        initial_conditions=str(out / IC_DIR), world_model=cfg.world_model, policies=tuple(names),
        scorer=spec, out=str(out), episodes=cfg.episodes, calibration_episodes=0,
        real=(str(out / REAL_FILE),), sample_steps=cfg.sample_steps, inverse_steps=cfg.inverse_steps,
        episode_seconds=seconds, taus=(math.inf,), batch=cfg.batch, learned_state=cfg.learned_state,
        progress=cfg.progress)
    return ic_sweep.run(ic_cfg, named=named_policy)


def check_model(path: str, wcfg) -> None:
    """A world model of the SO-101 table, as far as the conditions need: cameras the simulator renders, its frame
    rate and 4-D velocity actions; else one line before the conditions are written (or the real rollouts run)."""
    from .collect import FPS
    from .env import CAMERAS

    views = list(wcfg.data.views)
    if any(v not in CAMERAS and v != "front" for v in views):
        raise UserError(f"{path}/config.json: data.views {views}, the SO-101 simulator renders "
                        f"{['front', *CAMERAS]}: give a world model of the SO-101 table (`sc3 train --config "
                        "so101_latent`)")
    if wcfg.data.fps is not None and abs(float(wcfg.data.fps) - FPS) > 1e-9:
        raise UserError(f"{path}/config.json: data.fps {wcfg.data.fps:g}, the SO-101 simulator's episodes are at "
                        f"{FPS:g} fps: give a world model of the SO-101 table (`sc3 train --config so101_latent`)")
    if wcfg.model.action_dim != 4:
        raise UserError(f"{path}/config.json: model.action_dim {wcfg.model.action_dim}, the SO-101 benchmark's "
                        "actions are 4-D (dx, dy, dz, gripper): give a world model of the SO-101 table")


def lerobot_real(specs: tuple[str, ...], names: list[str], episodes: int) -> dict[str, tuple[list[bool], dict]]:
    """``--lerobot-eval NAME=EVAL_INFO`` -> {NAME: (its first ``episodes`` successes, the eval_info)}: NAME one of the
    sweep's policies (as recorded), each once."""
    recorded = [_name(n) for n in names]
    given: dict[str, tuple[list[bool], dict]] = {}
    for spec in specs:
        name, path = lerobot_outcomes.parse(spec)
        if name not in recorded:
            raise UserError(f"--lerobot-eval {spec}: {name!r} is not one of the sweep's policies {recorded}")
        if name in given:
            raise UserError(f"--lerobot-eval {spec}: {name!r} is given twice")
        given[name] = lerobot_outcomes.successes(path, episodes)
    return given


def write_conditions(root: Path, seeds: list[int], image_size: tuple[int, int], views: tuple[str, ...]) -> None:
    """One episode per seed (``seed<SEED>``): the reset frame and state, then those after ``HOLD_STEPS`` of HOLD."""
    from sc3_jax.data.action_space import ActionSpace
    from sc3_jax.data.episodes import Episode, EpisodeStore

    from .collect import FPS, TASK
    from .env import ACTION_NAMES, STATE_NAMES, So101Env
    from .rollouts import HOLD

    store = EpisodeStore(root, views=list(views), fps=FPS, image_size=image_size, create=True,
                         action_space=ActionSpace("velocity", 4, tuple(ACTION_NAMES), (3,)), state_dim=len(STATE_NAMES),
                         state_names=list(STATE_NAMES), has_pose=False)
    todo = [s for s in seeds if f"seed{s}" not in store]
    if not todo:
        return
    env = So101Env(image_size, views=views)
    try:
        for s in todo:
            obs = env.reset(s)
            frames, states = [env.render_views()], [obs["agent_pos"]]
            for _ in range(HOLD_STEPS):
                obs, _, _ = env.step(HOLD)
                frames.append(env.render_views())
                states.append(obs["agent_pos"])
            f = np.stack(frames, 1)  # [V, T, H, W, 3]
            store.write(Episode(f"seed{s}", dict(zip(views, f)), np.repeat(HOLD[None], len(frames), 0), None,
                                TASK, {"seed": s, "source": "so101 reset + hold"},
                                np.stack(states).astype(np.float32)))
    finally:
        env.close()


def real_outcomes(out: Path, names: list[str], seeds: list[int], steps: int, image_size: tuple[int, int],
                  views: tuple[str, ...], scorer, workers: int, progress: bool, hz: float = 10.0,
                  given: dict[str, list[bool]] | None = None) -> None:
    """Append to OUT/real.csv (policy, episode, success) the (policy, seed) episodes it lacks, and the scorer's
    verdicts on their frames to OUT/scorer_check.json (per policy: agreement of the scorer with the simulator).
    ``given``: policies whose outcomes per seed are known already (``lerobot-eval``'s, ``lerobot_real``), written as
    they are, without a run here (and so without frames for the scorer check or the report's real frames)."""
    from tqdm import tqdm

    from .rollouts import Job, Setup, run_episodes

    path, check_path = out / REAL_FILE, out / CHECK_FILE
    rows: list[dict] = []
    if path.is_file():
        with open(path, newline="") as f:
            rows = list(csv.DictReader(f))
    have = {(r["policy"], r["episode"]) for r in rows}
    given = given or {}
    for n, done in given.items():  # a resumed store keeps what it holds: another evaluation's outcomes are refused
        held = {r["episode"]: r["success"] for r in rows if r["policy"] == n}
        if any(held.get(f"seed{s}", str(d).lower()) != str(d).lower() for s, d in zip(seeds, done)):
            raise UserError(f"--lerobot-eval {n}=...: {path} holds other real outcomes of {n!r}; another "
                            "evaluation goes in another --out")
    added = [{"policy": n, "episode": f"seed{s}", "success": str(done[i]).lower()} for n, done in given.items()
             for i, s in enumerate(seeds) if (n, f"seed{s}") not in have]
    rows += added
    jobs = [Job(s, policy=n) for n in names for s in seeds
            if _name(n) not in given and (_name(n), f"seed{s}") not in have]
    if not jobs:
        if added:
            _write_real(path, rows)
        return
    check = atomic.read_json(check_path)["per_policy"] if check_path.is_file() else {}
    setup = Setup(image_size, views, max_steps=steps, record=True, hold=HOLD_STEPS)
    try:
        for job, r in zip(jobs, tqdm(run_episodes(jobs, setup, workers), total=len(jobs), desc="real rollouts",
                                     unit="episode", disable=not progress)):
            said = _says_done(scorer, r.frames, r.states, r.seed)
            keep_real_frames(out, _name(job.policy), f"seed{job.seed}", r.frames, hz)
            rows.append({"policy": _name(job.policy), "episode": f"seed{job.seed}",
                         "success": str(r.succeeded).lower()})
            c = check.setdefault(_name(job.policy), {"agree": 0, "n": 0, "sim_done": 0, "scorer_done": 0})
            c["n"], c["agree"] = c["n"] + 1, c["agree"] + (said == r.succeeded)
            c["sim_done"], c["scorer_done"] = c["sim_done"] + r.succeeded, c["scorer_done"] + said
    finally:  # what finished is kept (a rerun runs the rest)
        _write_real(path, rows)
        total = {k: sum(c[k] for c in check.values()) for k in ("agree", "n", "sim_done", "scorer_done")}
        atomic.write_json(check_path, {"per_policy": check, "all": total,
                                       "agreement": total["agree"] / max(total["n"], 1),
                                       "what": "the scorer on the real episodes' frames (the rule it scores imagined "
                                               "rollouts with) against the simulator's success"})


def _write_real(path: Path, rows: list[dict]) -> None:
    atomic.write_text(path, "policy,episode,success\n" + "".join(
        f"{r['policy']},{r['episode']},{r['success']}\n" for r in rows))


def keep_real_frames(out: Path, policy: str, episode: str, frames: np.ndarray, hz: float) -> None:
    """``OUT/real_frames/POLICY/EPISODE.npz``: the real episode's frames [V, n, H, W, 3] at the report's times
    (``at``: model steps after the last context frame; past the episode's end, its last frame: the simulator ends an
    episode on success and the scene then stays as it is)."""
    from sc3_jax.measures import permanence
    from sc3_jax.evaluation.report_episodes import REAL_FRAMES
    from sc3_jax.core.safe_names import join_inside

    at = np.array(sorted(set(permanence.times(hz).values())), np.int64)
    sel = np.moveaxis(frames[np.minimum(at, len(frames) - 1)], 1, 0)
    root = out / REAL_FRAMES
    if not (root / "scene.json").is_file():
        atomic.write_json(root / "scene.json", {"benchmark": BENCHMARK})
    atomic.save_npz(join_inside(root, policy, f"{episode}.npz"), frames=sel, at=at, hz=np.float64(hz))


def _name(spec: str) -> str:
    """The name a policy spec is recorded under (``NAME=SPEC``: NAME), as the imagined sweep records it."""
    from sc3_jax.policies.resolve import parse

    name, body, _ = parse(spec)
    return name or body


def _says_done(scorer, frames: np.ndarray, states: np.ndarray, seed: int) -> bool:
    """The scorer's verdict on a real episode's frames [T, V, H, W, 3] and states [T, 14] (any criterion done: the
    task's one)."""
    from sc3_jax.evaluation.scorers import RolloutView

    return any(scorer(RolloutView(f"seed{seed}", np.moveaxis(frames, 1, 0), state=states)).values())

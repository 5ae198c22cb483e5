"""``sc3 rollout --world-model WM --policy P --data IC --out DIR [--SECTION.FIELD VALUE ...]``:
closed-loop (and optionally offline) rollouts of a policy inside a trained world model -> arrays, videos and a
summary (sc3_jax/rollout/rollout_io.py, sc3_jax/evaluation/rollout_summary.py, docs/rollout.md).

Writes ``OUT/rollout.npz`` (every array of ``Rollout.run``, see sc3_jax/rollout/rollout.py), ``OUT/summary.json``, one
``OUT/<episode>_<view>.mp4`` per episode and view (context frames, then the kept frames up to termination) and, with
``--offline`` (episode stores only), ``OUT/offline.npz`` with PSNR per frame and view against the recorded frames."""
from __future__ import annotations

import dataclasses
import math
from pathlib import Path

from sc3_jax.commands import parse_evaluated
from sc3_jax.evaluation.world_model_defaults import SamplerSteps

SUMMARY = "closed-loop and offline rollouts of a policy inside a world model"  # the line `sc3 --help` shows


@dataclasses.dataclass(frozen=True)
class Args(SamplerSteps):
    """Closed-loop rollouts of a policy inside a trained world model, sampled as `sc3 sweep` samples it (its sampler
    steps, horizon and U units: sc3_jax/evaluation/world_model_defaults.py; --sample-steps None: the model's own). Every
    field of the world model's config is an option: --SECTION.FIELD VALUE, e.g. --rollout.tau 0.05
    --rollout.episode-seconds 6 (the list: `sc3 train --help`)."""

    world_model: str
    """a saved world model: a `sc3 train` workdir or an exported one (config.json, norm_stats.json, checkpoints/ or
    params.npz)"""
    policy: str
    """a zoo name | zero | random | linear (built-in JAX policies) | ws://HOST:PORT (an openpi policy server, see
    --family) | package.module:attr (a JaxPolicy / HostPolicy or a zero-argument factory of one): every spelling of
    policies/resolve.py"""
    data: str
    """initial conditions: an episode store (its first K frames at the rollout stride from --start, and the pose at
    the last of them) or an .npz with frames uint8 [B, V, K, H, W, 3], state float32 [B, A] (A: the model's action
    dimension) and optionally task int32 [B]"""
    out: str
    """output directory: rollout.npz, summary.json, the videos (and offline.npz)"""
    step: int | None = None
    """checkpoint step of a training workdir (None: the latest)"""
    family: str = "native"
    """openpi observation mapping for ws:// policies: native, droid, libero or aloha (docs/openpi.md). With an episode
    store, the server gets each episode's own instruction and its cameras by the model's view names"""
    episodes: int | None = None
    """use the first N initial conditions (None: all)"""
    start: int = 0
    """first frame of the initial context in each stored episode"""
    task: int = 0
    """task id given to the policy (episode stores carry none; a mapped ws:// policy gets the episodes' prompts, and
    for an .npz the --benchmark's prompt of its task ids, else none)"""
    batch: int | None = None
    """episodes per jitted call (None: all at once)"""
    data_fps: float | None = None
    """frame rate the model was trained at (None: the world model's own, config.json data.fps; a store at another
    rate is refused)"""
    seed: int = 0
    """sampler and policy noise: episode i's draws depend only on (seed, i)"""
    offline: bool = False
    """also replay the recorded actions open loop and compare with the recorded frames (episode stores only)"""
    perception: str | None = None
    """weights for the benchmark's outcome scorer, the success estimate's (None: the benchmark's own)"""
    benchmark: str = "none"
    """whose outcome scorer makes the success estimate and whose policy names --policy takes: a benchmark's name
    (sc3_jax/evaluation/benchmark.py: bussing, the simulated benchmark's perception and zoo; so101) or
    package.module:attr; none: no success estimate and only the built-in policy spellings, since a model of any
    robot can be rolled out"""
    learned_state: bool = True
    """hand the policy the world model's learned robot state where it has one (state_head.npz); --no-learned-state:
    the integrated commands (exact for absolute targets, or velocities of the recorded state)"""
    video: bool = True
    """one mp4 per episode and view (--no-video: none)"""
    progress: bool = True
    """progress bars on stderr (--no-progress: none, for batch logs)"""


# each numeric option's bounds (low, high, what): one line at the door, before the model loads
BOUNDS = {"episodes": (1, 10**6, "initial conditions"), "start": (0, 10**7, "a frame index"),
          "task": (0, 2**31 - 1, "a task id"), "batch": (1, 4096, "episodes per call"),
          "data_fps": (1e-3, 10_000, "frames per second"), "seed": (0, 2**32 - 1, "a seed"),
          "step": (0, 10**12, "a checkpoint step"), "sample_steps": (1, 1000, "sampler steps"),
          "inverse_steps": (1, 1000, "sampler steps")}


def check_options(a: Args) -> None:
    """Every numeric option within ``BOUNDS`` (``--episodes -1`` ran 15 of 16 episodes, ``--start -5`` started at
    frame 75), and --out a directory it can make, before anything loads."""
    from sc3_jax.core import validate

    for name, (low, high, what) in BOUNDS.items():
        value = getattr(a, name)
        if value is not None:
            validate.in_range(f"--{name.replace('_', '-')}", value, low, high, what)
    validate.out_dir(a.out, "--out")


def benchmark_of(name: str):
    """The benchmark ``--benchmark`` names; "none": one with no scorer and no policy names, as sc3 diagnose reads
    it (its success estimate then says there is none)."""
    from sc3_jax.evaluation import benchmark

    return benchmark.get_or_none(name)


def main(argv: list[str]) -> int:
    a, cfg = parse_evaluated(Args, argv, "rollout")
    check_options(a)
    import numpy as np

    from sc3_jax.core import atomic
    from sc3_jax.model import checkpoint
    from sc3_jax.rollout import rollout, rollout_io, state_head
    from sc3_jax.core.errors import UserError
    from sc3_jax.evaluation import rollout_summary
    from sc3_jax.evaluation.diagnose_outcomes import no_scorer
    from sc3_jax.policies.openpi_mappings import for_world_model, get_mapping
    from sc3_jax.policies.resolve import resolve

    rollout_io.check_seconds(cfg.rollout.episode_seconds)
    tau = cfg.rollout.tau  # -1 stopped every episode at its first chunk, nan never, both with exit 0
    if tau is not None and (not isinstance(tau, (int, float)) or math.isnan(tau) or tau < 0):
        raise UserError(f"--rollout.tau {tau}: a threshold is a non-negative number (inf: never stop)")
    bm = benchmark_of(a.benchmark)  # an unknown name: one line before the model loads
    stats = checkpoint.read_norm_stats(a.world_model)
    if Path(a.data).suffix != ".npz":  # the store against the model's views and image size before its params load
        from sc3_jax.data.shape import check_shape  # (a config.json image size the data lacks: a params.npz error)

        check_shape(cfg, a.data)
    params = checkpoint.load_params(a.world_model, cfg, a.step)
    fps = rollout_io.data_fps(a.world_model, a.data_fps)
    ro = rollout.Rollout(cfg, stats, data_fps=fps, head=state_head.load(a.world_model) if a.learned_state else None)
    ids, ics, store = rollout_io.load_initial_conditions(a.data, cfg, ro.spec, a.episodes, a.start, a.task)
    family = a.family
    if store is not None and get_mapping(a.family) is not None:
        # an openpi server reads each episode's own instruction (not a mapping's table by --task), and its
        # cameras by the model's view names where it has them (as `sc3 sweep episodes --data` sends them)
        prompts = [atomic.read_json(store.root / e / "meta.json").get("prompt", "") for e in ids]
        table = list(dict.fromkeys(prompts))
        ics = ics._replace(task=np.asarray([table.index(p) for p in prompts], np.int32))
        family = for_world_model(a.family, tuple(cfg.data.views), table, f"--family {a.family}")
    elif get_mapping(a.family) is not None and bm.prompts:  # an .npz's task ids: the benchmark's words for them
        family = get_mapping(a.family).replace(prompts=dict(bm.prompts))
    try:  # an unknown name, or a module:attr that is no policy: one line, before anything compiles
        policy = resolve(a.policy, cfg.rollout.policy_chunk, family, action_space=stats.action_space,
                         named=bm.named_policy, num_views=len(cfg.data.views)).policy
    except (ValueError, TypeError, ConnectionError, TimeoutError) as e:  # a ws:// server not there, too
        if isinstance(e, UserError):
            raise
        raise UserError(f"--policy {a.policy}: {' '.join(str(e).split())}") from None
    n, s, tau = len(ids), ro.spec, ro.tau
    size = a.batch or n
    rollout_io.check_horizon(s, cfg.rollout.episode_seconds, min(size, n))
    out = Path(a.out)
    keys = np.asarray(rollout.episode_keys(a.seed, n))
    result = rollout_io.closed_loop(ro, params, policy, ics, keys, tau, size, a.progress)
    rollout_summary.check_result(result, a.policy)  # before anything is written
    out.mkdir(parents=True, exist_ok=True)
    atomic.save_npz(out / "rollout.npz", **result, episode_ids=np.asarray(ids))
    u = rollout_summary.u_summary(result, tau, cfg.rollout.tau_units)
    summary = {"episodes": ids, "policy": a.policy, "seed": a.seed, "num_chunks": s.num_chunks, "keep_frames": s.keep,
               "stride": s.stride, "control_hz": cfg.rollout.control_hz, "episode_seconds": cfg.rollout.episode_seconds,
               # the sampler as it ran: forward-dynamics steps, and those of the re-read that yields U
               "sample_steps": s.steps, "inverse_steps": s.inverse_steps or s.steps,
               "termination_rate": result["termination_rate"], "terminated_at": result["terminated_at"].tolist(),
               "mean_u": u.pop("u_mean_per_episode"), **u,
               "success": rollout_summary.success_estimate(result, ids, store, cfg, bm.outcome_scorer or no_scorer,
                                                       a.perception)}
    if a.video:
        summary["videos"] = rollout_io.write_videos(out, ids, result, cfg.data.views, cfg.rollout.control_hz)
    if a.offline:
        off, targets, n_off = rollout_summary.offline(cfg, stats, params, store, ids, fps, s, a.start, a.task, keys,
                                                      size, a.progress)
        atomic.save_npz(out / "offline.npz", **off, targets=targets, episode_ids=np.asarray(ids))
        summary["offline_psnr_per_view"] = dict(zip(cfg.data.views, np.nanmean(off["psnr_view"], 0).tolist()))
        summary["offline_chunks"] = n_off
    atomic.write_json(out / "summary.json", summary)
    print("\n".join(_report(summary, out, a)))
    return 0


def _report(sm: dict, out: Path, a: Args) -> list[str]:
    """What the rollouts did, what the numbers mean, and where they are."""
    n = len(sm["episodes"])
    lines = [f"rollout: {n} episodes of {a.policy} x {sm['num_chunks']} chunks of {sm['keep_frames']} frames "
             f"({sm['episode_seconds']:g} s at {sm['control_hz']:g} Hz), {sm['sample_steps']} sampler steps, U re-read "
             f"in {sm['inverse_steps']}",
             f"U_chunk ({sm['tau_units']} action units; the policy's actions against those re-read from the imagined "
             f"frames, lower = the model followed them): mean {sm['u_mean']:.4f}, median {sm['u_median']:.4f}, "
             f"max {sm['u_max']:.4f} over the chunks run",
             f"stopped at tau = {sm['tau']:g}: {sm['stopped']} of {n} episodes"
             + (f" (in chunk {sm['stopped_at_chunk_mean'] + 1:.1f} of {sm['num_chunks']} on average; that chunk's "
                "frames and the later ones are not kept)" if sm["stopped"] else "")]
    sc = sm["success"]
    if sc["available"]:
        im, rec = sc["imagined"], sc["recorded_physics"]
        lines.append(f"success estimate ({a.benchmark}'s scorer on the imagined frames, {im['n_objects']} objects in "
                     f"{sc['episodes']} episodes): " + _rates(im))
        if rec:
            lines.append("  for reference, the recorded episodes from the same starts (their own actions, physics): "
                         + _rates(rec))
    else:
        lines.append(f"no success estimate: {sc['note']}")
    if "offline_psnr_per_view" in sm:
        lines.append(f"offline replay of the recorded actions ({sm['offline_chunks']} chunks), PSNR against the "
                     "recorded frames: " + ", ".join(f"{k} {v:.2f} dB" for k, v in sm["offline_psnr_per_view"].items()))
    wrote = ["rollout.npz", "summary.json"] + (["offline.npz"] if a.offline else [])
    lines.append(f"wrote {out}/: " + ", ".join(wrote) + (f", {len(sm['videos'])} videos (<episode>_<view>.mp4)"
                                                          if a.video else ""))
    return lines


def _rates(r: dict) -> str:
    return ", ".join(f"{c} {v:.2f}" for c, v in r.items() if c != "n_objects")  # the criteria, in their order

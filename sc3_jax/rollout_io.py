"""What ``sc3 rollout`` needs around ``rollout.Rollout``: initial conditions from an episode store or an ``.npz``,
rollouts in batches of episodes, the offline replay of the recorded actions, videos, and the figures its summary
reports (U_chunk, termination, a perception-scored success estimate)."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from sc3_jax import atomic
from sc3_jax.errors import UserError


def load_initial_conditions(path: str, cfg, spec, episodes: int | None, start: int, task: int):
    """(ids, InitialConditions, store or None) of an episode store (its first K frames at the rollout stride from
    frame ``start``, and the state measured at the last of them) or an ``.npz`` with ``frames`` uint8 [B, V, K, H, W, 3],
    ``state`` float32 [B, A] (the model's imagined state: A = its action dimension), optionally ``task`` int32 [B] and
    ``robot`` float32 [B, S] (the robot's state, for a world model with a learned state); the first ``episodes`` of
    them (None: all)."""
    from sc3_jax import rollout

    p = Path(path)
    if p.suffix == ".npz":
        with atomic.open_npz(p, "write the initial conditions again") as z:
            n = len(z["frames"]) if episodes is None else min(episodes, len(z["frames"]))
            tasks = z["task"][:n] if "task" in z else np.full(n, task, np.int32)
            robot = z["robot"][:n].astype(np.float32) if "robot" in z else None
            ics = rollout.InitialConditions(z["frames"][:n], z["state"][:n].astype(np.float32), tasks.astype(np.int32),
                                            robot)
        return [f"ic{i:04d}" for i in range(n)], ics, None
    from sc3_jax.data.episodes import EpisodeStore

    from sc3_jax.data.shape import check_shape

    store = EpisodeStore(p)
    check_shape(cfg, store)  # views, image size, action dimension: one line naming both sides, before any compile
    if abs(float(store.fps) - float(spec.data_fps)) > 1e-9:
        raise UserError(f"{p}/dataset.json: episodes at {store.fps} fps, the world model's rollout runs on data at "
                        f"{spec.data_fps} fps (its config.json data.fps): give episodes at its frame rate")
    if spec.state_dim and store.state_dim != spec.state_dim:
        raise UserError(f"{p}: the world model's learned state is {spec.state_dim}-D, this store records "
                        f"{'no state' if not store.state_dim else f'a {store.state_dim}-D one'} (dataset.json "
                        "\"state\"): give held-out episodes of the robot it was trained on")
    ids = store.episode_ids()[:episodes]
    if not ids:
        raise UserError(f"{p}: no episodes")
    K, s = spec.context, spec.stride
    items = []
    for eid in ids:
        ep = store.load(eid)
        idx = [start + s * i for i in range(K)]
        if idx[-1] >= ep.length:
            raise UserError(f"{p}: episode {eid} has {ep.length} frames, the initial context needs frame {idx[-1]}; "
                            "give a smaller --start")
        frames = np.stack([np.asarray(ep.frames[v])[idx] for v in cfg.data.views])
        robot = np.asarray(ep.state[idx[-1]], np.float32) if spec.state_dim else None
        items.append((frames, rollout.initial_state(ep, spec, idx[-1]), np.int32(task), robot))
    return ids, rollout.stack_initial_conditions(items), store


def data_fps(source: str, given: float | None) -> float:
    """The frame rate the model was trained at: ``given``, else what ``source`` records -- a saved world model its
    own (``checkpoint.read_robot``: config.json's data.fps), an episode store its dataset.json's -- else a one-line
    UserError (no frame rate is assumed)."""
    if given is not None:
        return given
    p = Path(source)
    if (p / "config.json").is_file():
        from sc3_jax import checkpoint
        return checkpoint.read_robot(p).fps
    meta = p / "dataset.json"
    if meta.exists():
        return atomic.read_json(meta, "restore it (the episode store's metadata)")["fps"]
    raise UserError(f"{source}: neither a saved world model nor an episode store, so no frame rate to read: give "
                    "--data-fps (the frame rate of the data the world model was trained on)")


def write_videos(out: Path, ids, result: dict, views, fps: float) -> list[str]:
    """One mp4 per episode and view: the context frames, then the kept frames up to termination."""
    from sc3_jax.video import write_mp4

    written = []
    for b, eid in enumerate(ids):
        valid = result["frame_valid"][b]
        for v, view in enumerate(views):
            path = out / f"{eid}_{view}.mp4"
            write_mp4(path, np.concatenate([result["initial_frames"][b, v], result["frames"][b, v][valid]]), fps)
            written.append(path.name)
    return written


def run_batched(fn, n: int, size: int, progress: bool, desc: str) -> dict:
    """Run ``fn(slice)`` over batches of ``size`` episodes and concatenate the per-episode arrays; adds
    ``termination_rate`` (the fraction of episodes whose ``done`` ever turned on)."""
    parts = []
    it = [slice(i, min(i + size, n)) for i in range(0, n, size)]
    if progress:
        from tqdm import tqdm
        it = tqdm(it, desc=desc, unit="batch")
    for sl in it:
        parts.append(fn(sl))
    out = {}
    for k, v in parts[0].items():
        out[k] = np.concatenate([p[k] for p in parts]) if isinstance(v, np.ndarray) and v.ndim > 0 else v
    out["termination_rate"] = float(out["done"].any(-1).mean())
    return out


def closed_loop(ro, params, policy, ics, keys, tau: float, size: int, progress: bool) -> dict:
    """``policy`` acting inside the world model from ``ics``, ``size`` episodes per jitted call: JAX policies run
    inside the scan, host policies between jitted chunk steps."""
    from sc3_jax.policies.base import JaxPolicy

    pick = ics.take
    if isinstance(policy, JaxPolicy):
        return run_batched(lambda sl: ro.run(params, policy, pick(sl), keys[sl], tau), len(keys), size, progress,
                           "rollout")
    return run_batched(lambda sl: ro.run_host(params, policy, pick(sl), keys[sl], tau, progress=progress,
                                              skip_done=True), len(keys), size, False, "rollout")


def offline(cfg, stats, params, store, ids, fps: float, spec, start: int, task: int, keys, size: int,
            progress: bool) -> tuple[dict, np.ndarray, int]:
    """The recorded actions replayed open loop from each episode's start, as many chunks as every episode supports
    (at most the closed-loop ``spec``'s): (the rollout's arrays with ``psnr`` [B, V, T] and ``psnr_view`` [B, V] against the
    recorded frames, those frames, the chunks run)."""
    from sc3_jax import rollout
    from sc3_jax.evaluate.metrics import psnr_by_view

    if store is None:
        raise UserError("--offline replays recorded actions: give an episode store as --data")
    eps = [store.load(e) for e in ids]
    n_off = min(min(rollout.max_offline_chunks(ep.length, spec, start) for ep in eps), spec.num_chunks)
    if n_off < 1:
        raise UserError(f"{store.root}: episodes too short for one offline chunk from frame {start}")
    ro = rollout.Rollout(cfg, stats, data_fps=fps, num_chunks=n_off)
    items = [rollout.from_episode(ep, cfg.data.views, ro.spec, start, task) for ep in eps]
    ics = rollout.stack_initial_conditions([it[0] for it in items])
    acts, tgts = np.stack([it[1] for it in items]), np.stack([it[2] for it in items])
    pick = ics.take
    off = run_batched(lambda sl: ro.run_offline(params, pick(sl), acts[sl], keys[sl], math.inf), len(ids), size,
                      progress, "offline")
    off["psnr"], off["psnr_view"] = (x.astype(np.float32) for x in psnr_by_view(off["frames"], tgts,
                                                                                 off["frame_valid"]))
    return off, tgts, n_off


def u_summary(result: dict, tau: float, tau_units: str) -> dict:
    """U_chunk in ``tau_units`` over every chunk run (chunks after termination are not run), and how many episodes
    stopped at tau and after how many chunks."""
    u = result["u_raw" if tau_units == "raw" else "u"]  # [B, N]
    ran = np.ones(u.shape, bool)
    for b, t in enumerate(result["terminated_at"]):
        if t >= 0:
            ran[b, t + 1:] = False  # the terminating chunk itself ran (its U is what stopped it)
    vals = u[ran]
    stopped = result["terminated_at"][result["terminated_at"] >= 0]
    return {"tau": tau, "tau_units": tau_units, "u_mean": float(vals.mean()), "u_median": float(np.median(vals)),
            "u_max": float(vals.max()), "u_mean_per_episode": [float(u[b][ran[b]].mean()) for b in range(len(u))],
            "stopped": int(len(stopped)),
            "stopped_at_chunk_mean": float(stopped.mean()) if len(stopped) else None}


def success_estimate(result: dict, ids, store, cfg, scorer_for, perception: str | None = None) -> dict:
    """The benchmark's scorer (``scorer_for(views, image_size, weights)``, as ``diagnose.diagnose`` takes it) on each
    imagined rollout (its last context frame, then its frames up to termination,
    as the sweep reads online rollouts): per-criterion success over the objects named by the episodes' meta.
    ``{"available": False, "note": why}`` when the model's frames are not the scorer's or no object is named."""
    from sc3_jax.evaluate.diagnose_outcomes import episode_objects, success_rates
    from sc3_jax.evaluate.scorers import RolloutView

    if store is None:
        return {"available": False, "note": "an .npz of initial conditions names no objects to score"}
    scorer, note = scorer_for(cfg.data.views, cfg.data.image_size, perception)
    if scorer is None:
        return {"available": False, "note": note}
    imagined, recorded = [], []
    for b, eid in enumerate(ids):
        ep = store.load(eid)
        objects, dests, physics = episode_objects(ep.meta)
        if objects is None:
            continue
        frames = np.concatenate([result["initial_frames"][b][:, -1:], result["frames"][b][:, result["frame_valid"][b]]],
                                1)
        imagined.append(scorer.score(RolloutView(eid, frames, objects, dests)))
        if physics is not None:
            recorded.append(physics)
    if not imagined:
        return {"available": False, "note": f"{store.root}: no episode names its objects (meta.labels / "
                                            "meta.initial_condition, as `sc3 sim demos` writes)"}
    return {"available": True, "episodes": len(imagined), "imagined": success_rates(imagined),
            # the recorded episodes' own outcomes: a reference for the same starts, under the recording's policy
            "recorded_physics": success_rates(recorded) if recorded else None}


MAX_EPISODE_SECONDS = 3600.0  # an hour of imagined video per episode: beyond it the frames are the bound


def check_seconds(episode_seconds: float) -> None:
    """``--rollout.episode-seconds`` positive and finite (``-1`` was an IndexError blamed on the policy, ``inf`` an
    OverflowError), at most ``MAX_EPISODE_SECONDS``: checked before the model loads."""
    from sc3_jax.validate import in_range

    in_range("--rollout.episode-seconds", episode_seconds, 1e-3, MAX_EPISODE_SECONDS, "seconds of one episode")


def check_horizon(spec, episode_seconds: float, episodes: int) -> None:
    """The uint8 frames of one batch of ``episodes`` within the machine's available memory (``1e9`` seconds would
    grow until the kernel kills the run)."""
    from sc3_jax.validate import host_available_bytes

    frames = episodes * spec.num_chunks * spec.keep * spec.views * math.prod(spec.image_size) * 3
    avail = host_available_bytes()
    if avail is not None and frames > avail / 2:
        raise UserError(f"--rollout.episode-seconds {episode_seconds:g}: {episodes} episodes' frames need about "
                        f"{frames / 1e9:.1f} GB, this machine has {avail / 1e9:.1f} GB available; give fewer seconds "
                        "or a smaller --batch")


def check_result(result: dict, policy: str) -> None:
    """The policy's actions (and the U they give) finite in every episode, as a sweep requires: else one line,
    nothing written (a NaN in summary.json would read as a number)."""
    from sc3_jax.evaluate.results import check_actions

    u_raw = result.get("u_raw")
    for b in range(len(result["actions"])):
        check_actions(f"{policy}/{b}", result["actions"][b], None if u_raw is None else u_raw[b])


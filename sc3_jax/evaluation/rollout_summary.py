"""``sc3 rollout``'s summaries of a rollout: the offline replay against recorded frames, U_chunk, the success
estimate, the finite-actions check. Over ``rollout_io.py`` (batched runs) and ``rollout.py``; scored with
``evaluate``'s metrics, scorers and outcome labels."""
from __future__ import annotations

import math

import numpy as np

from sc3_jax.core.errors import UserError
from sc3_jax.rollout.rollout_io import run_batched


def offline(cfg, stats, params, store, ids, fps: float, spec, start: int, task: int, keys, size: int,
            progress: bool) -> tuple[dict, np.ndarray, int]:
    """The recorded actions replayed open loop from each episode's start, as many chunks as every episode supports
    (at most the closed-loop ``spec``'s): (the rollout's arrays with ``psnr`` [B, V, T] and ``psnr_view`` [B, V] against the
    recorded frames, those frames, the chunks run)."""
    from sc3_jax.rollout import rollout
    from sc3_jax.measures.metrics import psnr_by_view

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
    from sc3_jax.evaluation.diagnose_outcomes import episode_objects, success_rates
    from sc3_jax.evaluation.scorers import RolloutView

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


def check_result(result: dict, policy: str) -> None:
    """The policy's actions (and the U they give) finite in every episode, as a sweep requires: else one line,
    nothing written (a NaN in summary.json would read as a number)."""
    from sc3_jax.evaluation.results import check_actions

    u_raw = result.get("u_raw")
    for b in range(len(result["actions"])):
        check_actions(f"{policy}/{b}", result["actions"][b], None if u_raw is None else u_raw[b])

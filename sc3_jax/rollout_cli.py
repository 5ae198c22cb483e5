"""``sc3 rollout``: closed-loop (and optionally offline) rollouts of a trained world model -> arrays and videos.

    sc3 rollout --checkpoint runs/tiny --policy zero --initial-conditions runs/synthetic/heldout --out runs/ro \\
        [--episodes 8] [--tau 0.02|inf] [--num-chunks N] [--offline] [--seed 0]

``--checkpoint``: a saved world model (``checkpoint.py``: a training workdir or an exported directory).
``--policy``: any spelling of ``policies/resolve.py``: a zoo name, ``zero`` | ``random`` | ``linear`` (built-in JAX
policies), ``ws://HOST:PORT`` (an openpi policy server, see ``--family``) or ``package.module:attr`` (a JaxPolicy /
HostPolicy, or a zero-argument factory of one). JAX policies run inside the scan; host policies are called between
jitted chunk steps.
``--initial-conditions``: an episode store (its first K frames at the rollout stride and the pose at the last of them)
or an ``.npz`` with ``frames`` uint8 [B, V, K, H, W, 3], ``state`` float32 [B, 7] and optionally ``task`` int32 [B].
Writes ``OUT/rollout.npz`` (every array of ``Rollout.run``, see sc3_jax/rollout.py), ``OUT/summary.json``, one
``OUT/<episode>_<view>.mp4`` per episode and view (context frames, then the kept frames up to termination) and, with
``--offline`` (episode stores only), ``OUT/offline.npz`` with PSNR per frame and view against the recorded frames.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np


def load_initial_conditions(path: str, cfg, spec, episodes: int | None, start: int, task: int):
    """(ids, InitialConditions, store or None)."""
    from sc3_jax import rollout

    p = Path(path)
    if p.suffix == ".npz":
        z = np.load(p)
        n = len(z["frames"]) if episodes is None else min(episodes, len(z["frames"]))
        tasks = z["task"][:n] if "task" in z else np.full(n, task, np.int32)
        ids = [f"ic{i:04d}" for i in range(n)]
        return ids, rollout.InitialConditions(z["frames"][:n], z["state"][:n].astype(np.float32),
                                              tasks.astype(np.int32)), None
    from sc3_jax.data.episodes import EpisodeStore

    store = EpisodeStore(p)
    ids = store.episode_ids()[:episodes]
    if not ids:
        raise ValueError(f"{p}: no episodes")
    K, s = spec.context, spec.stride
    items = []
    for eid in ids:
        ep = store.load(eid)
        idx = [start + s * i for i in range(K)]
        if idx[-1] >= ep.length:
            raise ValueError(f"episode {eid}: {ep.length} frames, the initial context needs frame {idx[-1]}")
        frames = np.stack([np.asarray(ep.frames[v])[idx] for v in cfg.data.views])
        items.append((frames, np.asarray(ep.ee_pose[idx[-1]], np.float32), np.int32(task)))
    return ids, rollout.stack_initial_conditions(items), store


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


def _batches(n: int, size: int):
    for i in range(0, n, size):
        yield slice(i, min(i + size, n))


def _run_batched(fn, n: int, size: int, progress: bool, desc: str) -> dict:
    """Run ``fn(slice)`` over batches of episodes and concatenate the per-episode arrays."""
    parts = []
    it = list(_batches(n, size))
    if progress:
        from tqdm import tqdm
        it = tqdm(it, desc=desc, unit="batch")
    for sl in it:
        parts.append(fn(sl))
    out = {}
    for k, v in parts[0].items():
        out[k] = np.concatenate([p[k] for p in parts]) if isinstance(v, np.ndarray) and v.ndim > 0 else v
    done = out["done"]
    out["termination_rate"] = float(done.any(-1).mean())
    return out


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="sc3 rollout", description=__doc__.split("\n\n")[0])
    p.add_argument("--checkpoint", required=True, help="a training workdir or an exported world model (config.json, "
                   "norm_stats.json, checkpoints/ or params.npz)")
    p.add_argument("--step", type=int, default=None, help="checkpoint step (default: latest)")
    p.add_argument("--policy", required=True, help="a zoo name | zero | random | linear | ws://HOST:PORT | "
                   "package.module:attr (policies/resolve.py)")
    p.add_argument("--family", default="native", help="openpi observation mapping for ws:// policies")
    p.add_argument("--initial-conditions", required=True, help="episode store directory or .npz")
    p.add_argument("--out", required=True)
    p.add_argument("--episodes", type=int, default=None, help="use the first N initial conditions")
    p.add_argument("--start", type=int, default=0, help="first frame of the initial context in each episode")
    p.add_argument("--task", type=int, default=0, help="task id given to the policy (stores carry no task id)")
    p.add_argument("--tau", type=float, default=None, help="termination threshold (default: config rollout.tau; "
                   "'inf' never), compared with U_chunk in rollout.tau_units")
    p.add_argument("--tau-units", choices=("raw", "normalised"), default=None,
                   help="override rollout.tau_units (default: the config's; raw action units unless set)")
    p.add_argument("--num-chunks", type=int, default=None, help="default: episode_seconds * control_hz / keep")
    p.add_argument("--keep-frames", type=int, default=None, help="override rollout.keep_frames (l)")
    p.add_argument("--policy-chunk", type=int, default=None, help="override rollout.policy_chunk")
    p.add_argument("--sample-steps", type=int, default=None, help="override sample.steps (Euler steps)")
    p.add_argument("--inverse-steps", type=int, default=None, help="override sample.inverse_steps (Euler steps of "
                   "the inverse-dynamics re-read that yields U_chunk)")
    p.add_argument("--batch-size", type=int, default=None, help="episodes per jitted call (default: all)")
    p.add_argument("--data-fps", type=float, default=None, help="frame rate the model was trained at (default: "
                   "the store's fps, else 20)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--offline", action="store_true", help="also replay the recorded actions (episode stores only)")
    p.add_argument("--no-video", action="store_true")
    p.add_argument("--no-progress", action="store_true")
    return p


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    from sc3_jax import checkpoint, rollout
    from sc3_jax.config import replace
    from sc3_jax.policies.base import JaxPolicy
    from sc3_jax.policies.resolve import resolve

    work = Path(args.checkpoint)
    cfg = checkpoint.read_config(work)
    overrides = {k: v for k, v in (("keep_frames", args.keep_frames), ("policy_chunk", args.policy_chunk),
                                   ("tau_units", args.tau_units)) if v is not None}
    cfg = replace(cfg, rollout=overrides)
    cfg = replace(cfg, sample={k: v for k, v in (("steps", args.sample_steps),
                                                 ("inverse_steps", args.inverse_steps)) if v is not None})
    stats = checkpoint.read_norm_stats(work)
    params = checkpoint.load_params(work, cfg, args.step)
    data_fps = args.data_fps
    if data_fps is None:
        ic = Path(args.initial_conditions)
        data_fps = json.loads((ic / "dataset.json").read_text())["fps"] if (ic / "dataset.json").exists() else 20.0
    ro = rollout.Rollout(cfg, stats, data_fps=data_fps, num_chunks=args.num_chunks)
    ids, ics, store = load_initial_conditions(args.initial_conditions, cfg, ro.spec, args.episodes, args.start,
                                              args.task)
    policy = resolve(args.policy, cfg.rollout.policy_chunk, args.family).policy
    tau = cfg.rollout.tau if args.tau is None else args.tau
    n = len(ids)
    size = args.batch_size or n
    progress = not args.no_progress
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    keys = np.asarray(rollout.episode_keys(args.seed, n))
    pick = lambda sl: rollout.InitialConditions(*(np.asarray(x)[sl] for x in ics))  # noqa: E731
    if isinstance(policy, JaxPolicy):
        result = _run_batched(lambda sl: ro.run(params, policy, pick(sl), keys[sl], tau), n, size, progress,
                              "rollout")
    else:
        result = _run_batched(lambda sl: ro.run_host(params, policy, pick(sl), keys[sl], tau, progress=progress,
                                                     skip_done=True), n, size, False, "rollout")
    u_tau = result["u_raw" if cfg.rollout.tau_units == "raw" else "u"]
    meta = {"episodes": ids, "policy": args.policy, "tau": tau, "tau_units": cfg.rollout.tau_units, "seed": args.seed,
            "num_chunks": ro.spec.num_chunks,
            "keep_frames": ro.spec.keep, "stride": ro.spec.stride, "control_hz": cfg.rollout.control_hz}
    np.savez_compressed(out / "rollout.npz", **{k: v for k, v in result.items()}, episode_ids=np.asarray(ids))
    summary = {**meta, "termination_rate": result["termination_rate"],
               "terminated_at": result["terminated_at"].tolist(), "mean_u": u_tau.mean(-1).tolist()}
    if not args.no_video:
        summary["videos"] = write_videos(out, ids, result, cfg.data.views, cfg.rollout.control_hz)
    if args.offline:
        from sc3_jax.evaluate.metrics import psnr_by_view
        if store is None:
            raise ValueError("--offline needs an episode store as --initial-conditions")
        eps = [store.load(e) for e in ids]
        n_off = min(rollout.max_offline_chunks(ep.length, ro.spec, args.start) for ep in eps)
        n_off = min(n_off, ro.spec.num_chunks)
        if n_off < 1:
            raise ValueError("episodes too short for one offline chunk")
        ro_off = rollout.Rollout(cfg, stats, data_fps=data_fps, num_chunks=n_off)
        items = [rollout.from_episode(ep, cfg.data.views, ro_off.spec, args.start, args.task) for ep in eps]
        off_ics = rollout.stack_initial_conditions([it[0] for it in items])
        acts, tgts = np.stack([it[1] for it in items]), np.stack([it[2] for it in items])
        pick_off = lambda sl: rollout.InitialConditions(*(np.asarray(x)[sl] for x in off_ics))  # noqa: E731
        off = _run_batched(lambda sl: ro_off.run_offline(params, pick_off(sl), acts[sl], keys[sl], math.inf), n, size,
                           progress, "offline")
        off["psnr"], off["psnr_view"] = (x.astype(np.float32) for x in psnr_by_view(off["frames"], tgts,
                                                                                     off["frame_valid"]))
        np.savez_compressed(out / "offline.npz", **off, targets=tgts, episode_ids=np.asarray(ids))
        summary["offline_psnr_per_view"] = dict(zip(cfg.data.views, np.nanmean(off["psnr_view"], 0).tolist()))
        summary["offline_chunks"] = n_off
    (out / "summary.json").write_text(json.dumps(summary, indent=1))
    print(f"rollout: {n} episodes x {ro.spec.num_chunks} chunks, termination rate {result['termination_rate']:.3f} "
          f"(tau={tau} {cfg.rollout.tau_units}), mean U {float(u_tau.mean()):.4f} -> {out}")
    if args.offline:
        print("offline PSNR per view: " + ", ".join(f"{k} {v:.2f} dB"
                                                    for k, v in summary["offline_psnr_per_view"].items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""What ``sc3 rollout`` needs around ``rollout.Rollout``: initial conditions from an episode store or an ``.npz``,
rollouts in batches of episodes (closed loop, and the termination rate), videos, and the checks of its horizon made
before the model loads. Imports nothing from ``sc3_jax.evaluation``: the summaries of a rollout (the offline replay,
U_chunk, the success estimate, the finite-actions check) are ``evaluation/rollout_summary.py``."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from sc3_jax.core import atomic
from sc3_jax.core.errors import UserError


def load_initial_conditions(path: str, cfg, spec, episodes: int | None, start: int, task: int):
    """(ids, InitialConditions, store or None) of an episode store (its first K frames at the rollout stride from
    frame ``start``, and the state measured at the last of them) or an ``.npz`` with ``frames`` uint8 [B, V, K, H, W, 3],
    ``state`` float32 [B, A] (the model's imagined state: A = its action dimension), optionally ``task`` int32 [B] and
    ``robot`` float32 [B, S] (the robot's state, for a world model with a learned state); the first ``episodes`` of
    them (None: all)."""
    from sc3_jax.rollout import rollout

    p = Path(path)
    if p.suffix == ".npz":
        with atomic.open_npz(p, "write the initial conditions again") as z:
            arrays = {k: z[k] for k in ("frames", "state", "task", "robot") if k in z}
        _check_npz(p, arrays)
        n = len(arrays["frames"]) if episodes is None else min(episodes, len(arrays["frames"]))
        tasks = arrays["task"][:n] if "task" in arrays else np.full(n, task, np.int32)
        robot = arrays["robot"][:n].astype(np.float32) if "robot" in arrays else None
        ics = rollout.InitialConditions(arrays["frames"][:n], arrays["state"][:n].astype(np.float32),
                                        tasks.astype(np.int32), robot)
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
    store.check_whole()  # an emptied episode: named, not passed over for the next one
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
        from sc3_jax.model import checkpoint
        return checkpoint.read_robot(p).fps
    meta = p / "dataset.json"
    if meta.exists():
        return atomic.read_json(meta, "restore it (the episode store's metadata)")["fps"]
    raise UserError(f"{source}: neither a saved world model nor an episode store, so no frame rate to read: give "
                    "--data-fps (the frame rate of the data the world model was trained on)")


def write_videos(out: Path, ids, result: dict, views, fps: float) -> list[str]:
    """One mp4 per episode and view: the context frames, then the kept frames up to termination."""
    from sc3_jax.core.video import write_mp4

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


def _check_npz(p: Path, arrays: dict) -> None:
    """An initial-conditions .npz at the door: frames uint8 [B, V, K, H, W, 3], state finite numbers [B, A], task
    integers [B] and robot finite numbers [B, S] where given, one B (complex frames were cast to pixels without a
    word)."""
    fix = "write the initial conditions again (frames uint8 [B, V, K, H, W, 3], state float32 [B, A])"
    for key in ("frames", "state"):
        if key not in arrays:
            raise UserError(f"{p}: no {key!r} array; {fix}")
    f = arrays["frames"]
    if f.dtype != np.uint8 or f.ndim != 6 or f.shape[-1] != 3 or len(f) < 1:
        raise UserError(f"{p}: frames is {f.dtype} {list(f.shape)}, expected uint8 [B, V, K, H, W, 3]; {fix}")
    for key, ndim, kinds in (("state", 2, "fiu"), ("robot", 2, "fiu"), ("task", 1, "iu")):
        x = arrays.get(key)
        if x is None:
            continue
        if x.dtype.kind not in kinds or x.ndim != ndim or len(x) != len(f):
            want = "integers [B]" if key == "task" else "numbers [B, N]"
            raise UserError(f"{p}: {key} is {x.dtype} {list(x.shape)}, expected {want} with B = {len(f)} (frames); "
                            f"{fix}")
        if x.dtype.kind == "f" and not np.isfinite(x).all():
            raise UserError(f"{p}: {key} holds NaN or inf; {fix}")


MAX_EPISODE_SECONDS = 3600.0  # an hour of imagined video per episode: beyond it the frames are the bound


def check_seconds(episode_seconds: float) -> None:
    """``--rollout.episode-seconds`` positive and finite (``-1`` was an IndexError blamed on the policy, ``inf`` an
    OverflowError), at most ``MAX_EPISODE_SECONDS``: checked before the model loads."""
    from sc3_jax.core.validate import in_range

    in_range("--rollout.episode-seconds", episode_seconds, 1e-3, MAX_EPISODE_SECONDS, "seconds of one episode")


def check_horizon(spec, episode_seconds: float, episodes: int) -> None:
    """The uint8 frames of one batch of ``episodes`` within the machine's available memory (``1e9`` seconds would
    grow until the kernel kills the run)."""
    from sc3_jax.core.validate import host_available_bytes

    frames = episodes * spec.num_chunks * spec.keep * spec.views * math.prod(spec.image_size) * 3
    avail = host_available_bytes()
    if avail is not None and frames > avail / 2:
        raise UserError(f"--rollout.episode-seconds {episode_seconds:g}: {episodes} episodes' frames need about "
                        f"{frames / 1e9:.1f} GB, this machine has {avail / 1e9:.1f} GB available; give fewer seconds "
                        "or a smaller --batch")

"""``sc3 diagnose``: the checks that gate a world-model checkpoint, on held-out episodes (an episode store).

    sc3 diagnose WORLD_MODEL --data HELDOUT_STORE [--episodes N] [--out result.json] [--seed 0]

Everything is computed first (:func:`diagnose` -> a JSON-able dict), then rendered (:func:`render_table` ->
markdown). Sections (``l'`` = data.future_frames predicted frames per chunk, at ``rollout.control_hz``):

* teacher-forced, one chunk ahead from real context: the context is re-seeded from the real frames at every chunk
  start (chunk c starts at model step c*l, the open-loop rollout's chunk cadence); PSNR at the chunk's last frame
  (``l' / control_hz`` s, 0.8 s for the shipped model) over the whole frame and over *moving pixels*, against
  copy-last (the last real context frame), copy-first (the episode's first frame) and the temporal median ("erase
  the arm": the per-pixel median over all frames of the real episode, what a model that blurs the robot away
  scores); the same with action chunks shuffled across episodes (same noise draws).
* drift: open loop from the episode's first real frames with the recorded actions (after the episode's end the
  robot holds still, as in the sweep's offline mode), PSNR at fixed horizons, as far as episodes last.
* counterfactual: from real starts, the recorded chunk and the same chunk plus a displacement of +-x / +-y (a few
  cm spread over the chunk). Read-out, model-agnostic: the arm's image position = centroid of the pixels that
  differ from the episode's temporal median (the robot is what the median erases), in the third-person views; its
  imagined shift against the recorded-chunk prediction is compared with the commanded shift mapped to the image by
  an affine camera fitted on the real frames (end-effector xyz -> arm centroid; its R^2 is reported).
* inverse dynamics on real frames: the ID mode's action estimate from real context + real future frames, MSE in
  normalised action units, against the floors "zero" (the training mean action) and "the held-out mean action".
* offline outcome reproduction: the perception scorer on the open-loop imagined rollout vs the real episode's
  physics labels (``meta.labels``, ``sc3 sim demos``), per object; where the rollout does not cover the whole
  episode (``max_seconds``) or no labels exist, against the perception scorer on the real frames of the same
  window instead (the reference is named in the result).
* gates: each acceptance gate with value, threshold and pass/fail (see ``GATES`` and docs/world_model.md).

PSNR over a set of frames is the PSNR of their pooled squared error (``10 log10(255^2 n / SSE)``): defined whenever
anything differs (no per-frame inf to drop), frames without moving pixels simply add nothing to the moving-pixel
figure, and baselines and the model are pooled over exactly the same pixels. Moving pixels of a target frame: any
channel differs from the reference frame (the last real context frame) by more than ``moving_threshold`` in [-1, 1]
units (0.06 = 7.65 grey levels: above the renderer's anti-aliasing flicker, below the arm-on-table contrast).

Frames are only ever produced by the rollout machinery (``rollout.Rollout.run_offline``) and the tokenizer
interface, so any tokenizer works unchanged.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

from sc3_jax.evaluate import metrics  # numpy only: the module stays cheap for report.py to import

PREDICTORS = ("model", "copy_last", "copy_first", "median")
AXES = {"+x": (1.0, 0.0, 0.0), "-x": (-1.0, 0.0, 0.0), "+y": (0.0, 1.0, 0.0), "-y": (0.0, -1.0, 0.0)}


@dataclasses.dataclass(frozen=True)
class DiagnoseConfig:
    episodes: int | None = None  # N episodes evenly spaced over the store's sorted ids; None = all
    seed: int = 0  # sampler noise (per sample / episode keys) and the action shuffle
    moving_threshold: float = 0.06  # [-1, 1] units, any channel (see the module docstring)
    horizons: tuple[float, ...] = (0.8, 2.0, 4.0, 6.0, 8.0)  # drift curve points (s)
    max_seconds: float | None = None  # cap on the open-loop horizon (None: the longest episode)
    batch: int = 8  # rollouts per jitted call (rounded up to the device count)
    sample_steps: int | None = None  # Euler steps (None: the model's sample.steps)
    cf_distance: float = 0.05  # counterfactual displacement (m) added over one chunk
    cf_starts: int = 2  # counterfactual start chunks per episode (evenly spaced over its teacher-forced chunks)
    arm_threshold: float = 0.12  # [-1, 1] units: a pixel belongs to the arm when it differs this much from the median
    min_arm_pixels: int = 4
    perception: str | None = None  # perception weights (None: the shipped ones)
    progress: bool = True
    # gates (see GATES)
    gate_margin_db: float = 3.0
    gate_actions_db: float = 2.0
    gate_reproduction: float = 0.75


# ================================================================================================================
# Pure metric pieces (numpy)
# ================================================================================================================
def moving_mask(target: np.ndarray, reference: np.ndarray, threshold: float) -> np.ndarray:
    """uint8 [..., H, W, 3] frames -> bool [..., H, W]: pixels where any channel of ``target`` differs from
    ``reference`` by more than ``threshold`` in [-1, 1] units (one grey level = 1 / 127.5)."""
    d = np.abs(np.asarray(target, np.int16) - np.asarray(reference, np.int16)) / 127.5
    return np.any(d > threshold, axis=-1)


def squared_errors(pred: np.ndarray, target: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """[whole SSE, whole count, moving SSE, moving count] summed over every leading axis (counts in values:
    pixels x channels). ``pred`` may be float (the temporal median) or uint8, on the 0..255 scale."""
    e = (np.asarray(pred, np.float64) - np.asarray(target, np.float64)) ** 2  # [..., H, W, C]
    m = np.asarray(mask, bool)[..., None]
    return np.array([e.sum(), e.size, (e * m).sum(), m.sum() * e.shape[-1]], np.float64)


def psnr_from_sums(sse: float, n: float) -> float:
    """PSNR (dB, 0..255 scale) of a pooled squared error: inf when nothing differs, nan when nothing was counted."""
    if n <= 0:
        return math.nan
    if sse <= 0:
        return math.inf
    return float(metrics.psnr_from_mse(sse / n))


def temporal_median(frames: np.ndarray) -> np.ndarray:
    """uint8 [T, H, W, 3] -> float64 [H, W, 3]: the per-pixel median over time ("erase the arm")."""
    return np.median(np.asarray(frames), axis=0)


def arm_centroid(frame: np.ndarray, median: np.ndarray, threshold: float, min_pixels: int) -> np.ndarray:
    """(row, col) centroid of the pixels of ``frame`` that differ from the temporal ``median`` by more than
    ``threshold`` ([-1, 1] units, any channel); nan when fewer than ``min_pixels`` do."""
    m = np.any(np.abs(np.asarray(frame, np.float64) - median) / 127.5 > threshold, axis=-1)
    if m.sum() < min_pixels:
        return np.full(2, np.nan)
    r, c = np.nonzero(m)
    return np.array([r.mean(), c.mean()])


class ErrorSums:
    """Pooled squared errors per key (e.g. (view, horizon, predictor))."""

    def __init__(self):
        self.sums: dict[tuple, np.ndarray] = {}
        self.frames: dict[tuple, int] = {}

    def add(self, key: tuple, pred, target, mask):
        self.sums[key] = self.sums.get(key, np.zeros(4)) + squared_errors(pred, target, mask)
        self.frames[key] = self.frames.get(key, 0) + 1

    def psnr(self, key: tuple, region: str) -> float:
        s = self.sums.get(key)
        if s is None:
            return math.nan
        return psnr_from_sums(s[0], s[1]) if region == "whole" else psnr_from_sums(s[2], s[3])

    def moving_fraction(self, key: tuple) -> float:
        s = self.sums.get(key)
        return math.nan if s is None or s[1] == 0 else float(s[3] / s[1])


# ================================================================================================================
# Loading
# ================================================================================================================
def load(world_model):
    """(config, norm stats, params, name) of a path (``sc3 train`` workdir or exported dir) or a loaded triple."""
    if isinstance(world_model, (str, Path)):
        from sc3_jax import checkpoint
        cfg, stats, params = checkpoint.load(world_model)
        return cfg, stats, params, str(world_model)
    cfg, stats, params = world_model
    return cfg, stats, params, cfg.name if hasattr(cfg, "name") else "<loaded>"


class _Batcher:
    """Fixed-size batches over a list of samples, the last one padded by repetition (one compiled shape)."""

    def __init__(self, size: int):
        self.size = size

    def chunks(self, n: int):
        for i in range(0, n, self.size):
            yield i, min(i + self.size, n)

    def pad(self, x: np.ndarray) -> np.ndarray:
        x = np.asarray(x)
        if len(x) < self.size:
            x = np.concatenate([x, np.repeat(x[-1:], self.size - len(x), 0)])
        return x


# ================================================================================================================
# The computation
# ================================================================================================================
def diagnose(world_model, heldout_store, config: DiagnoseConfig | None = None, **overrides) -> dict:
    """Every diagnostic of ``world_model`` (a path or ``(cfg, norm_stats, params)``) on the episode store
    ``heldout_store`` (path or ``EpisodeStore``); see the module docstring. Returns a JSON-able dict
    (non-finite numbers as floats: write it with :func:`save_result`)."""
    import jax
    from tqdm import tqdm

    from sc3_jax import modes
    from sc3_jax import rollout as ro_mod
    from sc3_jax.config import replace
    from sc3_jax.data.episodes import EpisodeStore
    from sc3_jax.evaluate.world_model import make_sampler

    dc = dataclasses.replace(config or DiagnoseConfig(), **overrides)
    t0 = time.time()
    cfg, stats, params, name = load(world_model)
    if dc.sample_steps:
        cfg = replace(cfg, sample=dict(steps=dc.sample_steps))
    store = heldout_store if isinstance(heldout_store, EpisodeStore) else EpisodeStore(heldout_store)
    views = list(cfg.data.views)
    missing = [v for v in views if v not in store.views]
    if missing:
        raise ValueError(f"{store.root}: the world model needs views {views}, the store has {store.views}")
    if tuple(store.image_size) != tuple(cfg.data.image_size):
        raise ValueError(f"{store.root}: images {tuple(store.image_size)}, the world model takes "
                         f"{tuple(cfg.data.image_size)}")
    ids = store.episode_ids()
    if dc.episodes is not None and dc.episodes < len(ids):  # evenly spaced: stores are ordered by generation knob
        ids = [ids[i] for i in np.linspace(0, len(ids) - 1, dc.episodes).round().astype(int)]
    if not ids:
        raise ValueError(f"{store.root}: no episodes")
    eps = [store.load(e, mmap=True) for e in ids]

    # one chunk of l' frames from real context (keep every predicted frame) and the open-loop rollout
    K, Tp, hz = cfg.data.context_frames, cfg.data.future_frames, cfg.rollout.control_hz
    cfg_tf = replace(cfg, rollout=dict(keep_frames=Tp))
    tf = ro_mod.Rollout(cfg_tf, stats, data_fps=store.fps, num_chunks=1)
    spec1, s = tf.spec, ro_mod.make_spec(cfg, store.fps, 1)
    stride, l = s.stride, s.keep
    B = -(-dc.batch // tf.batch_multiple) * tf.batch_multiple
    bat = _Batcher(B)
    off = stride * (K - 1)  # episode frame of rollout step 0 (the last context frame) from start 0
    steps_in = [(ep.length - 1 - off) // stride for ep in eps]  # target steps each episode has from start 0
    if min(steps_in) < 1:
        raise ValueError(f"episodes too short for a rollout: need > {off + stride} frames")
    cap = math.inf if dc.max_seconds is None else int(round(dc.max_seconds * hz))
    n_chunks = max(1, math.ceil(min(max(steps_in), cap) / l))
    ol = ro_mod.Rollout(cfg, stats, data_fps=store.fps, num_chunks=n_chunks)
    S = ol.spec
    horizon_steps = [int(round(h * hz)) for h in dc.horizons]

    # teacher-forced samples: (episode, start frame) for every chunk start with a full chunk of targets
    samples = _tf_starts(eps, spec1, l, stride)
    rng = np.random.default_rng(dc.seed)
    donors = _shuffle_donors(samples, rng)

    medians = [np.stack([temporal_median(ep.frames[v]) for v in views]) for ep in eps]  # [V, H, W, 3]
    first = [np.stack([np.asarray(ep.frames[v][0]) for v in views]) for ep in eps]
    tf_sums, cf_rows, id_acc = ErrorSums(), [], {"mse": [], "zero": [], "sum": [], "n": 0}
    u_tf = []
    ol_sums = ErrorSums()
    outcome_rows = []
    id_mean = make_sampler(cfg, steps=1)  # one step from pure noise = the model's conditional-mean estimate
    third = [i for i, v in enumerate(views) if "wrist" not in v]
    calib = _calibrate(eps, views, third, medians, stride, dc)
    scorer, perception_note = _scorer(dc, views, cfg.data.image_size)

    bar = tqdm(total=len(eps), desc="diagnose", unit="episode", disable=not dc.progress)
    group = B  # episodes per step: one open-loop batch (their teacher-forced chunks fill several batches)
    for g0 in range(0, len(eps), group):
        g = list(range(g0, min(g0 + group, len(eps))))
        # -- teacher-forced, true and shuffled actions; ID on the same real windows -------------------------------
        bar.set_postfix_str("teacher-forced")
        idx = [i for i, (e, _) in enumerate(samples) if e in g]
        items = [ro_mod.from_episode(eps[samples[i][0]], views, spec1, start=samples[i][1]) for i in idx]
        shuffled = [ro_mod.from_episode(eps[samples[donors[i]][0]], views, spec1, start=samples[donors[i]][1])[1]
                    for i in idx]
        for a, b in bat.chunks(len(items)):
            part = items[a:b]
            ics = ro_mod.stack_initial_conditions([it[0] for it in part])
            ics = ro_mod.InitialConditions(*(bat.pad(x) for x in ics))
            keys = np.asarray(ro_mod.episode_keys(dc.seed, B, start=idx[a]))
            acts = bat.pad(np.stack([it[1] for it in part]))
            true = tf.run_offline(params, ics, acts, keys)
            shuf = tf.run_offline(params, ics, bat.pad(np.stack(shuffled[a:b])), keys)
            u_tf += true["u"][:b - a, 0].tolist()
            for j, it in enumerate(part):
                e = samples[idx[a + j]][0]
                _add_chunk(tf_sums, it[2], it[0][0][:, -1], true["frames"][j], shuf["frames"][j], first[e],
                           medians[e], dc.moving_threshold)
            window = np.concatenate([ics.frames, bat.pad(np.stack([it[2] for it in part]))], axis=2)
            a_norm = stats.normalize(acts[:, 0])
            strides = np.full((B,), stride, np.int32)
            k = jax.random.fold_in(jax.random.key(dc.seed), 10_000 + idx[a])
            pose = None
            if cfg.model.pose_conditioning:  # frame K-1's pose counts; the future ones are withheld in ID mode
                from sc3_jax.data.pipeline import integrate_poses
                pose = stats.normalize_pose(np.stack([integrate_poses(s0, a0) for s0, a0 in
                                                      zip(ics.state, acts[:, 0])]))
            _, est = id_mean(params, window, np.zeros_like(a_norm), strides, k, modes.ID, 0, pose)
            n = b - a
            est = np.asarray(est)[:n]
            id_acc["mse"].append(((est - a_norm[:n]) ** 2).sum((0, 1)))  # per action dimension [7]
            id_acc["zero"].append((a_norm[:n] ** 2).sum((0, 1)))
            id_acc["sum"].append(a_norm[:n].sum((0, 1)))
            id_acc["n"] += n * a_norm.shape[1]
        # -- counterfactual: recorded chunk vs displaced ones from the same real start --------------------------------
        bar.set_postfix_str("counterfactual")
        cf_items = []
        for e in g:
            starts = [st for ee, st in samples if ee == e]
            pick = sorted({starts[int(round(q))] for q in np.linspace(0, len(starts) - 1, min(dc.cf_starts,
                                                                                               len(starts)))})
            for st in pick:
                ic, acts, tgt = ro_mod.from_episode(eps[e], views, spec1, start=st)
                for name_v, vec in [("recorded", None)] + list(AXES.items()):
                    a2 = acts.copy()
                    if vec is not None:
                        a2[0, :, :3] += np.asarray(vec, np.float32) * dc.cf_distance / Tp
                    cf_items.append((e, st, name_v, ic, a2, tgt))
        cf_frames = []
        for a, b in bat.chunks(len(cf_items)):
            part = cf_items[a:b]
            ics = ro_mod.InitialConditions(*(bat.pad(x) for x in ro_mod.stack_initial_conditions(
                [it[3] for it in part])))
            # every variant of one start shares its noise: the difference between them is the actions'
            keys = np.stack([np.asarray(ro_mod.episode_keys(dc.seed + 1, 1, start=it[0] * 100_000 + it[1]))[0]
                             for it in part])
            out = tf.run_offline(params, ics, bat.pad(np.stack([it[4] for it in part])), bat.pad(keys))
            cf_frames += [out["frames"][j][:, -1] for j in range(b - a)]  # [V, H, W, 3] at the chunk's end
        cf_rows += _counterfactual_rows(cf_items, cf_frames, medians, calib, third, dc)
        # -- open loop from the first real frames: drift and outcomes ------------------------------------------------
        bar.set_postfix_str("open loop")
        ics_l, acts_l, tgts, valids = [], [], [], []
        for e in g:
            ep = eps[e]
            frames = np.stack([np.asarray(ep.frames[v]) for v in views])
            ic_frames = frames[:, [stride * i for i in range(K)]]
            ics_l.append((ic_frames, np.asarray(ep.ee_pose[off], np.float32), np.int32(0)))
            acts_l.append(ro_mod.chunk_actions(np.asarray(ep.actions)[off:], S))
            t, v = ro_mod.recorded_targets(frames[:, off:], S)
            tgts.append(t)
            valids.append(v)
        for a, b in bat.chunks(len(g)):
            ics = ro_mod.InitialConditions(*(bat.pad(x) for x in ro_mod.stack_initial_conditions(ics_l[a:b])))
            keys = np.asarray(ro_mod.episode_keys(dc.seed + 2, B, start=g[a]))
            out = ol.run_offline(params, ics, bat.pad(np.stack(acts_l[a:b])), keys)
            for j in range(b - a):
                e = g[a + j]
                pred, tgt, valid = out["frames"][j], tgts[a + j], valids[a + j]
                ctx_last = ics.frames[j][:, -1]
                for hi, hs in enumerate(horizon_steps):
                    if hs <= len(valid) and valid[hs - 1]:
                        _add_horizon(ol_sums, ("drift", hi), pred[:, hs - 1], tgt[:, hs - 1], ctx_last, first[e],
                                     medians[e], dc.moving_threshold)
                if scorer is not None:
                    outcome_rows.append(_outcome(scorer, eps[e], ics.frames[j], pred, tgt, valid,
                                                 steps_in[e]))
        bar.update(len(g))
    bar.close()

    result = {
        "world_model": name, "data": str(store.root), "episodes": ids, "seconds": None,
        "settings": {**dataclasses.asdict(dc), "context_frames": K, "future_frames": Tp, "keep_frames": l,
                     "control_hz": hz, "data_fps": store.fps, "stride": stride, "sample_steps": cfg.sample.steps,
                     "open_loop_chunks": n_chunks, "batch": B},
        "views": views, "third_person_views": [views[i] for i in third],
        "teacher_forced": _tf_section(tf_sums, views, Tp / hz, len(samples), u_tf),
        "drift": _drift_section(ol_sums, views, dc.horizons, horizon_steps),
        "counterfactual": _cf_section(cf_rows, calib, views, third, dc),
        "inverse_dynamics": _id_section(id_acc),
        "outcomes": _outcome_section(outcome_rows, perception_note),
    }
    result["gates"] = gates(result, dc)
    result["seconds"] = round(time.time() - t0, 1)
    return result


def _tf_starts(eps, spec1, keep: int, stride: int) -> list[tuple[int, int]]:
    """(episode index, start frame) of every teacher-forced chunk: starts every ``keep`` model steps (the open-loop
    chunk cadence) while a whole chunk of targets exists."""
    from sc3_jax.rollout import max_offline_chunks
    out = []
    for e, ep in enumerate(eps):
        c = 0
        while max_offline_chunks(ep.length, spec1, c * keep * stride) >= 1:
            out.append((e, c * keep * stride))
            c += 1
    if not out:
        raise ValueError("no episode is long enough for one chunk from real context")
    return out


def _shuffle_donors(samples, rng) -> list[int]:
    """For each sample the index of another sample whose action chunk it gets: from another episode when there is
    one (else another chunk of the same episode)."""
    ep = np.array([e for e, _ in samples])
    out = []
    for i in range(len(samples)):
        pool = np.flatnonzero(ep != ep[i])
        if not len(pool):
            pool = np.array([j for j in range(len(samples)) if j != i] or [i])
        out.append(int(rng.choice(pool)))
    return out


def _add_horizon(sums: ErrorSums, key, pred, target, ctx_last, first, median, thr):
    """One target frame per view: model and baselines into ``sums[(*key, view, predictor)]``."""
    for v in range(target.shape[0]):
        m = moving_mask(target[v], ctx_last[v], thr)
        for p, x in (("model", pred[v]), ("copy_last", ctx_last[v]), ("copy_first", first[v]),
                     ("median", median[v])):
            sums.add((*key, v, p), x, target[v], m)


def _add_chunk(sums: ErrorSums, targets, ctx_last, pred, pred_shuffled, first, median, thr):
    """A teacher-forced chunk: every predicted frame (offset i = 1..l'), model, shuffled and baselines."""
    for i in range(targets.shape[1]):
        _add_horizon(sums, ("tf", i), pred[:, i], targets[:, i], ctx_last, first, median, thr)
        for v in range(targets.shape[0]):
            sums.add(("tf", i, v, "shuffled"), pred_shuffled[v, i], targets[v, i],
                     moving_mask(targets[v, i], ctx_last[v], thr))


def _region_table(sums: ErrorSums, key, predictors) -> dict:
    return {p: {"whole": sums.psnr((*key, p), "whole"), "moving": sums.psnr((*key, p), "moving")}
            for p in predictors}


def _tf_section(sums: ErrorSums, views, horizon_s: float, n: int, u) -> dict:
    last = max(k[1] for k in sums.sums)
    out = {"horizon_s": horizon_s, "n_chunks": n, "u_mean": float(np.mean(u)) if u else math.nan, "views": {}}
    for v, name in enumerate(views):
        psnr = _region_table(sums, ("tf", last, v), PREDICTORS + ("shuffled",))
        out["views"][name] = {
            "moving_fraction": sums.moving_fraction(("tf", last, v, "model")), "psnr": psnr,
            "true_minus_shuffled_moving": psnr["model"]["moving"] - psnr["shuffled"]["moving"],
            # per frame offset 1..l' (s = offset / control_hz): the whole chunk's curve
            "curve_moving": {p: [sums.psnr(("tf", i, v, p), "moving") for i in range(last + 1)]
                             for p in PREDICTORS + ("shuffled",)}}
    return out


def _drift_section(sums: ErrorSums, views, horizons, steps) -> dict:
    out = {"horizons_s": list(horizons), "views": {}}
    for v, name in enumerate(views):
        rows = []
        for hi, h in enumerate(horizons):
            key = ("drift", hi, v, "model")
            n = sums.frames.get(key, 0)  # one frame per episode that lasts this long
            rows.append({"horizon_s": h, "step": steps[hi], "n_episodes": n,
                         "moving_fraction": sums.moving_fraction(key),
                         "psnr": _region_table(sums, ("drift", hi, v), PREDICTORS)})
        out["views"][name] = rows
    return out


# -- counterfactual ------------------------------------------------------------------------------------------------
def _calibrate(eps, views, third, medians, stride: int, dc: DiagnoseConfig) -> dict:
    """Per third-person view an affine camera (least squares): [x, y, z, 1] @ W -> arm centroid (row, col), from
    every ``stride``-th real frame; with R^2 per image coordinate."""
    out = {}
    for v in third:
        X, Y = [], []
        for e, ep in enumerate(eps):
            fr = np.asarray(ep.frames[views[v]])
            for t in range(0, ep.length, stride):
                c = arm_centroid(fr[t], medians[e][v], dc.arm_threshold, dc.min_arm_pixels)
                if np.all(np.isfinite(c)):
                    X.append(np.r_[np.asarray(ep.ee_pose[t, :3], np.float64), 1.0])
                    Y.append(c)
        if len(X) < 8:
            out[views[v]] = {"W": None, "r2": [math.nan, math.nan], "n": len(X)}
            continue
        X, Y = np.asarray(X), np.asarray(Y)
        W = np.linalg.lstsq(X, Y, rcond=None)[0]  # [4, 2]
        res = Y - X @ W
        r2 = 1 - (res ** 2).sum(0) / np.maximum(((Y - Y.mean(0)) ** 2).sum(0), 1e-12)
        out[views[v]] = {"W": W.tolist(), "r2": r2.tolist(), "n": len(X)}
    return out


def _counterfactual_rows(items, frames, medians, calib, third, dc) -> list[dict]:
    """One row per (start, third-person view, displaced variant): commanded vs imagined image shift (px)."""
    rows = []
    by_start: dict = {}
    for it, f in zip(items, frames):
        by_start.setdefault((it[0], it[1]), {})[it[2]] = (f, it[5])
    for (e, st), variants in by_start.items():
        ref, tgt = variants["recorded"]
        for v in third:
            cal = calib[list(calib)[third.index(v)]]
            c_ref = arm_centroid(ref[v], medians[e][v], dc.arm_threshold, dc.min_arm_pixels)
            c_real = arm_centroid(tgt[v, -1], medians[e][v], dc.arm_threshold, dc.min_arm_pixels)
            for name, vec in AXES.items():
                c = arm_centroid(variants[name][0][v], medians[e][v], dc.arm_threshold, dc.min_arm_pixels)
                want = (np.asarray(cal["W"])[:3].T @ (np.asarray(vec) * dc.cf_distance)) if cal["W"] else \
                    np.full(2, np.nan)
                rows.append({"episode": e, "start": st, "view": v, "variant": name, "imagined": (c - c_ref).tolist(),
                             "commanded": want.tolist(), "ref_error_px": float(np.linalg.norm(c_ref - c_real))})
    return rows


def _cf_section(rows, calib, views, third, dc) -> dict:
    out = {"distance_m": dc.cf_distance, "calibration_r2": {k: v["r2"] for k, v in calib.items()},
           "views": {}}
    for v in third + [None]:
        sel = [r for r in rows if v is None or r["view"] == v]
        d = np.array([r["imagined"] for r in sel]).reshape(-1, 2)
        w = np.array([r["commanded"] for r in sel]).reshape(-1, 2)
        ok = np.all(np.isfinite(d), 1) & np.all(np.isfinite(w), 1) & (np.linalg.norm(w, axis=1) >= 0.5)
        dots = (d[ok] * w[ok]).sum(1)
        # opposite commands (+x vs -x, +y vs -y) should shift the imagined arm opposite ways
        opp = []
        for r in sel:
            if r["variant"] in ("+x", "+y"):
                other = next(o for o in sel if (o["episode"], o["start"], o["view"]) ==
                             (r["episode"], r["start"], r["view"]) and o["variant"] == "-" + r["variant"][1])
                a, b = np.asarray(r["imagined"]), np.asarray(other["imagined"])
                if np.all(np.isfinite(a)) and np.all(np.isfinite(b)) and (np.any(a) or np.any(b)):
                    opp.append(float(a @ b < 0))
        ref_err = [r["ref_error_px"] for r in sel if r["variant"] == "+x" and math.isfinite(r["ref_error_px"])]
        out["views"]["all" if v is None else views[v]] = {
            "n_pairs": int(ok.sum()),
            "direction_agreement": float(np.mean(dots > 0)) if ok.any() else math.nan,
            "correlation": _corr(d[ok].ravel(), w[ok].ravel()),
            "gain": float(dots.sum() / (w[ok] ** 2).sum()) if ok.any() else math.nan,
            "opposite_fraction": float(np.mean(opp)) if opp else math.nan,
            "commanded_px": float(np.linalg.norm(w[ok], axis=1).mean()) if ok.any() else math.nan,
            "imagined_px": float(np.linalg.norm(d[ok], axis=1).mean()) if ok.any() else math.nan,
            "recorded_position_error_px": float(np.median(ref_err)) if ref_err else math.nan}
    return out


def _corr(a, b) -> float:
    if len(a) < 3 or np.std(a) == 0 or np.std(b) == 0:
        return math.nan
    return float(np.corrcoef(a, b)[0, 1])


# -- inverse dynamics -----------------------------------------------------------------------------------------------
def _id_section(acc) -> dict:
    n = acc["n"]
    per = {k: np.sum(acc[k], 0) / n for k in ("mse", "zero")}  # per action dimension, over every step
    per["mean_floor"] = per["zero"] - (np.sum(acc["sum"], 0) / n) ** 2  # the evaluated steps' own mean action
    out = {k: float(v.mean()) for k, v in per.items()}
    out["per_dim_mse"] = per["mse"].tolist()
    out["per_dim_floor"] = per["zero"].tolist()
    out["ratio_to_floor"] = out["mse"] / min(out["zero"], out["mean_floor"])
    out["n_steps"] = n
    return out


# -- outcomes -------------------------------------------------------------------------------------------------------
def _scorer(dc: DiagnoseConfig, views, image_size):
    from sc3_jax.evaluate import perception
    if list(views) != ["left", "right", "wrist"] or tuple(image_size) != (64, 64):
        return None, f"perception scorer reads left/right/wrist at 64x64; this model has {views} at {image_size}"
    from sc3_jax.evaluate.scorers import PerceptionScorer
    return PerceptionScorer(perception.load(dc.perception or perception.DEFAULT_WEIGHTS)), None


def _objects(meta: dict):
    """(objects, destinations, physics labels or None) from an episode's meta (``sc3 sim demos`` format)."""
    labels = (meta.get("labels") or {}).get("objects")
    if labels:
        return tuple(o["name"] for o in labels), {o["name"]: o["destination"] for o in labels}, labels
    ic = meta.get("initial_condition")
    if ic and "destinations" in ic:
        return tuple(ic["objects"]), dict(ic["destinations"]), None
    return None, None, None


def _outcome(scorer, ep, ctx, pred, tgt, valid, steps_in: int) -> dict | None:
    from sc3_jax.evaluate.scorers import RolloutView
    objects, dests, physics = _objects(ep.meta)
    if objects is None:
        return None
    n = int(valid.sum())
    imagined = np.concatenate([ctx, pred[:, :n]], 1)
    real = np.concatenate([ctx, tgt[:, :n]], 1)
    im = scorer.score(RolloutView(ep.episode_id, imagined, objects, dests))
    re = scorer.score(RolloutView(ep.episode_id, real, objects, dests))
    covered = n >= steps_in
    return {"episode": ep.episode_id, "imagined": im, "real_perception": re,
            "physics": physics if covered else None, "covered": covered}


def _outcome_section(rows, note) -> dict:
    from sc3_jax.evaluate.metrics import CRITERIA, outcome_category
    rows = [r for r in rows if r is not None]
    category = lambda o: outcome_category({c: o[c] for c in CRITERIA})  # noqa: E731  (sim spells "no failure")
    if not rows:
        return {"available": False, "note": note or "no episode has object labels (meta.labels / "
                                                    "meta.initial_condition)"}

    def agree(a_key, b_key):
        pairs = [(a, b) for r in rows if r[a_key] is not None and r[b_key] is not None
                 for a, b in zip(r[a_key], r[b_key], strict=True)]
        if not pairs:
            return None
        d = {c: float(np.mean([a[c] == b[c] for a, b in pairs])) for c in CRITERIA}
        d["outcome"] = float(np.mean([category(a) == category(b) for a, b in pairs]))
        d["lifting_and_placing"] = float(np.mean([a["lifting"] == b["lifting"] and a["placing"] == b["placing"]
                                                  for a, b in pairs]))
        d["n_objects"] = len(pairs)
        return d

    vs_physics = agree("imagined", "physics")
    return {"available": True, "n_episodes": len(rows),
            "reference": "physics" if vs_physics else "perception(real frames)",
            "imagined_vs_physics": vs_physics, "imagined_vs_real_perception": agree("imagined", "real_perception"),
            "real_perception_vs_physics": agree("real_perception", "physics")}


# ================================================================================================================
# Gates
# ================================================================================================================
GATES = ("teacher-forced moving PSNR - copy-last, every third-person view (dB)",
         "teacher-forced moving PSNR - temporal median, every third-person view (dB)",
         "true - shuffled actions, moving PSNR, every view (dB)",
         "offline per-object outcome reproduction",
         "drift curve reported per view")


def gates(result: dict, dc: DiagnoseConfig) -> list[dict]:
    tf = result["teacher_forced"]["views"]
    third = result["third_person_views"] or result["views"]

    def margin(base):
        vals = [tf[v]["psnr"]["model"]["moving"] - tf[v]["psnr"][base]["moving"] for v in third]
        return min(vals) if vals else math.nan

    shuffled = min(tf[v]["true_minus_shuffled_moving"] for v in result["views"])
    oc = result["outcomes"]
    if oc.get("available"):
        ref = oc["imagined_vs_physics"] or oc["imagined_vs_real_perception"]
        repro, note = ref["outcome"], f"outcome category vs {oc['reference']}, {ref['n_objects']} objects"
    else:
        repro, note = math.nan, oc.get("note", "")
    drift_ok = all(r[0]["n_episodes"] > 0 for r in result["drift"]["views"].values())
    rows = [(GATES[0], margin("copy_last"), dc.gate_margin_db, ""),
            (GATES[1], margin("median"), dc.gate_margin_db, ""),
            (GATES[2], shuffled, dc.gate_actions_db, ""),
            (GATES[3], repro, dc.gate_reproduction, note)]
    out = [{"gate": g, "value": v, "threshold": t, "pass": bool(math.isfinite(v) and v >= t), "note": n}
           for g, v, t, n in rows]
    out.append({"gate": GATES[4], "value": float(drift_ok), "threshold": 1.0, "pass": drift_ok,
                "note": "horizons " + ", ".join(f"{h:g} s" for h in result["drift"]["horizons_s"])})
    return out


# ================================================================================================================
# Rendering
# ================================================================================================================
def _f(x, fmt="{:.2f}") -> str:
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "n/a"
    if isinstance(x, float) and math.isinf(x):
        return "inf"
    return fmt.format(x)


def _pct(x) -> str:
    return "n/a" if x is None or math.isnan(x) else f"{100 * x:.1f}%"


def render_table(result: dict) -> str:
    """Markdown of a :func:`diagnose` result (every number comes from ``result``)."""
    st = result["settings"]
    L = [f"## World-model diagnostics: {result['world_model']}", "",
         f"held-out data {result['data']} ({len(result['episodes'])} episodes), K={st['context_frames']} "
         f"context, l'={st['future_frames']} predicted, l={st['keep_frames']} kept frames per chunk at "
         f"{st['control_hz']:g} Hz (stride {st['stride']}), {st['sample_steps']} sampler steps, moving pixels: any "
         f"channel > {st['moving_threshold']:g} from the last real context frame; PSNR in dB of pooled errors; "
         f"{_f(result['seconds'], '{:.0f}')} s", ""]
    tf = result["teacher_forced"]
    L += [f"### One chunk ahead from real context (teacher-forced, {tf['horizon_s']:g} s, {tf['n_chunks']} chunks, "
          f"mean U {_f(tf['u_mean'], '{:.3f}')})", "",
          "| view | moving px | whole: model | copy-last | copy-first | median | moving: model | copy-last | "
          "copy-first | median | shuffled actions | true - shuffled |",
          "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for v, r in tf["views"].items():
        p = r["psnr"]
        L.append(f"| {v} | {_pct(r['moving_fraction'])} | " +
                 " | ".join(_f(p[k]["whole"]) for k in PREDICTORS) + " | " +
                 " | ".join(_f(p[k]["moving"]) for k in PREDICTORS) +
                 f" | {_f(p['shuffled']['moving'])} | {_f(r['true_minus_shuffled_moving'], '{:+.2f}')} |")
    L += ["", "### Drift (open loop from the first real frames, recorded actions)", "",
          "| view | horizon | episodes | moving px | whole: model | copy-last | copy-first | median | moving: model | "
          "copy-last | copy-first | median |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for v, rows in result["drift"]["views"].items():
        for r in rows:
            p = r["psnr"]
            L.append(f"| {v} | {r['horizon_s']:g} s | {r['n_episodes']} | {_pct(r['moving_fraction'])} | " +
                     " | ".join(_f(p[k]["whole"]) for k in PREDICTORS) + " | " +
                     " | ".join(_f(p[k]["moving"]) for k in PREDICTORS) + " |")
    cf = result["counterfactual"]
    L += ["", f"### Counterfactual actions (recorded chunk +- {100 * cf['distance_m']:g} cm in x / y, "
              "arm centroid vs the temporal median)", "",
          "| view | pairs | points the commanded way | correlation | gain | opposite commands opposite | "
          "commanded px | imagined px | recorded-chunk arm error px | camera fit R^2 (row, col) |",
          "|---|---|---|---|---|---|---|---|---|---|"]
    for v, r in cf["views"].items():
        r2 = cf["calibration_r2"].get(v)
        L.append(f"| {v} | {r['n_pairs']} | {_f(r['direction_agreement'])} | {_f(r['correlation'])} | "
                 f"{_f(r['gain'])} | {_f(r['opposite_fraction'])} | {_f(r['commanded_px'], '{:.1f}')} | "
                 f"{_f(r['imagined_px'], '{:.1f}')} | {_f(r['recorded_position_error_px'], '{:.1f}')} | "
                 + (f"{_f(r2[0])}, {_f(r2[1])}" if r2 else "") + " |")
    idr = result["inverse_dynamics"]
    L += ["", "### Inverse dynamics on real frames (normalised action units, MSE per dimension)", "",
          "| ID (1 step, conditional mean) | floor: zero (training mean) | floor: held-out mean | "
          "ratio to floor | steps |", "|---|---|---|---|---|",
          f"| {_f(idr['mse'], '{:.3f}')} | {_f(idr['zero'], '{:.3f}')} | "
          f"{_f(idr['mean_floor'], '{:.3f}')} | {_f(idr['ratio_to_floor'], '{:.3f}')} | {idr['n_steps']} |"]
    oc = result["outcomes"]
    L += ["", "### Offline outcome reproduction (perception scorer on the open-loop rollout)", ""]
    if not oc.get("available"):
        L.append(f"not available: {oc.get('note')}")
    else:
        L += ["| comparison | objects | language | lifting | placing | lifting and placing | outcome category |",
              "|---|---|---|---|---|---|---|"]
        for k, label in (("imagined_vs_physics", "imagined vs physics"),
                         ("imagined_vs_real_perception", "imagined vs perception(real)"),
                         ("real_perception_vs_physics", "perception(real) vs physics (scorer ceiling)")):
            r = oc[k]
            if r:
                L.append(f"| {label} | {r['n_objects']} | {_f(r['language'])} | {_f(r['lifting'])} | "
                         f"{_f(r['placing'])} | {_f(r['lifting_and_placing'])} | {_f(r['outcome'])} |")
    L += ["", "### Gates", "", "| gate | value | threshold | pass | note |", "|---|---|---|---|---|"]
    for g in result["gates"]:
        L.append(f"| {g['gate']} | {_f(g['value'])} | {g['threshold']:g} | {'PASS' if g['pass'] else 'FAIL'} | "
                 f"{g['note']} |")
    return "\n".join(L) + "\n"


def save_result(result: dict, path: str | Path) -> Path:
    """JSON with non-finite numbers as strings ("inf", "-inf", "nan")."""
    def clean(x):
        if isinstance(x, float) and not math.isfinite(x):
            return str(x)
        if isinstance(x, dict):
            return {str(k): clean(v) for k, v in x.items()}
        if isinstance(x, (list, tuple)):
            return [clean(v) for v in x]
        if isinstance(x, np.generic):
            return clean(x.item())
        return x
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(clean(result), indent=1))
    return path


def load_result(path: str | Path) -> dict:
    """A result written by :func:`save_result`, non-finite numbers restored (ready for :func:`render_table`)."""
    def restore(x):
        if isinstance(x, str) and x in ("inf", "-inf", "nan"):
            return float(x)
        if isinstance(x, dict):
            return {k: restore(v) for k, v in x.items()}
        if isinstance(x, list):
            return [restore(v) for v in x]
        return x
    return restore(json.loads(Path(path).read_text()))


# ================================================================================================================
# CLI
# ================================================================================================================
def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="sc3 diagnose", description="Diagnostics that gate a world-model checkpoint "
                                 "on held-out episodes (docs/world_model.md#diagnostics).")
    ap.add_argument("world_model", help="a `sc3 train` workdir or an exported world model dir")
    ap.add_argument("--data", required=True, help="held-out episode store")
    ap.add_argument("--episodes", type=int, default=None, help="N episodes evenly spaced over the store (default: "
                    "all)")
    ap.add_argument("--cf-starts", type=int, default=DiagnoseConfig.cf_starts, help="counterfactual starts per "
                    "episode")
    ap.add_argument("--out", default=None, help="write the result as JSON here (the table goes to stdout)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--max-seconds", type=float, default=None, help="cap on the open-loop horizon")
    ap.add_argument("--batch", type=int, default=DiagnoseConfig.batch)
    ap.add_argument("--sample-steps", type=int, default=None)
    ap.add_argument("--moving-threshold", type=float, default=DiagnoseConfig.moving_threshold)
    ap.add_argument("--horizons", type=float, nargs="+", default=list(DiagnoseConfig.horizons))
    ap.add_argument("--perception", default=None, help="perception weights (default: the shipped ones)")
    ap.add_argument("--no-progress", action="store_true")
    a = ap.parse_args(argv)
    result = diagnose(a.world_model, a.data, DiagnoseConfig(
        episodes=a.episodes, seed=a.seed, max_seconds=a.max_seconds, batch=a.batch, sample_steps=a.sample_steps,
        moving_threshold=a.moving_threshold, cf_starts=a.cf_starts, horizons=tuple(a.horizons), perception=a.perception,
        progress=not a.no_progress))
    print(render_table(result))
    if a.out:
        print(f"result: {save_result(result, a.out)}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

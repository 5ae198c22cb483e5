"""``sc3 diagnose``'s computation: the checks that gate a world-model checkpoint, on held-out episodes (an episode
store). Everything is computed first (:func:`diagnose` -> a JSON-able dict), then rendered
(``diagnose_report.render_table`` -> markdown). Sections (``l'`` = data.future_frames predicted frames per chunk, at
``rollout.control_hz``), each in the module of its concern:

* frames (``diagnose_video.py``): teacher-forced, one chunk ahead from real context: the context is re-seeded from
  the real frames at every chunk start (chunk c starts at model step c*l, the open-loop rollout's chunk cadence);
  PSNR at the chunk's last frame (``l' / control_hz`` s, 0.8 s for the shipped model) over the whole frame and over
  *moving pixels*, against copy-last (the last real context frame), copy-first (the episode's first frame) and the
  temporal median ("erase the arm": the per-pixel median over all frames of the real episode, what a model that
  blurs the robot away scores); the same with action chunks shuffled across episodes (same noise draws). Drift: open
  loop from the episode's first real frames with the recorded actions (after the episode's end the robot holds
  still, as in the sweep's offline mode), PSNR at fixed horizons, as far as episodes last.
* action following (``diagnose_follow.py``: ``action_following.py``, ``tracking.py``), the headline measures, for
  every action space: counterfactual chunks (the recorded commands shifted along each action axis by a fraction of
  its std) scored by where the imagined arm goes (the learned state head's end effector, or the arm's image
  position) -- the cosine with the commanded direction and the gain; the imagined end effector, arm and objects
  against the real ones in the open loop at 1, 2, 4, 8 s; whether a block the real gripper carries is carried.
* inverse dynamics (``diagnose_actions.py``) on real frames against the mean-action floors.
* outcomes (``diagnose_outcomes.py``): the perception scorer on the open-loop imagined rollout vs the real
  episode's physics labels, per object.
* kept (``diagnose_kept.py``): where objects die, the benchmark's scene measures (objects, the arm) imagined over
  real through the stages: the tokenizer's round trip, one chunk from real context, open loop; filmstrips.
* dense (``diagnose_dense.py``, only when asked for): the imagined object against the real one 0.5 s and 1 s after
  real context on every window in which the real arm carries it, each window's noise from (seed, episode, frame);
  ``diagnose_paired.py`` compares two models window by window (``sc3 diagnose --against``).
* gates (``diagnose_report.py``): each acceptance gate with value, threshold and pass/fail (``GATES``,
  docs/world_model.md).

``DiagnoseConfig.stages`` picks the passes that run: "teacher_forced" (frames one chunk ahead, shuffled actions,
inverse dynamics), "counterfactual", "open_loop" (drift and outcomes), "dense" (not by default). A section of a pass
not run reads ``{"available": false, "note": "not run (--stages)"}`` and its gates neither pass nor fail (``"pass":
null``), so a large outcome set costs only its open-loop rollouts.

Moving pixels of a target frame: any channel differs from the reference frame (the last real context frame) by more
than ``moving_threshold`` in [-1, 1] units (0.06 = 7.65 grey levels: above the renderer's anti-aliasing flicker,
below the arm-on-table contrast).

The sampler runs as the world model's config says: ``sc3 diagnose`` gives it the sweep's evaluation settings
(``world_model_defaults.py``) and the command line's ``--SECTION.FIELD`` overrides. Frames are only ever produced by
the rollout machinery (``rollout.Rollout.run_offline``) and the tokenizer interface, so any tokenizer works unchanged.
"""
from __future__ import annotations

import dataclasses
import math
import time
from pathlib import Path
from typing import Any

import numpy as np

# numpy only, all of them: the module stays cheap for report_bench.py to import
from sc3_jax.evaluation import (diagnose_dense, diagnose_follow, diagnose_kept, diagnose_outcomes, diagnose_paired,
                                 diagnose_video)
from sc3_jax.evaluation.diagnose_actions import InverseErrors, arm_centroid  # noqa: F401  (public names)
from sc3_jax.evaluation.diagnose_config import DEFAULT_STAGES, STAGES, DiagnoseConfig, Stage  # noqa: F401
from sc3_jax.evaluation.diagnose_report import (GATES, NOT_RUN_NOTE, gates, load_result,  # noqa: F401
                                              render_table, save_result, verdict)
from sc3_jax.evaluation.diagnose_video import (PREDICTORS, ErrorSums, moving_mask, psnr_from_sums,  # noqa: F401
                                             squared_errors, temporal_median)


NOT_RUN = {"available": False, "note": NOT_RUN_NOTE}


def load(world_model, model_config=None, store=None):
    """(config, norm stats, params, name) of a path (``sc3 train`` workdir or exported dir) or a loaded triple.
    ``model_config``: the config to evaluate it under (default: its own). ``store``: the held-out store it will read,
    checked against the model's views and image size before its params load (a config.json image size the data
    does not have was a params.npz shape error)."""
    if isinstance(world_model, (str, Path)):
        from sc3_jax.model import checkpoint
        cfg = model_config or checkpoint.read_config(world_model)
        if store is not None:
            _check_store(store, cfg)
        return cfg, checkpoint.read_norm_stats(world_model), checkpoint.load_params(world_model, cfg), str(world_model)
    cfg, stats, params = world_model
    if store is not None:
        _check_store(store, model_config or cfg)
    return model_config or cfg, stats, params, cfg.name if hasattr(cfg, "name") else "<loaded>"


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


@dataclasses.dataclass(frozen=True)
class _Plan:
    """What every stage of one diagnosis shares (:func:`_plan`)."""
    dc: DiagnoseConfig
    cfg: Any
    stats: Any
    params: Any
    views: list
    third: list  # indices of the third-person views (the counterfactual read-out's)
    eps: list
    tf: Any  # Rollout: one chunk of l' frames from real context, every predicted frame kept
    ol: Any  # Rollout: open loop over the longest episode (capped at max_seconds)
    stride: int  # data frames per model step
    keep: int  # l
    off: int  # episode frame of rollout step 0 (the last context frame) from start 0
    batch: int  # dc.batch rounded up to the device count
    samples: list  # (episode, start frame) of every teacher-forced chunk
    donors: list  # per sample, the sample whose actions its shuffled twin gets
    medians: list  # per episode [V, H, W, 3]
    first: list  # per episode its first frame [V, H, W, 3]
    steps_in: list  # per episode the target steps it has from start 0
    horizon_steps: list
    scorer: Any
    scorer_note: str | None
    kept: Any  # diagnose_kept.Kept (the benchmark's scene measures through the stages) or None
    tokenizer: Any  # the world model's, for the round-trip stage
    id_mean: Any  # one sampler step from pure noise = the model's conditional-mean estimate
    follow: Any = None  # diagnose_follow.Follow: the action-following read-outs and tracks


@dataclasses.dataclass
class _Sums:
    """What the stages add up, one group of episodes after another."""
    tf: ErrorSums = dataclasses.field(default_factory=ErrorSums)
    ol: ErrorSums = dataclasses.field(default_factory=ErrorSums)
    inverse: InverseErrors = dataclasses.field(default_factory=InverseErrors)
    cf_rows: list = dataclasses.field(default_factory=list)
    u: list = dataclasses.field(default_factory=list)
    outcomes: list = dataclasses.field(default_factory=list)


def diagnose(world_model, heldout_store, config: DiagnoseConfig | None = None, *, model_config=None,
             scorer_for=None, scene=None, filmstrips=None, locators=None, head=None, category_names=None,
             **overrides) -> dict:
    """Every diagnostic of ``world_model`` (a path or ``(cfg, norm_stats, params)``) on the episode store
    ``heldout_store`` (path or ``EpisodeStore``); see the module docstring. ``model_config``: the world model's
    config to evaluate under (default: its own; ``sc3 diagnose`` passes the sweep's evaluation settings and the
    command line's overrides). ``scorer_for(views, image_size, weights) -> (scorer, None) | (None, why not)``: the
    benchmark's outcome scorer for the open-loop stage (``sc3 diagnose --benchmark NAME`` passes that benchmark's,
    e.g. the simulated one's ``perception_scorer``; None: no outcome reproduction); ``scene``: the benchmark's scene
    measure (``permanence.SceneMeasure``, or a dict of them by name: ``{"objects": ..., "arm": ...}``), with which every
    stage says how much of the objects the imagined frames keep over time (None: not measured); ``filmstrips``: a
    folder for a filmstrip per stage (None: none); ``locators``: the benchmark's (``benchmark.Locators``: the arm,
    its objects, what the actions move; None: the arm by the median rule, no objects); ``head``: the learned state
    head (default: ``state_head.npz`` beside a world model given as a path); ``category_names``: the benchmark's words
    for its outcome categories (``Benchmark.category_names``; None: each by its own name). Returns a JSON-able dict
    (non-finite numbers as floats: write it with :func:`save_result`)."""
    from tqdm import tqdm

    from sc3_jax.data.episodes import EpisodeStore

    dc = dataclasses.replace(config or DiagnoseConfig(), **overrides)
    _check_stages(dc.stages)
    t0 = time.time()
    store = heldout_store if isinstance(heldout_store, EpisodeStore) else EpisodeStore(heldout_store)
    cfg, stats, params, name = load(world_model, model_config, store)
    ids = _episodes(store, cfg, dc.episodes)
    if head is None and isinstance(world_model, (str, Path)):
        from sc3_jax.rollout import state_head
        head = state_head.load(world_model)
    measures = {"objects": scene} if callable(scene) else dict(scene or {})
    p = _plan(cfg, stats, params, store, ids, dc, scorer_for or diagnose_outcomes.no_scorer, measures)
    p = dataclasses.replace(p, follow=diagnose_follow.plan(p, store, head, locators, dc.stages))
    # its windows chosen before any rollout: a store where nothing is carried is one line, not an hour's NaN
    dense = diagnose_dense.plan(p, ids, str(store.root)) if "dense" in dc.stages else None
    acc = _Sums()
    bar = tqdm(total=len(p.eps), desc="diagnose", unit="episode", disable=not dc.progress)
    for g0 in range(0, len(p.eps), p.batch):  # episodes per step: one open-loop batch
        g = list(range(g0, min(g0 + p.batch, len(p.eps))))
        for stage, run in (("teacher_forced", _teacher_forced), ("counterfactual", _counterfactual),
                           ("open_loop", _open_loop)):
            if stage in dc.stages:
                bar.set_postfix_str(stage)
                run(p, acc, g)
        if p.kept is not None:
            _round_trip(p, g)
        bar.update(len(g))
    bar.close()
    result = _result(p, acc, name, store, ids, category_names)
    result["dense"] = dict(NOT_RUN) if dense is None else \
        diagnose_dense.run(p, dense, ids, _imagine(p, dense.rollout, np.asarray))
    if p.kept is not None and filmstrips is not None:
        result["permanence"]["filmstrips"] = p.kept.write_filmstrips(filmstrips, p.views)
    result["gates"] = gates(result, dc)
    result["seconds"] = round(time.time() - t0, 1)
    return result


def _check_stages(stages) -> None:
    from sc3_jax.core.errors import UserError
    bad = [s for s in stages if s not in STAGES]
    if bad or not stages:
        raise UserError(f"--stages {' '.join(map(str, stages)) or '(none)'}: name one or more of {' '.join(STAGES)}")


def _episodes(store, cfg, n: int | None) -> list[str]:
    """The ids to diagnose: ``n`` evenly spaced over the store (stores are ordered by generation knob), or all."""
    _check_store(store, cfg)
    store.check_whole()  # an emptied episode: named, not passed over
    ids = store.episode_ids()
    if n is not None and n < len(ids):
        ids = [ids[i] for i in np.linspace(0, len(ids) - 1, n).round().astype(int)]
    if not ids:
        raise ValueError(f"{store.root}: no episodes")
    return ids


def _check_store(store, cfg) -> None:
    """The held-out store has the world model's views and image size (one line naming both), else nothing fits."""
    from sc3_jax.core.errors import UserError

    views = list(cfg.data.views)
    if [v for v in views if v not in store.views]:
        raise UserError(f"{store.root}/dataset.json: views {list(store.views)}, the world model needs {views} "
                        "(its config.json data.views): give held-out episodes of its cameras")
    if tuple(store.image_size) != tuple(cfg.data.image_size):
        raise UserError(f"{store.root}/dataset.json: images {list(store.image_size)}, the world model takes "
                        f"{list(cfg.data.image_size)} (its config.json data.image_size): give held-out episodes "
                        "at its image size")


def model_fps(cfg, store) -> float:
    """The frame rate the world model (config ``cfg``) was trained at, which its held-out ``store`` must have: its
    config.json's ``data.fps`` (``checkpoint.read_robot``); a model saved before it recorded one: the store's."""
    from sc3_jax.core.errors import UserError

    if cfg.data.fps is None:
        return float(store.fps)
    if abs(float(cfg.data.fps) - float(store.fps)) > 1e-9:
        raise UserError(f"{store.root}/dataset.json: episodes at {store.fps} fps, the world model was trained at "
                        f"{cfg.data.fps} fps (its config.json data.fps): give held-out episodes at its frame rate")
    return float(cfg.data.fps)


def _plan(cfg, stats, params, store, ids, dc: DiagnoseConfig, scorer_for, measures: dict) -> _Plan:
    from sc3_jax.rollout import rollout as ro_mod
    from sc3_jax.core.config import replace
    from sc3_jax.evaluation.world_model import make_sampler
    from sc3_jax.model.tokenizer import make_tokenizer

    views = list(cfg.data.views)
    eps = [store.load(e, mmap=True) for e in ids]
    K, Tp, hz = cfg.data.context_frames, cfg.data.future_frames, cfg.rollout.control_hz
    fps = model_fps(cfg, store)
    s = ro_mod.make_spec(cfg, fps, 1, action_space=stats.action_space)  # the model's action space and frame rate
    # teacher forcing keeps every predicted frame of recorded actions: a policy chunk as long as the window
    whole = dict(keep_frames=Tp, policy_chunk=max(cfg.rollout.policy_chunk, s.raw_needed))
    tf = ro_mod.Rollout(replace(cfg, rollout=whole), stats, data_fps=fps, num_chunks=1)
    stride, keep = s.stride, s.keep
    off = stride * (K - 1)
    steps_in = [(ep.length - 1 - off) // stride for ep in eps]
    if min(steps_in) < 1:
        raise ValueError(f"episodes too short for a rollout: need > {off + stride} frames")
    cap = math.inf if dc.max_seconds is None else int(round(dc.max_seconds * hz))
    n_chunks = max(1, math.ceil(min(max(steps_in), cap) / keep))
    samples = diagnose_video.tf_starts(eps, tf.spec, keep, stride)
    medians = [np.stack([temporal_median(ep.frames[v]) for v in views]) for ep in eps]
    third = [i for i, v in enumerate(views) if "wrist" not in v]
    scorer, note = scorer_for(views, cfg.data.image_size, dc.perception) if "open_loop" in dc.stages else (None, None)
    return _Plan(
        dc=dc, cfg=cfg, stats=stats, params=params, views=views, third=third, eps=eps, tf=tf,
        ol=ro_mod.Rollout(cfg, stats, data_fps=fps, num_chunks=n_chunks), stride=stride, keep=keep, off=off,
        batch=-(-dc.batch // tf.batch_multiple) * tf.batch_multiple, samples=samples,
        donors=diagnose_video.shuffle_donors(samples, np.random.default_rng(dc.seed)), medians=medians,
        first=[np.stack([np.asarray(ep.frames[v][0]) for v in views]) for ep in eps], steps_in=steps_in,
        horizon_steps=[int(round(h * hz)) for h in dc.horizons],
        scorer=scorer, scorer_note=note,
        kept=diagnose_kept.Kept(measures, hz, keep, len(views)) if measures else None,
        tokenizer=make_tokenizer(cfg.model), id_mean=make_sampler(cfg, steps=1))


def _teacher_forced(p: _Plan, acc: _Sums, group: list[int]):
    """Every teacher-forced chunk of the episodes of ``group``, with true and shuffled actions, and inverse dynamics
    on the same real windows."""
    from sc3_jax.rollout import rollout as ro_mod
    bat, spec1 = _Batcher(p.batch), p.tf.spec
    idx = [i for i, (e, _) in enumerate(p.samples) if e in group]
    items = [ro_mod.from_episode(p.eps[p.samples[i][0]], p.views, spec1, start=p.samples[i][1]) for i in idx]
    shuffled = [ro_mod.from_episode(p.eps[p.samples[p.donors[i]][0]], p.views, spec1,
                                    start=p.samples[p.donors[i]][1])[1] for i in idx]
    for a, b in bat.chunks(len(items)):
        part = items[a:b]
        ics = _padded(bat, ro_mod.stack_initial_conditions([it[0] for it in part]))
        keys = np.asarray(ro_mod.episode_keys(p.dc.seed, p.batch, start=idx[a]))
        acts = bat.pad(np.stack([it[1] for it in part]))
        true = p.tf.run_offline(p.params, ics, acts, keys)
        shuf = p.tf.run_offline(p.params, ics, bat.pad(np.stack(shuffled[a:b])), keys)
        acc.u += true["u"][:b - a, 0].tolist()
        for j, it in enumerate(part):
            e, start = p.samples[idx[a + j]]
            if p.kept is not None:  # chunk c covers open-loop steps c*l+1 ... (its first l frames: the table's)
                c0 = start // p.stride
                ks = p.kept.wanted(c0 + 1, c0 + p.keep)
                at = [k - c0 - 1 for k in ks]
                p.kept.add("one chunk", e, ks, true["frames"][j][:, at], it[2][:, at])
            diagnose_video.add_chunk(acc.tf, it[2], it[0][0][:, -1], true["frames"][j], shuf["frames"][j],
                                     p.first[e], p.medians[e], p.dc.moving_threshold)
        _inverse_dynamics(p, acc, ics, bat.pad(np.stack([it[2] for it in part])), acts, idx[a], b - a)


def _inverse_dynamics(p: _Plan, acc: _Sums, ics, targets, acts, first_sample: int, n: int):
    """The ID mode's estimate of the first chunk's actions from real context + real future frames (``targets``)."""
    import jax

    from sc3_jax.model import modes
    window = np.concatenate([ics.frames, targets], axis=2)
    a_norm = p.stats.normalize(acts[:, 0])
    strides = np.full((p.batch,), p.stride, np.int32)
    k = jax.random.fold_in(jax.random.key(p.dc.seed), 10_000 + first_sample)
    pose = None
    if p.cfg.model.pose_conditioning:  # frame K-1's pose counts; the future ones are withheld in ID mode
        from sc3_jax.data.pipeline import integrate_poses
        pose = p.stats.normalize_pose(np.stack([integrate_poses(s0, a0, p.stats.action_space, p.tf.spec.model_dt)
                                                for s0, a0 in zip(ics.state, acts[:, 0])]))
    _, est = p.id_mean(p.params, window, np.zeros_like(a_norm), strides, k, modes.ID, 0, pose)
    acc.inverse.add(np.asarray(est)[:n], a_norm[:n])


def _counterfactual(p: _Plan, acc: _Sums, group: list[int]):
    """The recorded chunk vs chunks shifted along each action axis from the same real starts
    (``diagnose_follow.counterfactual``), every variant of one start with the same noise."""
    from sc3_jax.rollout import rollout as ro_mod
    key_of = lambda k: np.asarray(ro_mod.episode_keys(p.dc.seed + 1, 1, start=k))[0]  # noqa: E731
    acc.cf_rows += diagnose_follow.counterfactual(p, p.follow, group, _imagine(p, p.tf, key_of))


def _imagine(p: _Plan, rollout, key_of):
    """``imagine(ics, actions, noise) -> frames [V, n, H, W, 3]`` each: ``rollout``'s offline run in batches; each
    item's sampler key ``key_of(its noise)`` (raw key data [2])."""
    from sc3_jax.rollout import rollout as ro_mod
    bat = _Batcher(p.batch)

    def imagine(ics, actions, noise):
        out = []
        for a, b in bat.chunks(len(ics)):
            ic = _padded(bat, ro_mod.stack_initial_conditions(ics[a:b]))
            keys = np.stack([key_of(k) for k in noise[a:b]])
            res = rollout.run_offline(p.params, ic, bat.pad(np.stack(actions[a:b])), bat.pad(keys))
            out += [res["frames"][j] for j in range(b - a)]
        return out
    return imagine


def _open_loop(p: _Plan, acc: _Sums, group: list[int]):
    """Open loop from each episode's first real frames with its recorded actions: drift and outcomes."""
    from sc3_jax.rollout import rollout as ro_mod
    bat, S, K = _Batcher(p.batch), p.ol.spec, p.cfg.data.context_frames
    ics_l, acts_l, tgts, valids = [], [], [], []
    for e in group:
        ep = p.eps[e]
        frames = np.stack([np.asarray(ep.frames[v]) for v in p.views])
        ics_l.append((frames[:, [p.stride * i for i in range(K)]], ro_mod.initial_state(ep, S, p.off), np.int32(0)))
        acts_l.append(ro_mod.chunk_actions(np.asarray(ep.actions)[p.off:], S))
        t, v = ro_mod.recorded_targets(frames[:, p.off:], S)
        tgts.append(t)
        valids.append(v)
    for a, b in bat.chunks(len(group)):
        ics = _padded(bat, ro_mod.stack_initial_conditions(ics_l[a:b]))
        keys = np.asarray(ro_mod.episode_keys(p.dc.seed + 2, p.batch, start=group[a]))
        out = p.ol.run_offline(p.params, ics, bat.pad(np.stack(acts_l[a:b])), keys)
        for j in range(b - a):
            e = group[a + j]
            pred, tgt, valid = out["frames"][j], tgts[a + j], valids[a + j]
            ctx_last = ics.frames[j][:, -1]
            for hi, hs in enumerate(p.horizon_steps):
                if hs <= len(valid) and valid[hs - 1]:
                    diagnose_video.add_horizon(acc.ol, ("drift", hi), pred[:, hs - 1], tgt[:, hs - 1], ctx_last,
                                               p.first[e], p.medians[e], p.dc.moving_threshold)
            if p.kept is not None:  # step k (k >= 1) is predicted frame k - 1, as far as the episode was recorded
                ks = p.kept.wanted(1, int(np.asarray(valid).sum()))
                at = [k - 1 for k in ks]
                p.kept.add("open loop", e, ks, pred[:, at], tgt[:, at])
            diagnose_follow.track(p, p.follow, e, ctx_last, pred, tgt, int(np.asarray(valid).sum()), acts_l[a + j])
            if p.scorer is not None:
                acc.outcomes.append(diagnose_outcomes.outcome(p.scorer, p.eps[e], ics.frames[j], pred, tgt, valid,
                                                              p.steps_in[e]))


def _round_trip(p: _Plan, group: list[int]):
    """The round-trip stage: the episodes' real frames at the table's times through the tokenizer alone."""
    for e in group:
        ep = p.eps[e]
        ks = p.kept.wanted(1, (ep.length - 1 - p.off) // p.stride)
        if ks:
            real = np.stack([np.asarray(ep.frames[v])[[p.off + p.stride * k for k in ks]] for v in p.views])
            p.kept.add("round trip", e, ks, diagnose_kept.round_trip(p.tokenizer, real, p.cfg.data.image_size), real)


def _kept_section(p: _Plan) -> dict:
    """Objects kept stage by stage (``diagnose_kept``), or a note why not."""
    if p.kept is None:
        return {"note": "no scene measure (a benchmark's: `sc3 diagnose --benchmark NAME` names whose)"}
    return p.kept.section(p.views, p.dc.seed)


def _result(p: _Plan, acc: _Sums, name: str, store, ids, category_names=None) -> dict:
    cfg, dc, spec = p.cfg, p.dc, p.tf.spec
    ran = lambda stage, section: section() if stage in dc.stages else dict(NOT_RUN)  # noqa: E731
    return {
        "world_model": name, "data": str(store.root), "episodes": ids, "seconds": None,
        "settings": {**dataclasses.asdict(dc), "context_frames": cfg.data.context_frames,
                     "future_frames": cfg.data.future_frames, "keep_frames": p.keep,
                     "control_hz": cfg.rollout.control_hz, "data_fps": store.fps, "stride": p.stride,
                     # the sampler as it ran: forward-dynamics steps, and those of the re-read that yields U
                     "sample_steps": spec.steps, "inverse_steps": spec.inverse_steps or spec.steps,
                     "open_loop_chunks": p.ol.spec.num_chunks, "batch": p.batch},
        "views": p.views, "third_person_views": [p.views[i] for i in p.third],
        "teacher_forced": ran("teacher_forced", lambda: diagnose_video.tf_section(
            acc.tf, p.views, cfg.data.future_frames / cfg.rollout.control_hz, len(p.samples), acc.u)),
        "drift": ran("open_loop", lambda: diagnose_video.drift_section(acc.ol, p.views, dc.horizons,
                                                                       p.horizon_steps)),
        "counterfactual": ran("counterfactual", lambda: diagnose_follow.section(p, p.follow, acc.cf_rows)),
        # per episode too: what a paired comparison of two models (diagnose_paired.py) resamples
        "tracking": ran("open_loop", lambda: {**p.follow.tracks.section(seed=dc.seed),
                                              "per_episode": diagnose_paired.per_episode(p.follow.tracks, ids)}),
        "inverse_dynamics": ran("teacher_forced", acc.inverse.section),
        "outcomes": ran("open_loop", lambda: diagnose_outcomes.outcome_section(acc.outcomes, p.scorer_note,
                                                                               seed=dc.seed, names=category_names)),
        "permanence": _kept_section(p),
    }


def _padded(bat, ics):
    """``ics`` with each given field padded to the batch (``bat.pad``)."""
    return type(ics)(*(x if x is None else bat.pad(x) for x in ics))

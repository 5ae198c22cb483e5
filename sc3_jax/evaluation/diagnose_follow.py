"""``sc3 diagnose``'s action-following passes, glued to its plan: which read-outs a model and a store allow, the
counterfactual chunks through the teacher-forced rollout, and the open-loop position tracks
(``action_following.py``, ``tracking.py``, ``moved.py`` hold the measures; this module only feeds them).

Read-outs, for any action space: the learned state head (``state_head.npz`` beside the world model) where the store
records the state it was trained on and something says which entries the actions move (``moved.moved``); the arm's
image position in every third-person view (the benchmark's arm locator, else the median rule of ``locate.py``)."""
from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from sc3_jax.measures import action_following as af
from sc3_jax.measures import locate, tracking
from sc3_jax.measures import moved as mv


@dataclasses.dataclass
class Follow:
    moved: mv.Moved
    read: Any  # the head's read(robot0, actions, frames) -> states, or None
    arm: Any  # e -> the arm locator of episode e
    objects: dict  # name -> locator
    readouts: list  # the counterfactual's (HeadReadout, PixelReadout per third-person view with a fitted map)
    maps: dict  # view -> {"r2", "n"} of the image map
    axes: tuple
    notes: list
    tracks: tracking.Tracks | None


def head_reader(head: dict, action_dim: int):
    """``read(robot0 [S], actions [..., n, A], frames uint8 [V, n, H, W, 3]) -> [n, S]``: ``state_head.unroll``
    jitted, on the first n actions."""
    import jax

    from sc3_jax.rollout import state_head
    from sc3_jax.model.tokenizer import to_unit
    unroll = jax.jit(state_head.unroll)

    def read(robot0, actions, frames):
        n = frames.shape[1]
        a = np.asarray(actions, np.float32).reshape(-1, action_dim)[:n]
        return np.asarray(unroll(head, np.asarray(robot0, np.float32), a, to_unit(np.moveaxis(frames, 1, 0))))
    return read


def plan(p, store, head, locators, stages) -> Follow:
    """The read-outs of plan ``p`` (``diagnose._Plan``'s fields) on ``store``; the image maps are fitted on every
    teacher-forced chunk of the real episodes when the counterfactual pass runs."""
    space, dc = p.stats.action_space, p.dc
    moved = mv.moved(space, store, dict(locators.moves) if locators else None)
    notes = [f"what the actions move: {moved.how}"]
    read = None
    if head is None:
        notes.append("no state head beside the world model (sc3 train-state): the arm is read in pixels only")
    elif moved.source != "state":
        notes.append("the state head is not read: nothing says which state entries the actions move")
    elif int(np.shape(head["state_mean"])[0]) != store.state_dim:
        notes.append(f"the state head reads a {np.shape(head['state_mean'])[0]}-D state, the store records "
                     f"{store.state_dim}: not read")
    else:
        read = head_reader(head, space.dim)
    cache: dict = {}

    def arm(e):
        if locators is not None and locators.arm is not None:
            return locators.arm
        if e not in cache:
            cache[e] = locate.median_arm(p.medians[e], dc.arm_threshold, dc.min_arm_pixels)
        return cache[e]
    objects = dict(locators.objects) if locators else {}
    readouts, maps, axes = [], {}, tuple(moved.axes) or tuple(range(space.dim))
    if "counterfactual" in stages:
        chunks = _real_chunks(p)
        if read is not None:
            fs = af.fit_state_map([(a, st) for _, a, _, st in chunks if st is not None], space, p.tf.spec.model_dt,
                                  axes, af.cols_of(moved, axes))
            maps["state"] = {"r2": fs["r2"], "n": fs["n"]}
            readouts.append(af.HeadReadout(read, moved, store.state_names, fs["map"], axes))
        fitted = af.fit_image_map([c[:3] for c in chunks], arm, p.views, space, p.tf.spec.model_dt, axes)
        for v in p.third:
            maps[p.views[v]] = {"r2": fitted[v]["r2"], "n": fitted[v]["n"]}
            if fitted[v]["map"] is not None:
                readouts.append(af.PixelReadout(v, p.views, arm, fitted[v]["map"]))
        if read is None:  # pixels alone: the axes whose shift shows in some view
            n = p.tf.spec.predict
            seen = [i for i in axes if any(
                np.linalg.norm(ro.commanded(i, mv.shift_displacement(space, i, dc.cf_fraction * p.stats.std[i], n,
                                                                     p.tf.spec.model_dt))) >= af.MIN_PX
                for ro in readouts)]
            axes = tuple(seen)
    tracks = tracking.Tracks(p.cfg.rollout.control_hz, p.views, dc.carry_px) if "open_loop" in stages else None
    return Follow(moved, read, arm, objects, readouts, maps, axes, notes, tracks)


def _real_chunks(p):
    """(episode, model-rate actions [l', A], real frames at the chunk's start and end [V, 2, H, W, 3], the recorded
    state there [2, S] or None) of a chunk from every stride-th frame of every episode (the maps need more chunks
    than the teacher-forced starts)."""
    from sc3_jax.rollout import rollout as ro_mod
    out = []
    s = p.tf.spec
    span = p.stride * s.predict
    for e, ep in enumerate(p.eps):
        acts_all = np.asarray(ep.actions)
        for f0 in range(p.off, ep.length - span, p.stride):
            acts = ro_mod.chunk_actions(acts_all[f0:], s)[0]
            state = None if getattr(ep, "state", None) is None else np.asarray(ep.state, np.float64)[[f0, f0 + span]]
            out.append((e, acts, np.stack([np.asarray(ep.frames[v])[[f0, f0 + span]] for v in p.views]), state))
    return out


def counterfactual(p, f: Follow, group: list[int], imagine) -> list[dict]:
    """The counterfactual rows of ``dc.cf_starts`` evenly spaced teacher-forced starts of each episode of
    ``group``."""
    from sc3_jax.rollout import rollout as ro_mod
    if not f.readouts or not f.axes:
        return []
    starts = []
    for e in group:
        mine = [st for ee, st in p.samples if ee == e]
        pick = sorted({mine[int(round(q))] for q in np.linspace(0, len(mine) - 1, min(p.dc.cf_starts, len(mine)))})
        for st in pick:
            ic, acts, _ = ro_mod.from_episode(p.eps[e], p.views, p.tf.spec, start=st)
            robot = None if getattr(p.eps[e], "state", None) is None else np.asarray(p.eps[e].state[st + p.off])
            starts.append({"episode": e, "start": st, "ic": ic, "actions": acts, "robot": robot,
                           "noise": e * 100_000 + st})
    return af.run(starts, imagine, f.readouts, p.stats.action_space, f.axes, p.stats.std, p.dc.cf_fraction,
                  p.tf.spec.model_dt)


def track(p, f: Follow, e: int, ctx_last, pred, tgt, n: int, actions) -> None:
    """One open-loop rollout of episode ``e`` into the tracks: ``pred`` / ``tgt`` [V, >= n, H, W, 3] its n valid
    imagined and real steps after the last context frame ``ctx_last`` [V, H, W, 3]; ``actions`` its model-rate
    actions [N, l', A] (the first l of every chunk are the kept steps')."""
    if f.tracks is None or n < 1:
        return
    ep = p.eps[e]
    keep = p.keep
    im = np.concatenate([ctx_last[:, None], pred[:, :n]], 1)
    re = np.concatenate([ctx_last[:, None], tgt[:, :n]], 1)
    if f.read is not None:
        acts = np.asarray(actions)[:, :keep].reshape(-1, actions.shape[-1])[:n]
        st = np.asarray(ep.state, np.float64)
        real = st[[p.off + p.stride * k for k in range(n + 1)]][:, list(f.moved.pose)]
        robot0 = st[p.off]
        head_im = np.asarray(f.read(robot0, acts, pred[:, :n]))[:, list(f.moved.pose)]
        head_re = np.asarray(f.read(robot0, acts, tgt[:, :n]))[:, list(f.moved.pose)]
        f.tracks.add_state("state head", "robot units: " + ", ".join(f.moved.names), e,
                           np.concatenate([real[:1], head_im]), np.concatenate([real[:1], head_re]), real)
    arm_im, arm_re = f.arm(e)(im, p.views), f.arm(e)(re, p.views)
    f.tracks.add_pixels("arm", "arm", e, arm_im, arm_re)
    for name, loc in f.objects.items():
        o_im, o_re = loc(im, p.views), loc(re, p.views)
        # several objects: also pooled ("every object"), the headline's row; each one's in the JSON
        for as_ in [name] + (["every object"] if len(f.objects) > 1 else []):
            f.tracks.add_pixels("objects", as_, e, o_im, o_re)
            f.tracks.add_carried(as_, e, o_im, arm_im, o_re, arm_re)


def section(p, f: Follow, rows: list[dict]) -> dict:
    """The counterfactual section: per read-out cosine and gain with intervals, and how they were read."""
    space = p.stats.action_space
    readouts = af.section(rows, space.names, seed=p.dc.seed)
    order = [k for k in readouts if readouts[k]["kind"] == "state"] + \
        [k for k in readouts if k.startswith("arm pixels: every")] + list(readouts)
    return {"fraction_of_std": p.dc.cf_fraction, "axes": [space.names[i] for i in f.axes],
            "shift_raw": {space.names[i]: float(p.dc.cf_fraction * p.stats.std[i]) for i in f.axes},
            "image_map": f.maps, "notes": f.notes, "readouts": readouts, "headline": order[0] if order else None}

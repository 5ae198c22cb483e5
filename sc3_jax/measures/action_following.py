"""Does the imagined arm go where it is commanded? ``sc3 diagnose``'s counterfactual chunks, for any action space.

From a held-out window's real context, the world model imagines one chunk under the recorded commands and under
the same commands shifted along one action axis (+- ``fraction`` of that axis's recorded std, on every action of
the chunk: a velocity or a delta moves the arm further, a target is moved itself; ``moved.shift_displacement``
says how far). A read-out says where the arm is at the chunk's end in each imagination; the measured displacement
``m`` (shifted minus recorded imagination, same noise) is scored against the commanded displacement ``d``:

* cosine ``m.d / (|m| |d|)`` -- 1: the arm goes the commanded way, 0: it does not move or moves at random (an arm
  that does not move at all reads 0, not undefined: it points no way);
* gain ``m.d / |d|^2`` -- the fraction of the commanded displacement the imagined arm makes along it.

Read-outs (:class:`HeadReadout`, :class:`PixelReadout`): the world model's learned state head (``state_head.py``),
in the robot's units, where the model has one and something says which state entries the actions move
(``moved.py``); and the arm's image position per third-person view (a benchmark's arm locator, or the median rule
of ``locate.py``), the commanded displacement mapped to pixels by a linear map fitted on the real frames
(:func:`fit_image_map`: what the recorded chunks command -> how far the real arm moved in the image). Means over
(start, axis, sign) with percentile-bootstrap intervals resampling episodes (``stats.resample``).

The world model is called through ``imagine(ics, actions, noise) -> frames``: a test hands in doubles. numpy only
(the head's unroll comes in as a function)."""
from __future__ import annotations

import math

import numpy as np

from sc3_jax.measures import moved as mv
from sc3_jax.stats import interval, resample

DRAWS = 2000
MIN_PX = 0.5  # a commanded image shift below half a pixel says nothing a centroid could read


def cols_of(moved: mv.Moved, axes=None) -> list[int]:
    """The state entries the shifted ``axes`` (default: every axis ``moved`` maps) move, sorted."""
    return sorted({moved.entry_of(i) for i in (moved.axes if axes is None else axes)} - {None})


class HeadReadout:
    """The arm as the learned state head reads it off the frames, entries ``cols`` of the state (``Moved``).
    ``read(robot0 [S], actions [n, A], frames uint8 [V, n, H, W, 3]) -> states [n, S]``. It is fed the recorded
    actions under every variant, so a difference between variants comes from the frames alone (the head also reads
    the actions: fed the shifted ones it would move with them whatever the frames show)."""

    kind = "state"

    def __init__(self, read, moved: mv.Moved, state_names, state_map: np.ndarray | None = None, axes=None):
        self.read, self.moved, self.map = read, moved, state_map
        self.cols = cols_of(moved, axes)  # [A, len(cols)] is state_map's shape (fit_state_map)
        self.name = "end effector (state head): " + ", ".join(state_names[j] for j in self.cols)

    def position(self, start: dict, frames: np.ndarray) -> np.ndarray:
        return np.asarray(self.read(start["robot"], start["actions"], frames))[-1, self.cols]

    def commanded(self, axis: int, disp: float) -> np.ndarray:
        """The state map's row (:func:`fit_state_map`: the recorded units per commanded unit) where one was fitted,
        else the entry the axis moves, one for one."""
        if self.map is not None:
            return self.map[axis] * disp
        d = np.zeros(len(self.cols))
        j = self.moved.entry_of(axis)
        if j is not None:
            d[self.cols.index(j)] = disp
        return d


class PixelReadout:
    """The arm's image position in view ``v``; the commanded displacement in pixels through ``image_map`` [A, 2]
    (:func:`fit_image_map`). ``locator(e)``: episode ``e``'s arm locator (``benchmark.Locators``' signature)."""

    kind = "pixels"

    def __init__(self, v: int, views, locator, image_map: np.ndarray):
        self.v, self.views, self.locator, self.map = v, list(views), locator, np.asarray(image_map)
        self.name = f"arm pixels: {views[v]}"

    def position(self, start: dict, frames: np.ndarray) -> np.ndarray:
        return self.locator(start["episode"])(frames[:, -1:], self.views)[self.v, 0]

    def commanded(self, axis: int, disp: float) -> np.ndarray:
        return self.map[axis] * disp


def fit_image_map(chunks, locator, views, space, dt: float, axes=None) -> dict:
    """Per view the least-squares map [A, 2] from what a real chunk commands along ``axes`` (default every axis;
    ``moved.chunk_displacement``) to how far the real arm's image position moved over it, no intercept (a chunk
    that commands nothing leaves the arm put), with R^2 per image coordinate; the other axes' rows are 0.
    ``chunks``: (episode, model-rate actions [n, A], real frames at the chunk's start and end [V, 2, H, W, 3]).
    None where fewer than max(8, 2 x axes) chunks show the arm at both ends."""
    axes = list(range(space.dim) if axes is None else axes)
    X, Y = [], {}
    for e, acts, pair in chunks:
        pos = locator(e)(pair, views)  # [V, 2, 2]
        X.append(mv.chunk_displacement(space, acts, dt)[axes])
        for v in range(len(views)):
            Y.setdefault(v, []).append(pos[v, 1] - pos[v, 0])
    out = {}
    X = np.asarray(X).reshape(len(X), len(axes))
    for v, ys in Y.items():
        ys = np.asarray(ys)
        ok = np.all(np.isfinite(ys), 1)
        if ok.sum() < max(8, 2 * len(axes)):
            out[v] = {"map": None, "r2": [math.nan, math.nan], "n": int(ok.sum())}
            continue
        J = np.zeros((space.dim, 2))
        J[axes] = np.linalg.lstsq(X[ok], ys[ok], rcond=None)[0]
        res = ys[ok] - X[ok] @ J[axes]
        r2 = 1 - (res ** 2).sum(0) / np.maximum(((ys[ok] - ys[ok].mean(0)) ** 2).sum(0), 1e-12)
        out[v] = {"map": J, "r2": [float(x) for x in r2], "n": int(ok.sum())}
    return out


def fit_state_map(chunks, space, dt: float, axes, cols) -> dict:
    """The least-squares map [A, len(cols)] from what a real chunk commands along ``axes`` to how far the recorded
    state entries ``cols`` moved over it (no intercept; R^2 per entry): the commanded displacement in the state's own
    units whatever the actions' scale (a velocity in [-1, 1] that moves the gripper at 0.2 m/s). ``chunks``:
    (model-rate actions [n, A], the recorded state at the chunk's start and end [2, S])."""
    X = np.asarray([mv.chunk_displacement(space, a, dt)[list(axes)] for a, _ in chunks]).reshape(-1, len(axes))
    Y = np.asarray([st[1, cols] - st[0, cols] for _, st in chunks], np.float64).reshape(-1, len(cols))
    ok = np.all(np.isfinite(Y), 1)
    if ok.sum() < max(8, 2 * len(axes)):
        return {"map": None, "r2": [math.nan] * len(cols), "n": int(ok.sum())}
    J = np.zeros((space.dim, len(cols)))
    J[list(axes)] = np.linalg.lstsq(X[ok], Y[ok], rcond=None)[0]
    res = Y[ok] - X[ok] @ J[list(axes)]
    r2 = 1 - (res ** 2).sum(0) / np.maximum(((Y[ok] - Y[ok].mean(0)) ** 2).sum(0), 1e-12)
    return {"map": J, "r2": [float(x) for x in r2], "n": int(ok.sum())}


def shifted(actions: np.ndarray, axes, std: np.ndarray, fraction: float) -> list[tuple[str, int, float, np.ndarray]]:
    """(variant name, axis, shift in raw units, actions) for the recorded chunk ``actions`` [..., n, A] and each axis
    of ``axes`` shifted by +- ``fraction`` of its recorded ``std``; the recorded chunk first (axis -1)."""
    out = [("recorded", -1, 0.0, np.asarray(actions))]
    for i in axes:
        for sign in (1.0, -1.0):
            a = np.array(actions, np.float32, copy=True)
            delta = sign * fraction * float(std[i])
            a[..., i] += delta
            out.append((f"{'+' if sign > 0 else '-'}{i}", i, delta, a))
    return out


def run(starts, imagine, readouts, space, axes, std, fraction: float, dt: float) -> list[dict]:
    """Every start's variants imagined (one batch) and read: one row per (start, read-out, shifted variant).
    ``starts``: dicts with "episode", "start", "ic" (one condition), "actions" (model-rate [1, n, A] raw), "robot"
    (the recorded state there, or None), optionally "noise" (its noise id; default its index); ``imagine(ics, actions, noise ids) -> frames [V, n, H, W, 3]`` each (the
    variants of one start share a noise id, so what differs between them is the actions)."""
    jobs = [(k, var) for k, s in enumerate(starts) for var in shifted(s["actions"], axes, std, fraction)]
    frames = imagine([starts[k]["ic"] for k, _ in jobs], [var[3] for _, var in jobs],
                     [starts[k].get("noise", k) for k, _ in jobs])
    by_start: dict[int, dict] = {}
    for (k, (name, axis, delta, _)), f in zip(jobs, frames):
        by_start.setdefault(k, {})[name] = (axis, delta, f)
    rows = []
    for k, variants in by_start.items():
        s = starts[k]
        n = s["actions"].shape[-2]
        for ro in readouts:
            ref = ro.position(s, variants["recorded"][2])
            for name, (axis, delta, f) in variants.items():
                if axis < 0:
                    continue
                m = ro.position(s, f) - ref
                d = ro.commanded(axis, mv.shift_displacement(space, axis, delta, n, dt))
                rows.append({"episode": s["episode"], "start": s["start"], "readout": ro.name, "kind": ro.kind,
                             "axis": axis, "variant": name, "measured": m.tolist(), "commanded": d.tolist()})
    return rows


def pair_scores(m: np.ndarray, d: np.ndarray) -> tuple[float, float]:
    """(cosine, gain) of a measured displacement ``m`` against the commanded ``d``; cosine 0 where ``m`` is 0."""
    dd = float(d @ d)
    nm = float(np.linalg.norm(m))
    dot = float(m @ d)
    return (dot / (nm * math.sqrt(dd)) if nm > 1e-12 else 0.0), dot / dd


def scored(rows) -> list[dict]:
    """The rows a read-out could score (finite, a commanded displacement it can see), with "cosine" and "gain"."""
    out = []
    for r in rows:
        m, d = np.asarray(r["measured"], np.float64), np.asarray(r["commanded"], np.float64)
        if not (np.all(np.isfinite(m)) and np.all(np.isfinite(d))):
            continue
        if np.linalg.norm(d) < (MIN_PX if r["kind"] == "pixels" else 1e-12):
            continue
        c, g = pair_scores(m, d)
        out.append({**r, "cosine": c, "gain": g})
    return out


def episode_mean(values: dict, draws: int = DRAWS, seed: int = 0) -> dict:
    """{"value", "lo", "hi", "nan_draws", "n", "episodes"}: the mean of every item of ``values`` (episode -> list of
    numbers), with the percentile interval of resampling episodes (an episode's items share its frames: they are not
    independent draws); no interval from a single episode."""
    eps = [e for e in values if len(values[e])]
    sums = np.array([np.sum(values[e]) for e in eps], np.float64)
    cnts = np.array([len(values[e]) for e in eps], np.float64)
    n = int(cnts.sum())
    if not n:
        return {"value": math.nan, "lo": math.nan, "hi": math.nan, "nan_draws": 0, "n": 0, "episodes": 0}
    point = float(sums.sum() / cnts.sum())
    if len(eps) < 2:
        return {"value": point, "lo": math.nan, "hi": math.nan, "nan_draws": 0, "n": n, "episodes": len(eps)}
    w = resample.multiplicities(len(eps), draws, seed)
    return {**interval.summary(point, (w @ sums) / (w @ cnts)), "n": n, "episodes": len(eps)}


def section(rows, names_of_axes, draws: int = DRAWS, seed: int = 0) -> dict:
    """Per read-out (and the pixel views pooled) the cosine and the gain with intervals, and per axis."""
    ok = scored(rows)
    out = {}
    groups = {}
    for r in ok:
        groups.setdefault(r["readout"], []).append(r)
    pixel_views = [k for k in groups if groups[k][0]["kind"] == "pixels"]
    if len(pixel_views) > 1:
        groups["arm pixels: every third-person view"] = [r for k in pixel_views for r in groups[k]]
    for name, sel in groups.items():
        def stat(key, keep=lambda r: True):
            per: dict = {}
            for r in sel:
                if keep(r):
                    per.setdefault(r["episode"], []).append(r[key])
            return episode_mean(per, draws, seed)
        out[name] = {"kind": sel[0]["kind"], "cosine": stat("cosine"), "gain": stat("gain"),
                     "axes": {names_of_axes[a]: {"cosine": stat("cosine", lambda r, a=a: r["axis"] == a),
                                                 "gain": stat("gain", lambda r, a=a: r["axis"] == a)}
                              for a in sorted({r["axis"] for r in sel})}}
    return out

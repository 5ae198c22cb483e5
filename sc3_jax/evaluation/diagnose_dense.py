"""``sc3 diagnose``'s dense probe (stage "dense"): where the imagined object is a moment after real context, on every
window of the held-out episodes in which the real arm carries it. The open-loop tracks give one error per episode and
time, with a spread over episodes too wide to tell a change to the recipe from a seed on a few episodes; windows give
hundreds, and ``diagnose_paired.py`` compares two models window by window on the same noise.

A window is a last context frame f0: every model step of every episode from the first whole context on, while one
rollout's real targets follow (``rollout.max_offline_chunks``). From the real frames up to f0 and the recorded actions
the model imagines what follows (``Rollout.run_offline``, the teacher-forced pass's rollout: one chunk of l' frames,
every one kept; chunk after chunk only where a horizon lies past l'). At each horizon of :data:`SECONDS` (k =
round(s * rollout.control_hz) model steps, data frame f0 + k * stride) and each view where the benchmark's locator
reads the object (SO-101: the block in the workspace view), the window counts where the real object is carried there:
it moved at least ``carry_px`` from its place at f0 the way the arm moved (``tracking.moves_with``, the open-loop
"carried" rule). Its error is the object located in the imagined frame against the real frame at the same time, in
pixels; an imagined frame that shows no object is "lost" (counted, not averaged). Beside it, holding the start (the
object left where it was at f0: its real displacement, at least ``carry_px`` by construction).

Noise: a window's sampler key is ``fold_in(fold_in(key(seed + KEY_STREAM), crc32(episode id)), f0)``, nothing of the
model, so two models compared see the same noise per window (the same draws where their latents have one shape).

Means pool windows; intervals resample episodes (an episode's windows share its frames and motion:
``action_following.episode_mean``). numpy at import; the keys and the rollouts import JAX where they run."""
from __future__ import annotations

import dataclasses
import math
import zlib
from typing import Any

import numpy as np

from sc3_jax.measures import tracking
from sc3_jax.measures.action_following import DRAWS, episode_mean

SECONDS = (0.5, 1.0)
KEY_STREAM = 3  # the teacher-forced, counterfactual and open-loop passes draw from seed, seed + 1, seed + 2
REFERENCES = ("imagined", "hold the start")


@dataclasses.dataclass(frozen=True)
class Window:
    episode: int  # index into the diagnosis' episodes
    f0: int  # the last real context frame
    carried: tuple  # (object, view index, time label, real position at f0, real position then) where carried


@dataclasses.dataclass(frozen=True)
class Dense:
    """What the probe runs (:func:`plan`)."""
    steps: dict  # time label -> model steps after f0
    rollout: Any  # rollout.Rollout: from real context, at least max(steps) frames kept
    windows: list
    candidates: int  # windows considered (carried or not)
    keys: np.ndarray  # uint32 [len(windows), 2]: each window's sampler key data
    objects: dict  # name -> locator


def steps_of(seconds, hz: float) -> dict[str, int]:
    """Time label ("0.5 s") -> model steps after the last context frame at ``hz`` (the model's rollout.control_hz); a
    horizon under one step has no frame and is left out."""
    out = {f"{s:g} s": int(round(s * hz)) for s in seconds}
    return {k: v for k, v in out.items() if v >= 1}


def window_keys(seed: int, episode_ids, frames) -> np.ndarray:
    """uint32 [n, 2]: the sampler key data of each window (episode id, last context frame f0), from these and
    ``seed`` alone; an id is folded in by its CRC-32 (stable across processes, unlike ``hash``)."""
    import jax
    import jax.numpy as jnp
    ep = jnp.asarray([zlib.crc32(str(e).encode()) & 0x7FFFFFFF for e in episode_ids], jnp.uint32)
    base = jax.random.key(seed)
    one = lambda e, f: jax.random.key_data(jax.random.fold_in(jax.random.fold_in(base, e), f))  # noqa: E731
    return np.asarray(jax.vmap(one)(ep, jnp.asarray(frames, jnp.uint32)))


def select(eps, views, spec, arm_of, objects: dict, carry_px: float, steps: dict) -> tuple[list[Window], int]:
    """(the windows in which the real arm carries an object at some horizon of ``steps``, how many windows there
    were) over episodes ``eps`` whose rollouts have ``spec``; ``arm_of(e)``: episode e's arm locator, ``objects``:
    name -> locator (``benchmark.Locators``). Real frames only: nothing is imagined here."""
    from sc3_jax.rollout.rollout import max_offline_chunks
    off = spec.stride * (spec.context - 1)
    windows, candidates = [], 0
    for e, ep in enumerate(eps):
        n = 0  # windows of this episode: a later f0 never has more room (max_offline_chunks falls with the start)
        while max_offline_chunks(ep.length, spec, n * spec.stride) >= spec.num_chunks:
            n += 1
        if not n:
            continue
        candidates += n
        grid = off + spec.stride * np.arange(n + max(steps.values()))  # f0 of window j is grid[j]
        frames = np.stack([np.asarray(ep.frames[v])[grid] for v in views])
        arm = arm_of(e)(frames, views)
        where = {name: loc(frames, views) for name, loc in objects.items()}
        for j in range(n):
            at = [j] + [j + k for k in steps.values()]
            hits = tuple((name, v, label, tuple(pos[v, j]), tuple(pos[v, j + k]))
                         for name, pos in where.items() for v in range(len(views))
                         for (label, k), carried in zip(steps.items(),
                                                        tracking.moves_with(pos[v, at], arm[v, at], carry_px))
                         if carried)
            if hits:
                windows.append(Window(e, int(grid[j]), hits))
    return windows, candidates


def plan(p, ids, data: str) -> Dense:
    """The probe of diagnosis plan ``p`` (``diagnose._Plan``) over the episodes ``ids`` of store ``data``: its
    windows and keys, chosen before any rollout; a one-line UserError where there is nothing to measure."""
    from sc3_jax.core.errors import UserError
    from sc3_jax.rollout import rollout as ro_mod

    objects = dict(p.follow.objects)
    if not objects:
        raise UserError("--stages dense: the probe locates a benchmark's objects and this diagnosis has none: name "
                        "a benchmark whose locators read them (--benchmark so101: the block)")
    steps = steps_of(SECONDS, p.cfg.rollout.control_hz)
    if not steps:
        raise UserError(f"--stages dense: rollout.control_hz {p.cfg.rollout.control_hz:g} has no model step within "
                        f"{max(SECONDS):g} s")
    need, spec = max(steps.values()), p.tf.spec
    if need <= spec.predict:  # one chunk of every predicted frame: the teacher-forced pass's own rollout
        rollout = p.tf
    else:  # a horizon past l': chunk after chunk, as the open loop does, from each window's real context
        rollout = ro_mod.Rollout(p.cfg, p.stats, data_fps=spec.data_fps, num_chunks=math.ceil(need / p.keep))
    windows, n = select(p.eps, p.views, rollout.spec, p.follow.arm, objects, p.dc.carry_px, steps)
    if not windows:
        raise UserError(f"{data}: in none of the {n} windows of its {len(ids)} episodes does the real arm carry "
                        f"{' or '.join(objects)} (moved >= --carry-px {p.dc.carry_px:g} px with the arm by "
                        f"{' or '.join(steps)}): the dense probe has nothing to measure; give episodes in which the "
                        "arm carries it")
    keys = window_keys(p.dc.seed + KEY_STREAM, [ids[w.episode] for w in windows], [w.f0 for w in windows])
    return Dense(steps, rollout, windows, n, keys, objects)


def run(p, d: Dense, ids, imagine) -> dict:
    """Every window of ``d`` imagined (``imagine(ics, actions, keys) -> frames [V, n, H, W, 3]`` each, the
    diagnosis' batched ``run_offline``) and scored: the :func:`section`."""
    from tqdm import tqdm

    from sc3_jax.rollout import rollout as ro_mod
    off, at = d.rollout.spec.stride * (d.rollout.spec.context - 1), [k - 1 for k in d.steps.values()]
    rows = []
    bar = tqdm(total=len(d.windows), desc="dense probe", unit="window", disable=not p.dc.progress)
    for a in range(0, len(d.windows), p.batch):
        part, keys = d.windows[a:a + p.batch], d.keys[a:a + p.batch]
        items = [ro_mod.from_episode(p.eps[w.episode], p.views, d.rollout.spec, start=w.f0 - off) for w in part]
        frames = imagine([it[0] for it in items], [it[1] for it in items], list(keys))
        for w, key, f in zip(part, keys, frames):
            found = {name: loc(f[:, at], p.views) for name, loc in d.objects.items()}  # [V, times, 2]
            rows.append(_row(w, ids, key, found, list(d.steps), p.views))
        bar.update(len(part))
    bar.close()
    return section(rows, d, p.dc, p.views)


def _row(w: Window, ids, key, found: dict, labels: list, views) -> dict:
    """One window's record: its episode, f0, key and per carried (object: view, time) the imagined error and the
    hold-the-start one (nan: lost)."""
    out = []
    for name, v, label, start, then in w.carried:
        im = found[name][v, labels.index(label)]
        err = float(np.linalg.norm(im - np.asarray(then))) if np.all(np.isfinite(im)) else math.nan
        out.append({"measure": f"{name}: {views[v]}", "time": label, "imagined": err,
                    "hold the start": float(np.linalg.norm(np.asarray(then) - np.asarray(start)))})
    return {"episode": ids[w.episode], "from_frame": w.f0, "key": [int(x) for x in key], "carried": out}


def section(rows: list, d: Dense, dc, views, draws: int = DRAWS) -> dict:
    """The probe's result: per (object: view) and time the imagined and hold-the-start errors over the carried
    windows (``episode_mean``: pooled over windows, interval over episodes), lost windows counted; every window's
    record (``windows``), what ``diagnose_paired.compare`` pairs."""
    per: dict = {}  # (measure, time, reference) -> {episode: [px]}
    for r in rows:
        for c in r["carried"]:
            for ref in REFERENCES:
                vals = per.setdefault((c["measure"], c["time"], ref), {}).setdefault(r["episode"], [])
                if math.isfinite(c[ref]):
                    vals.append(c[ref])
    measures: dict = {}
    for measure in dict.fromkeys(k[0] for k in per):
        times = measures.setdefault(measure, {"units": "px", "times": {}})["times"]
        for label in d.steps:
            if (measure, label, "imagined") not in per:
                continue
            lost = sum(1 for r in rows for c in r["carried"] if c["measure"] == measure and c["time"] == label
                       and not math.isfinite(c["imagined"]))
            times[label] = {ref: episode_mean(per[(measure, label, ref)], draws, dc.seed) for ref in REFERENCES}
            times[label]["imagined"]["lost"] = lost
    spec = d.rollout.spec
    return {"seconds": list(SECONDS), "steps": dict(d.steps), "carry_px": dc.carry_px,
            "with_arm_cosine": tracking.WITH_ARM, "key_seed": dc.seed + KEY_STREAM,
            "rollout": {"chunks": spec.num_chunks, "kept_per_chunk": spec.keep, "stride": spec.stride},
            "windows_considered": d.candidates, "windows_carried": len(rows),
            "episodes_carrying": len({r["episode"] for r in rows}), "views": list(views),
            "measures": measures, "windows": rows}


def lines(sec: dict) -> tuple[str, list[str]]:
    """(heading detail, markdown rows) of a :func:`section` for ``diagnose_report.render_table``."""
    from sc3_jax.evaluation.diagnose_headline import cell
    L = ["| object: view | time | windows | episodes | imagined error, px [95% interval over episodes] | lost | "
         "hold the start, px |", "|---|---|---|---|---|---|---|"]
    for measure, m in sec["measures"].items():
        for label, t in m["times"].items():
            im = t["imagined"]
            L.append(f"| {measure} | {label} | {im['n'] + im['lost']} | {im['episodes']} | {cell(im)} | "
                     f"{im['lost']} | {cell(t['hold the start'])} |")
    detail = (f", {sec['windows_carried']} of {sec['windows_considered']} windows carry an object "
              f"(>= {sec['carry_px']:g} px with the arm), {sec['episodes_carrying']} episodes")
    return detail, L

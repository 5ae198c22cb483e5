"""Training windows drawn by what happens in them (``data.window_weights``, ``core/config.py`` ``WindowWeights``).

A small object the robot carries is a few percent of a frame and is carried in a minority of windows: drawn
uniformly, the model spends most of its training on windows where nothing but the arm moves. Here a window has an
*event* when one of the named entries of the store's ``object_state`` spans more than ``object_motion`` (max - min)
over the window's frames, or one of the named entries of its robot ``state`` (e.g. the gripper) spans more than
``state_change``. The window's frames are those it holds at the smallest of ``data.strides`` (every draw of it shows
at least these moments). Which entries count is the config's and the data's (dataset.json's names): nothing here
knows a robot.

The weights then make event windows ``share`` of what is drawn: the index of every (episode, start) window is
expanded by whole multiplicities before grain shuffles it (``weighted_pairs``), so the window order is as
deterministic, and as resumable with grain's iterator state, as the uniform one. If event windows are rarer than
``share``, each is repeated (``M`` copies in all, ``M = round(share * others / (1 - share))``, spread evenly: every
event window ``M // n`` or ``M // n + 1`` times); if they are commoner, the other windows are repeated instead. With
``share`` 0 (the default) the index is untouched: the order is bit-identical to a run without weights.
"""
from __future__ import annotations

import numpy as np

from sc3_jax.core.errors import UserError


def entries(requested, names: tuple[str, ...], dim: int | None, field: str, flag: str, where: str) -> list[int]:
    """The indices into ``field`` (``state`` / ``object_state`` of ``dim`` entries named ``names``) of the
    ``requested`` entries (each a name, or an index); one line naming what the store has for any it lacks."""
    if not requested:
        return []
    if not dim:
        raise UserError(f"{flag}={list(requested)}, but {where} records no {field} (dataset.json): "
                        + ("import it from a LeRobot dataset with observation.environment_state" if
                           field == "object_state" else "use a store that records one") + f", or leave {flag} empty")
    out = []
    for r in requested:
        r = str(r)
        if r in names:
            out.append(names.index(r))
        elif r.isdigit() and int(r) < dim:
            out.append(int(r))
        else:
            raise UserError(f"{flag}: {where} has no {field} entry {r!r}; its {dim} entries are "
                            f"{list(names) if names else f'0..{dim - 1}'} (names or indices)")
    return sorted(set(out))


def check(cfg, store) -> tuple[list[int], list[int]]:
    """(object_state indices, state indices) of ``cfg.window_weights`` (a ``DataConfig``'s) in ``store``: a name
    the store does not have is one line, before anything is read or trained."""
    w = getattr(cfg, "window_weights", None)
    if w is None:
        return [], []
    where = f"{store.root}/dataset.json"
    return (entries(w.objects, store.object_state_names, store.object_state_dim, "object_state",
                    "data.window_weights.objects", where),
            entries(w.state, store.state_names, store.state_dim, "state", "data.window_weights.state", where))


def spans(x: np.ndarray, starts: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """float [len(starts), D]: max - min of ``x`` [T, D] over the frames ``start + offsets`` of each window."""
    w = x[starts[:, None] + offsets[None, :]]  # [n, L, D]
    return w.max(axis=1) - w.min(axis=1)


def window_events(store, index, cfg) -> np.ndarray:
    """bool [len(index)]: which windows of ``index`` (``pipeline.WindowIndex``) hold an event (module docstring)."""
    w = cfg.window_weights
    objects, state = check(cfg, store)
    stride = min(int(s) for s in cfg.strides)
    offsets = stride * np.arange(cfg.context_frames + cfg.future_frames)
    events = np.zeros(len(index), bool)
    pairs = index.pairs
    for n, eid in enumerate(index.episode_ids):
        rows = np.nonzero(pairs[:, 0] == n)[0]
        if not len(rows):
            continue
        ep = store.load(eid, mmap=True, validate=False)
        starts = pairs[rows, 1]
        for x, cols, threshold in ((ep.object_state, objects, w.object_motion), (ep.state, state, w.state_change)):
            if cols:
                moved = spans(np.asarray(x, np.float64)[:, cols], starts, offsets) > threshold
                events[rows] |= moved.any(axis=1)
    return events


def multiplicities(events: np.ndarray, share: float) -> np.ndarray:
    """int64 [N]: how many times each window is in an epoch so that event windows make up ``share`` of it (as
    nearly as whole copies allow); all ones for ``share`` 0. Refuses (one line) a share no weights can give: no
    event window at all, or no window without one."""
    events = np.asarray(events, bool)
    mult = np.ones(len(events), np.int64)
    if share <= 0:
        return mult
    n_event = int(events.sum())
    n_other = len(events) - n_event
    if n_event == 0 or n_other == 0:
        raise UserError(f"data.window_weights.share={share}: {'none' if n_event == 0 else 'every one'} of the "
                        f"{len(events)} windows has an event, so no weights give it: "
                        + ("lower data.window_weights.object_motion / state_change or name other entries"
                           if n_event == 0 else "raise the thresholds") + ", or set share 0")
    natural = n_event / len(events)
    if np.isclose(share, natural):
        return mult
    if share > natural:  # event windows repeated
        group, copies = np.nonzero(events)[0], int(round(share * n_other / (1.0 - share)))
    else:  # the others repeated
        group, copies = np.nonzero(~events)[0], int(round((1.0 - share) * n_event / share))
    copies = max(copies, len(group))
    base, extra = divmod(copies, len(group))
    mult[group] = base
    if extra:  # one more for `extra` of them, spread evenly over the group
        mult[group[(np.arange(extra) * len(group)) // extra]] += 1
    return mult


def weighted_pairs(store, index, cfg, say: bool = False) -> np.ndarray:
    """The (episode, start) pairs the pipeline shuffles: ``index.pairs`` itself where ``cfg.window_weights`` names
    no entries (the default: unchanged order), else each window repeated by :func:`multiplicities` (copies adjacent;
    grain's shuffle spreads them). ``say``: print one line with the share of event windows before and after."""
    w = getattr(cfg, "window_weights", None)
    if w is None or not (w.objects or w.state):
        return index.pairs
    events = window_events(store, index, cfg)
    mult = multiplicities(events, w.share)
    if say:
        before = events.mean() if len(events) else 0.0
        drawn = int(mult.sum())
        after = float(mult[events].sum()) / max(drawn, 1)
        what = "; ".join(f"{field} {', '.join(names)} span > {thr:g}" for field, names, thr in
                         (("object_state", w.objects, w.object_motion), ("state", w.state, w.state_change)) if names)
        print(f"window weights: {events.sum()} of {len(events)} windows ({100 * before:.1f}%) have an event ({what}); "
              + (f"weighted, they are {100 * after:.1f}% of the {drawn} drawn per epoch (event windows x"
                 f"{mult[events].mean():.2f}, the others x{mult[~events].mean():.2f})" if w.share > 0 else
                 "data.window_weights.share 0: drawn uniformly"), flush=True)
    return np.repeat(index.pairs, mult, axis=0)

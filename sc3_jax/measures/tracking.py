"""Where the imagined arm and objects are against the real ones, under the same recorded actions: ``sc3 diagnose``'s
open-loop position errors at :data:`SECONDS` after the last context frame, and whether a block the real gripper
carries is carried in imagination.

* end effector: the learned state head's reading of the imagined frames against the recorded state, in the robot's
  units (metres where the state is metres), beside two references: the head on the real frames (the read-out's own
  error: the model cannot be judged below it) and holding the start (an arm that never moves);
* the arm and each object in pixels per third-person view (the benchmark's locators, ``benchmark.Locators``),
  against the same hold-the-start reference;
* carried: at a step where the real object has moved at least ``carry_px`` from where it was at the last context
  frame, the same way as the arm (cosine of the two displacements >= :data:`WITH_ARM`), the real gripper carries
  (or pushes) it; it is carried in imagination when the imagined object and arm do the same at that step.

Errors are means over episodes with percentile-bootstrap intervals resampling episodes
(``action_following.episode_mean``). numpy only."""
from __future__ import annotations

import numpy as np

from sc3_jax.measures.action_following import DRAWS, episode_mean

SECONDS = (1.0, 2.0, 4.0, 8.0)
WITH_ARM = 0.5  # cosine between the object's and the arm's displacement above which the object moves with the arm


def _dist(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.linalg.norm(np.asarray(a, np.float64) - np.asarray(b, np.float64), axis=-1)


def moves_with(obj: np.ndarray, arm: np.ndarray, carry_px: float) -> np.ndarray:
    """bool [n]: the object track [n + 1, 2] moved at least ``carry_px`` from its first position, the way the arm
    track [n + 1, 2] moved (cosine >= WITH_ARM), at each step after the first; False where either is unseen."""
    db, da = obj[1:] - obj[:1], arm[1:] - arm[:1]
    nb, na = np.linalg.norm(db, axis=-1), np.linalg.norm(da, axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        cos = (db * da).sum(-1) / (nb * na)
    return (np.nan_to_num(nb, nan=0.0) >= carry_px) & (np.nan_to_num(cos, nan=-1.0) >= WITH_ARM)


class Tracks:
    """Per episode, per measure and time: the errors; per object and view: the carried steps."""

    def __init__(self, hz: float, views, carry_px: float):
        self.at = {f"{s:g} s": int(round(s * hz)) for s in SECONDS}
        self.views, self.carry_px = list(views), carry_px
        self.err: dict = {}  # (group, name, time label, reference) -> {episode: [error]}
        self.units: dict = {}
        self.carried: dict = {}  # (object, view) -> {"real": {episode: n}, "hit": {episode: [0/1 per real step]}}

    def _add(self, group, name, e, im, re, refs: dict):
        """Tracks [n + 1, D] (row 0: the last context frame) of episode ``e``; ``refs``: other tracks to score."""
        for label, k in self.at.items():
            if k < len(re) and np.all(np.isfinite(re[k])):
                for ref, tr in {"imagined": im, **refs}.items():
                    if np.all(np.isfinite(tr[k])):
                        self.err.setdefault((group, name, label, ref), {}).setdefault(e, []).append(
                            float(_dist(tr[k], re[k])))
                    else:  # imagined but not found: it is lost, which the table counts (as the n column)
                        self.err.setdefault((group, name, label, ref), {}).setdefault(e, [])

    def add_state(self, name: str, units: str, e, imagined, on_real, real):
        """The end effector per step [n + 1, D] in robot units: the head on imagined frames, on real ones, and the
        recorded state (row 0 of each: the recorded start)."""
        self.units[("end effector", name)] = units
        self._add("end effector", name, e, imagined, real, {"head on real frames": on_real,
                                                             "hold the start": np.repeat(real[:1], len(real), 0)})

    def add_pixels(self, group: str, name: str, e, imagined, real):
        """Image positions [V, n + 1, 2] of the arm (group "arm") or an object (group "objects"), per view."""
        for v, view in enumerate(self.views):
            if np.isfinite(real[v]).any():
                self.units[(group, f"{name}: {view}")] = "px"
                self._add(group, f"{name}: {view}", e, imagined[v], real[v],
                          {"hold the start": np.repeat(real[v, :1], real.shape[1], 0)})

    def add_carried(self, name: str, e, im_obj, im_arm, re_obj, re_arm):
        """Object and arm image tracks [V, n + 1, 2], imagined and real: which real carries imagination keeps."""
        for v, view in enumerate(self.views):
            real = moves_with(re_obj[v], re_arm[v], self.carry_px)
            if not np.isfinite(re_obj[v]).any():
                continue
            im = moves_with(im_obj[v], im_arm[v], self.carry_px)
            c = self.carried.setdefault((name, view), {"real": {}, "hit": {}})
            c["real"][e] = c["real"].get(e, 0) + int(real.sum())  # (a pooled name adds its objects up)
            c["hit"].setdefault(e, []).extend(im[real].astype(float).tolist())

    def section(self, seed: int = 0, draws: int = DRAWS) -> dict:
        out: dict = {"seconds": list(SECONDS), "carry_px": self.carry_px, "with_arm_cosine": WITH_ARM}
        for (group, name, label, ref), per in self.err.items():
            g = out.setdefault(group, {}).setdefault(name, {"units": self.units[(group, name)], "times": {}})
            g["times"].setdefault(label, {})[ref] = {**episode_mean(per, draws, seed),
                                                     "lost": int(sum(1 for v in per.values() if not v))}
        out["carried"] = {f"{name}: {view}": {"real_steps": int(sum(c["real"].values())),
                                              "episodes_carrying": int(sum(1 for n in c["real"].values() if n)),
                                              "episodes": len(c["real"]),
                                              "carried_in_imagination": episode_mean(c["hit"], draws, seed)}
                          for (name, view), c in self.carried.items()}
        return out

"""``sc3 diagnose``'s action checks: does the model follow its actions, and can it read them back?

* counterfactual: from real starts, the recorded chunk and the same chunk plus a displacement of +-x / +-y. Read-out,
  model-agnostic: the arm's image position = centroid of the pixels that differ from the episode's temporal median
  (the robot is what the median erases), in the third-person views; its imagined shift against the recorded-chunk
  prediction is compared with the commanded shift mapped to the image by an affine camera fitted on the real frames
  (end-effector xyz -> arm centroid; its R^2 is reported).
* inverse dynamics on real frames: the ID mode's action estimate, MSE in normalised action units, against the floors
  "zero" (the training mean action) and "the held-out mean action".

Numpy only; the rollouts run in ``diagnose.py``."""
from __future__ import annotations

import math

import numpy as np

from sc3_jax.evaluate.diagnose_config import DiagnoseConfig
from sc3_jax.stats import correlation

AXES = {"+x": (1.0, 0.0, 0.0), "-x": (-1.0, 0.0, 0.0), "+y": (0.0, 1.0, 0.0), "-y": (0.0, -1.0, 0.0)}


def arm_centroid(frame: np.ndarray, median: np.ndarray, threshold: float, min_pixels: int) -> np.ndarray:
    """(row, col) centroid of the pixels of ``frame`` that differ from the temporal ``median`` by more than
    ``threshold`` ([-1, 1] units, any channel); nan when fewer than ``min_pixels`` do."""
    m = np.any(np.abs(np.asarray(frame, np.float64) - median) / 127.5 > threshold, axis=-1)
    if m.sum() < min_pixels:
        return np.full(2, np.nan)
    r, c = np.nonzero(m)
    return np.array([r.mean(), c.mean()])


# -- counterfactual ------------------------------------------------------------------------------------------------
def calibrate(eps, views, third, medians, stride: int, dc: DiagnoseConfig) -> dict:
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


def variants(eps, group, samples, views, spec1, dc: DiagnoseConfig) -> list[tuple]:
    """(episode, start, variant, initial conditions, actions, targets) for ``dc.cf_starts`` evenly spaced
    teacher-forced starts of each episode of ``group``: the recorded chunk and the same chunk displaced by
    ``dc.cf_distance`` along each of ``AXES`` (spread evenly over the chunk's l' actions)."""
    from sc3_jax.rollout import from_episode
    out = []
    for e in group:
        starts = [st for ee, st in samples if ee == e]
        pick = sorted({starts[int(round(q))] for q in np.linspace(0, len(starts) - 1, min(dc.cf_starts,
                                                                                           len(starts)))})
        for st in pick:
            ic, acts, tgt = from_episode(eps[e], views, spec1, start=st)
            for name, vec in [("recorded", None)] + list(AXES.items()):
                a2 = acts.copy()
                if vec is not None:
                    a2[0, :, :3] += np.asarray(vec, np.float32) * dc.cf_distance / spec1.predict
                out.append((e, st, name, ic, a2, tgt))
    return out


def counterfactual_rows(items, frames, medians, calib, third, dc: DiagnoseConfig) -> list[dict]:
    """One row per (start, third-person view, displaced variant): commanded vs imagined image shift (px)."""
    rows = []
    by_start: dict = {}
    for it, f in zip(items, frames):
        by_start.setdefault((it[0], it[1]), {})[it[2]] = (f, it[5])
    for (e, st), variants_ in by_start.items():
        ref, tgt = variants_["recorded"]
        for v in third:
            cal = calib[list(calib)[third.index(v)]]
            c_ref = arm_centroid(ref[v], medians[e][v], dc.arm_threshold, dc.min_arm_pixels)
            c_real = arm_centroid(tgt[v, -1], medians[e][v], dc.arm_threshold, dc.min_arm_pixels)
            for name, vec in AXES.items():
                c = arm_centroid(variants_[name][0][v], medians[e][v], dc.arm_threshold, dc.min_arm_pixels)
                want = (np.asarray(cal["W"])[:3].T @ (np.asarray(vec) * dc.cf_distance)) if cal["W"] else \
                    np.full(2, np.nan)
                rows.append({"episode": e, "start": st, "view": v, "variant": name, "imagined": (c - c_ref).tolist(),
                             "commanded": want.tolist(), "ref_error_px": float(np.linalg.norm(c_ref - c_real))})
    return rows


def cf_section(rows, calib, views, third, dc: DiagnoseConfig) -> dict:
    """The counterfactual result per third-person view (and all of them pooled)."""
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
    """Pearson r of imagined against commanded displacements (``stats.correlation.pearson``: nan when either is
    constant); nan below 3 pairs, where r is +-1 or undefined whatever the model does."""
    return math.nan if len(a) < 3 else float(correlation.pearson(a, b))


# -- inverse dynamics -----------------------------------------------------------------------------------------------
class InverseErrors:
    """Squared errors of the ID estimates per action dimension, pooled over every evaluated step."""

    def __init__(self):
        self.mse, self.zero, self.sum, self.n = [], [], [], 0

    def add(self, estimate: np.ndarray, actions: np.ndarray):
        """``estimate`` and the recorded ``actions``: normalised [B, l', 7]."""
        self.mse.append(((estimate - actions) ** 2).sum((0, 1)))
        self.zero.append((actions ** 2).sum((0, 1)))
        self.sum.append(actions.sum((0, 1)))
        self.n += actions.shape[0] * actions.shape[1]

    def section(self) -> dict:
        n = self.n
        per = {"mse": np.sum(self.mse, 0) / n, "zero": np.sum(self.zero, 0) / n}  # per action dimension
        per["mean_floor"] = per["zero"] - (np.sum(self.sum, 0) / n) ** 2  # the evaluated steps' own mean action
        out = {k: float(v.mean()) for k, v in per.items()}
        out["per_dim_mse"] = per["mse"].tolist()
        out["per_dim_floor"] = per["zero"].tolist()
        out["ratio_to_floor"] = out["mse"] / min(out["zero"], out["mean_floor"])
        out["n_steps"] = n
        return out

"""``sc3 diagnose``'s action read-back (whether the model follows its actions: ``action_following.py``):

* the arm's image position by the median rule (:func:`arm_centroid`, one frame);
* inverse dynamics on real frames: the ID mode's action estimate, MSE in normalised action units, against the floors
  "zero" (the training mean action) and "the held-out mean action".

Numpy only; the rollouts run in ``diagnose.py``."""
from __future__ import annotations

import numpy as np


def arm_centroid(frame: np.ndarray, median: np.ndarray, threshold: float, min_pixels: int) -> np.ndarray:
    """(row, col) centroid of the pixels of ``frame`` that differ from the temporal ``median`` by more than
    ``threshold`` ([-1, 1] units, any channel); nan when fewer than ``min_pixels`` do."""
    m = np.any(np.abs(np.asarray(frame, np.float64) - median) / 127.5 > threshold, axis=-1)
    if m.sum() < min_pixels:
        return np.full(2, np.nan)
    r, c = np.nonzero(m)
    return np.array([r.mean(), c.mean()])


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

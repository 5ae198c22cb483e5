"""``sc3 diagnose``'s settings: :class:`DiagnoseConfig` (episodes, seeds, thresholds, the passes to run, the gates'
thresholds) and the passes' names (``Stage``, ``STAGES``, in the order they run). Imports nothing from the diagnose
modules, so each of them (``diagnose.py``, ``diagnose_actions.py``, ``diagnose_report.py``) can import it."""
from __future__ import annotations

import dataclasses
from typing import Literal

Stage = Literal["teacher_forced", "counterfactual", "open_loop", "dense"]
STAGES: tuple[Stage, ...] = ("teacher_forced", "counterfactual", "open_loop", "dense")  # the order they run in
# what runs unless --stages says otherwise: "dense" (hundreds of rollouts, diagnose_dense.py) only when asked for
# (--stages ... dense, or --against, whose paired comparison it is)
DEFAULT_STAGES: tuple[Stage, ...] = ("teacher_forced", "counterfactual", "open_loop")


@dataclasses.dataclass(frozen=True)
class DiagnoseConfig:
    episodes: int | None = None  # N episodes evenly spaced over the store's sorted ids; None = all
    seed: int = 0  # sampler noise (per sample / episode keys) and the action shuffle
    moving_threshold: float = 0.06  # [-1, 1] units, any channel (see diagnose.py's module docstring)
    horizons: tuple[float, ...] = (0.8, 2.0, 4.0, 6.0, 8.0)  # drift curve points (s)
    max_seconds: float | None = None  # cap on the open-loop horizon (None: the longest episode)
    batch: int = 8  # rollouts per jitted call (rounded up to the device count)
    cf_fraction: float = 0.5  # counterfactual shift per action axis, a fraction of the axis's recorded std
    cf_starts: int = 2  # counterfactual start chunks per episode (evenly spaced over its teacher-forced chunks)
    arm_threshold: float = 0.12  # [-1, 1] units: a pixel belongs to the arm when it differs this much from the median
    min_arm_pixels: int = 4
    carry_px: float = 3.0  # an object the real arm moves this many pixels (its way) is carried (tracking.py)
    perception: str | None = None  # the benchmark's outcome scorer's weights (None: the benchmark's own)
    progress: bool = True
    stages: tuple[Stage, ...] = DEFAULT_STAGES  # the passes to run (diagnose.py's docstring); the others read NOT_RUN
    # gates (see diagnose_report.GATES)
    gate_margin_db: float = 3.0
    gate_actions_db: float = 2.0
    gate_reproduction: float = 0.75

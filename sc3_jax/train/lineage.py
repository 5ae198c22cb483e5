"""A world model's compute since its initialisation (``lineage.json``), never per stretch: the windows it has seen
and the stretches that trained it, each with its code commit, steps, windows and wall time, and, for a branch
(``sc3 branch``), its decay. A run writes it in its workdir at every checkpoint; an export, a travelling state and a
branch carry it; a run that starts from a saved model (``train.init_from`` / ``train.resume_from``) continues its.

    {"windows": 46100, "stretches": [{"commit", "run", "from_step", "to_step", "batch", "windows", "wall_s",
     "train_s", "schedule", "started"}, ...], "branch": {"decay_start": S, "to_step": S + N}}

``wall_s`` is the stretch's elapsed time; ``train_s`` leaves out the pauses (``scripts/trunk.sh`` stops a trunk
with SIGSTOP while heavy jobs run: a gap between two steps far longer than the steps around it is a pause)."""
from __future__ import annotations

import datetime
import os
import subprocess
from pathlib import Path

from sc3_jax.core import atomic
from sc3_jax.core.errors import UserError

FILE = "lineage.json"
PAUSE_FACTOR, PAUSE_MIN_S = 20.0, 5.0  # a gap 20x the typical step (and >= 5 s) was a pause, not training


def read(path: str | Path | None) -> dict | None:
    """The lineage saved in directory ``path``; None where it records none."""
    if path is None or not (Path(path) / FILE).is_file():
        return None
    lin = atomic.read_json(Path(path) / FILE, "restore it from the model it came with")
    if not (isinstance(lin, dict) and isinstance(lin.get("stretches"), list)):
        raise UserError(f"{path}/{FILE}: expected {{windows, stretches: [...]}}; restore it from the model it came "
                        "with")
    return lin


def total(lin: dict) -> int:
    return int(sum(int(s.get("windows", 0)) for s in lin["stretches"]))


def begin(base: dict | None, cfg, run: str, start_step: int, origin: str | None = None) -> dict:
    """The lineage of a stretch that starts at ``start_step`` of run ``run``: ``base``'s stretches (this run's own,
    cut back to ``start_step`` -- steps after its last checkpoint are trained again), and a new one. ``origin``: what
    a run started from a model without a lineage began from (its windows are not known: said, not guessed)."""
    stretches = []
    for s in (base or {}).get("stretches", []):
        if s.get("run") == run and s["to_step"] > start_step:
            s = {**s, "to_step": start_step, "windows": (start_step - s["from_step"]) * s["batch"]}
            if s["to_step"] <= s["from_step"]:
                continue
        stretches.append(s)
    if base is None and origin is not None:
        stretches.append({"run": origin, "note": "started from a model without a lineage: its windows are unknown",
                          "windows": 0, "from_step": 0, "to_step": 0, "batch": 0})
    t = cfg.train
    stretches.append({"commit": code_commit(), "run": run, "from_step": start_step, "to_step": start_step,
                      "batch": cfg.data.batch_size, "windows": 0, "wall_s": 0.0, "train_s": 0.0,
                      "schedule": t.schedule, "lr": t.lr,
                      "started": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")})
    lin = {"windows": 0, "stretches": stretches}
    if t.schedule == "wsd" and t.decay_start is not None:
        lin["branch"] = {"decay_start": t.decay_start, "to_step": t.steps}
    elif base and "branch" in base:  # a branch's branch is not a trunk: its decay stays on record
        lin["branch"] = base["branch"]
    lin["windows"] = total(lin)
    return lin


def advance(lin: dict, step: int, wall_s: float, train_s: float) -> dict:
    """``lin`` with its current stretch trained up to ``step``."""
    cur = lin["stretches"][-1]
    cur = {**cur, "to_step": step, "windows": (step - cur["from_step"]) * cur["batch"], "wall_s": round(wall_s, 1),
           "train_s": round(train_s, 1)}
    out = {**lin, "stretches": lin["stretches"][:-1] + [cur]}
    out["windows"] = total(out)
    return out


class StepClock:
    """Seconds a stretch trained: the gaps between the loop's syncs (its metrics fetched every ``train.log_every``
    steps: steps are dispatched asynchronously, so only a sync says they ran), less the pauses (a gap
    ``PAUSE_FACTOR`` times the median of the last gaps, and at least ``PAUSE_MIN_S``, counts as one typical gap)."""

    def __init__(self, now: float):
        self.start = self.last = now
        self.train_s, self.recent = 0.0, []

    def tick(self, now: float) -> None:
        gap, self.last = now - self.last, now
        typical = sorted(self.recent)[len(self.recent) // 2] if self.recent else gap
        if self.recent and gap > max(PAUSE_MIN_S, PAUSE_FACTOR * typical):
            gap = typical  # a pause (SIGSTOP) or a sleep: not training
        else:
            self.recent = (self.recent + [gap])[-50:]
        self.train_s += gap

    def wall_s(self, now: float) -> float:
        return now - self.start


def code_commit() -> str:
    """The code a stretch ran: ``SC3_CODE_COMMIT`` (a frozen copy outside the tree says which commit it was made
    from), else the package's git checkout (``+dirty`` with uncommitted changes), else "unknown"."""
    if os.environ.get("SC3_CODE_COMMIT"):
        return os.environ["SC3_CODE_COMMIT"]
    here = Path(__file__).resolve().parent
    try:
        head = subprocess.run(["git", "-C", str(here), "rev-parse", "--short=12", "HEAD"], capture_output=True,
                              text=True, timeout=10)
        if head.returncode != 0:
            return "unknown"
        dirty = subprocess.run(["git", "-C", str(here), "status", "--porcelain", "--untracked-files=no", "."],
                               capture_output=True, text=True, timeout=10).stdout.strip()
        return head.stdout.strip() + ("+dirty" if dirty else "")
    except (OSError, subprocess.SubprocessError):
        return "unknown"

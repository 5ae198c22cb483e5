"""Several world models' ``sc3 diagnose`` results side by side (``sc3 diagnose-table --world-model DIR ... --baseline
NAME``): the offline half of an ablation table: the full recipe and its ablations trained at one budget (scripts/ablations.sh
says which; the table cannot tell how long a model was trained), at a budget where the closed loop of every variant
would still read as a guess (docs/results.md#training-ablations-at-an-equal-budget).

Each DIR is an exported world model or a ``sc3 train`` workdir holding ``diagnose.json`` (what ``sc3 diagnose --out``
writes) and ``config.json``; its label is the directory's name, or its parent's when the directory is called
``export`` (scripts/ablations.sh's layout). With ``--baseline``, every cell also gives its difference to that row.

No intervals: each figure comes from one training run and 4 held-out episodes, so a difference between two variants
is read against the spread of the same recipe trained with another seed (scripts/ablations.sh's ``full_seed1``).
"""
from __future__ import annotations

import math
from pathlib import Path

from sc3_jax.core import atomic
from sc3_jax.model import modes
from sc3_jax.core.errors import UserError
from sc3_jax.evaluation.diagnose import GATES
from sc3_jax.evaluation.diagnose_report import load_result

# (key, column heading, higher is better)
COLUMNS = (
    ("tf_copy_last", "TF moving - copy-last, worst 3rd-person view (dB)", True),
    ("tf_median", "TF moving - median, worst 3rd-person view (dB)", True),
    ("wrist", "wrist TF moving - copy-last (dB)", True),
    ("actions", "true - shuffled actions, worst view (dB)", True),
    ("drift", "open loop 4 s moving - copy-last, 3rd-person mean (dB)", True),
    ("direction", "counterfactual cosine (headline read-out)", True),
    ("inverse", "inverse dynamics MSE / floor", False),
    ("outcome", "outcome reproduction", True),
    ("gates_failed", "gates failed", False),
)
DRIFT_HORIZON_S = 4.0


def label_of(path: Path) -> str:
    path = Path(path).resolve()
    return path.parent.name if path.name == "export" else path.name


def summary(result: dict, config: dict) -> dict:
    """The table's scalars from one diagnose result and the config of the model it diagnosed. A mode the model was
    never trained on gives None (its inverse-dynamics head is untrained, so its error means nothing)."""
    tf = result["teacher_forced"].get("views", {})  # none where `sc3 diagnose --stages` skipped the pass
    third = result["third_person_views"] or result["views"]
    gate = {g["gate"]: g for g in result["gates"]}
    wrist = [v for v in result["views"] if v not in third]

    def vs_copy_last(psnr):
        return psnr["model"]["moving"] - psnr["copy_last"]["moving"]

    drift = []
    for v in third:
        rows = result["drift"].get("views", {}).get(v, [])  # none where --stages skipped the open loop
        at = [r for r in rows if r["horizon_s"] == DRIFT_HORIZON_S and r["n_episodes"] > 0]
        drift += [vs_copy_last(r["psnr"]) for r in at]
    trains_inverse = config["modes"]["probs"][modes.ID] > 0
    return {
        "tf_copy_last": gate[GATES[0]]["value"],
        "tf_median": gate[GATES[1]]["value"],
        "wrist": min((vs_copy_last(tf[v]["psnr"]) for v in wrist if v in tf), default=math.nan),
        "actions": gate[GATES[2]]["value"],
        "drift": sum(drift) / len(drift) if drift else math.nan,
        "direction": _cosine(result["counterfactual"]),
        "inverse": result["inverse_dynamics"].get("ratio_to_floor", math.nan) if trains_inverse else None,
        "outcome": gate[GATES[3]]["value"],
        "gates_failed": sum(g.get("pass") is False for g in result["gates"]),
    }


def _cosine(cf: dict) -> float:
    """The counterfactual's headline cosine; a result from before the measure: its fraction pointing the commanded
    way (the nearest figure it has)."""
    if cf.get("readouts") and cf.get("headline"):
        return cf["readouts"][cf["headline"]]["cosine"]["value"]
    return cf.get("views", {}).get("all", {}).get("direction_agreement", math.nan)


def load(path: str | Path) -> tuple[str, dict]:
    path = Path(path).expanduser()
    missing = [f for f in ("diagnose.json", "config.json") if not (path / f).exists()]
    if missing:
        raise FileNotFoundError(f"{path}: no {' or '.join(missing)} (run `sc3 diagnose --world-model {path} --data "
                                f"HELDOUT --out {path}/diagnose.json` on a trained or exported world model)")
    # load_result: the file spells non-finite numbers as strings ("nan": a gate --stages skipped)
    return label_of(path), summary(load_result(path / "diagnose.json"),
                                   atomic.read_json(path / "config.json", "restore it, or export the model again"))


def _cell(key: str, value, base) -> str:
    """``value`` (None: not trained), with its difference to ``base`` when that is given."""
    if value is None:
        return "not trained"
    if isinstance(value, float) and math.isnan(value):
        return "n/a"
    if key == "gates_failed":
        return f"{value}" if base is None or value == base else f"{value} ({value - base:+d})"
    text = f"{value:.2f}"
    if base is None or (isinstance(base, float) and math.isnan(base)):
        return text
    return f"{text} ({value - base:+.2f})"


def table(rows: dict[str, dict], baseline: str | None = None) -> str:
    """Markdown: one row per model, one column per ``COLUMNS`` entry; with ``baseline`` (a row's label) every other
    row's cells also give their difference to it."""
    if baseline is not None and baseline not in rows:
        raise UserError(f"baseline {baseline!r} is not one of {sorted(rows)}")
    base = rows[baseline] if baseline else {}
    head = "| model | " + " | ".join(h for _, h, _ in COLUMNS) + " |"
    lines = [head, "|" + "---|" * (len(COLUMNS) + 1)]
    for label, row in rows.items():
        own = label == baseline
        cells = [_cell(k, row[k], None if own or base.get(k) is None else base[k]) for k, _, _ in COLUMNS]
        lines.append(f"| {'**' + label + '**' if own else label} | " + " | ".join(cells) + " |")
    better = ", ".join(h for _, h, up in COLUMNS if up is False)
    lines.append("")
    lines.append(f"Higher is better except {better}. TF = teacher-forced, one chunk ahead from real context; "
                 "moving = pixels that move; median = the temporal median of the real frames (erases the arm).")
    return "\n".join(lines)

"""``sc3 diagnose``'s verdicts and rendering: the acceptance gates (value, threshold, pass / fail; see ``GATES`` and
docs/world_model.md#diagnostics), the markdown table of a result, and its JSON file (non-finite numbers kept)."""
from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from sc3_jax import atomic
from sc3_jax.evaluate.diagnose_video import PREDICTORS

if TYPE_CHECKING:
    from sc3_jax.evaluate.diagnose import DiagnoseConfig


GATES = ("teacher-forced moving PSNR - copy-last, every third-person view (dB)",
         "teacher-forced moving PSNR - temporal median, every third-person view (dB)",
         "true - shuffled actions, moving PSNR, every view (dB)",
         "offline per-object outcome reproduction",
         "drift curve reported per view")


def gates(result: dict, dc: DiagnoseConfig) -> list[dict]:
    """Each gate of ``GATES`` on a :func:`diagnose` result: value, ``dc``'s threshold, pass, note."""
    tf = result["teacher_forced"]["views"]
    third = result["third_person_views"] or result["views"]

    def margin(base):
        vals = [tf[v]["psnr"]["model"]["moving"] - tf[v]["psnr"][base]["moving"] for v in third]
        return min(vals) if vals else math.nan

    shuffled = min(tf[v]["true_minus_shuffled_moving"] for v in result["views"])
    oc = result["outcomes"]
    if oc.get("available"):
        ref = oc["imagined_vs_physics"] or oc["imagined_vs_real_perception"]
        repro, note = ref["outcome"], f"outcome category vs {oc['reference']}, {ref['n_objects']} objects"
    else:
        repro, note = math.nan, oc.get("note", "")
    drift_ok = all(r[0]["n_episodes"] > 0 for r in result["drift"]["views"].values())
    rows = [(GATES[0], margin("copy_last"), dc.gate_margin_db, ""),
            (GATES[1], margin("median"), dc.gate_margin_db, ""),
            (GATES[2], shuffled, dc.gate_actions_db, ""),
            (GATES[3], repro, dc.gate_reproduction, note)]
    out = [{"gate": g, "value": v, "threshold": t, "pass": bool(math.isfinite(v) and v >= t), "note": n}
           for g, v, t, n in rows]
    out.append({"gate": GATES[4], "value": float(drift_ok), "threshold": 1.0, "pass": drift_ok,
                "note": "horizons " + ", ".join(f"{h:g} s" for h in result["drift"]["horizons_s"])})
    return out


def _f(x, fmt="{:.2f}") -> str:
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "n/a"
    if isinstance(x, float) and math.isinf(x):
        return "inf"
    return fmt.format(x)


def _pct(x) -> str:
    return "n/a" if x is None or math.isnan(x) else f"{100 * x:.1f}%"


def render_table(result: dict) -> str:
    """Markdown of a :func:`diagnose` result (every number comes from ``result``)."""
    st = result["settings"]
    L = [f"## World-model diagnostics: {result['world_model']}", "",
         f"held-out data {result['data']} ({len(result['episodes'])} episodes), K={st['context_frames']} "
         f"context, l'={st['future_frames']} predicted, l={st['keep_frames']} kept frames per chunk at "
         f"{st['control_hz']:g} Hz (stride {st['stride']}), {st['sample_steps']} sampler steps"
         + (f" (U re-read in {st['inverse_steps']})" if st.get("inverse_steps") else "") +
         f", moving pixels: any channel > {st['moving_threshold']:g} from the last real context frame; PSNR in dB "
         f"of pooled errors; {_f(result['seconds'], '{:.0f}')} s", ""]
    tf = result["teacher_forced"]
    L += [f"### One chunk ahead from real context (teacher-forced, {tf['horizon_s']:g} s, {tf['n_chunks']} chunks, "
          f"mean U {_f(tf['u_mean'], '{:.3f}')})", "",
          "| view | moving px | whole: model | copy-last | copy-first | median | moving: model | copy-last | "
          "copy-first | median | shuffled actions | true - shuffled |",
          "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for v, r in tf["views"].items():
        p = r["psnr"]
        L.append(f"| {v} | {_pct(r['moving_fraction'])} | " +
                 " | ".join(_f(p[k]["whole"]) for k in PREDICTORS) + " | " +
                 " | ".join(_f(p[k]["moving"]) for k in PREDICTORS) +
                 f" | {_f(p['shuffled']['moving'])} | {_f(r['true_minus_shuffled_moving'], '{:+.2f}')} |")
    L += ["", "### Drift (open loop from the first real frames, recorded actions)", "",
          "| view | horizon | episodes | moving px | whole: model | copy-last | copy-first | median | moving: model | "
          "copy-last | copy-first | median |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for v, rows in result["drift"]["views"].items():
        for r in rows:
            p = r["psnr"]
            L.append(f"| {v} | {r['horizon_s']:g} s | {r['n_episodes']} | {_pct(r['moving_fraction'])} | " +
                     " | ".join(_f(p[k]["whole"]) for k in PREDICTORS) + " | " +
                     " | ".join(_f(p[k]["moving"]) for k in PREDICTORS) + " |")
    cf = result["counterfactual"]
    L += ["", f"### Counterfactual actions (recorded chunk +- {100 * cf['distance_m']:g} cm in x / y, "
              "arm centroid vs the temporal median)", "",
          "| view | pairs | points the commanded way | correlation | gain | opposite commands opposite | "
          "commanded px | imagined px | recorded-chunk arm error px | camera fit R^2 (row, col) |",
          "|---|---|---|---|---|---|---|---|---|---|"]
    for v, r in cf["views"].items():
        r2 = cf["calibration_r2"].get(v)
        L.append(f"| {v} | {r['n_pairs']} | {_f(r['direction_agreement'])} | {_f(r['correlation'])} | "
                 f"{_f(r['gain'])} | {_f(r['opposite_fraction'])} | {_f(r['commanded_px'], '{:.1f}')} | "
                 f"{_f(r['imagined_px'], '{:.1f}')} | {_f(r['recorded_position_error_px'], '{:.1f}')} | "
                 + (f"{_f(r2[0])}, {_f(r2[1])}" if r2 else "") + " |")
    idr = result["inverse_dynamics"]
    L += ["", "### Inverse dynamics on real frames (normalised action units, MSE per dimension)", "",
          "| ID (1 step, conditional mean) | floor: zero (training mean) | floor: held-out mean | "
          "ratio to floor | steps |", "|---|---|---|---|---|",
          f"| {_f(idr['mse'], '{:.3f}')} | {_f(idr['zero'], '{:.3f}')} | "
          f"{_f(idr['mean_floor'], '{:.3f}')} | {_f(idr['ratio_to_floor'], '{:.3f}')} | {idr['n_steps']} |"]
    oc = result["outcomes"]
    L += ["", "### Offline outcome reproduction (perception scorer on the open-loop rollout)", ""]
    if not oc.get("available"):
        L.append(f"not available: {oc.get('note')}")
    else:
        L += ["| comparison | objects | language | lifting | placing | lifting and placing | outcome category |",
              "|---|---|---|---|---|---|---|"]
        for k, label in (("imagined_vs_physics", "imagined vs physics"),
                         ("imagined_vs_real_perception", "imagined vs perception(real)"),
                         ("real_perception_vs_physics", "perception(real) vs physics (scorer ceiling)")):
            r = oc[k]
            if r:
                L.append(f"| {label} | {r['n_objects']} | {_f(r['language'])} | {_f(r['lifting'])} | "
                         f"{_f(r['placing'])} | {_f(r['lifting_and_placing'])} | {_f(r['outcome'])} |")
    L += ["", "### Gates", "", "| gate | value | threshold | pass | note |", "|---|---|---|---|---|"]
    for g in result["gates"]:
        L.append(f"| {g['gate']} | {_f(g['value'])} | {g['threshold']:g} | {'PASS' if g['pass'] else 'FAIL'} | "
                 f"{g['note']} |")
    return "\n".join(L) + "\n"


def save_result(result: dict, path: str | Path) -> Path:
    """JSON with non-finite numbers as strings ("inf", "-inf", "nan")."""
    def clean(x):
        if isinstance(x, float) and not math.isfinite(x):
            return str(x)
        if isinstance(x, dict):
            return {str(k): clean(v) for k, v in x.items()}
        if isinstance(x, (list, tuple)):
            return [clean(v) for v in x]
        if isinstance(x, np.generic):
            return clean(x.item())
        return x
    path = Path(path)
    atomic.write_json(path, clean(result))
    return path


def load_result(path: str | Path) -> dict:
    """A result written by :func:`save_result`, non-finite numbers restored (ready for :func:`render_table`)."""
    def restore(x):
        if isinstance(x, str) and x in ("inf", "-inf", "nan"):
            return float(x)
        if isinstance(x, dict):
            return {k: restore(v) for k, v in x.items()}
        if isinstance(x, list):
            return [restore(v) for v in x]
        return x
    return restore(atomic.read_json(path, "run `sc3 diagnose ... --out` again"))


def verdict(result: dict) -> list[str]:
    """The gates in a few lines: how many pass, and each failed one with its value against its threshold."""
    g = result["gates"]
    failed = [x for x in g if not x["pass"]]
    out = [f"gates: {len(g) - len(failed)} of {len(g)} pass" + (" (the checkpoint passes every gate)" if not failed
                                                                 else "; failed:")]
    out += [f"  FAIL {x['gate']}: {_f(x['value'])}, needs >= {x['threshold']:g}" + (f" ({x['note']})" if x["note"]
                                                                                      else "") for x in failed]
    return out

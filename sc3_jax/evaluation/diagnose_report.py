"""``sc3 diagnose``'s verdicts and rendering: the acceptance gates (value, threshold, pass / fail; see ``GATES`` and
docs/world_model.md#diagnostics), the markdown table of a result, and its JSON file (non-finite numbers kept)."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from sc3_jax.core import atomic
from sc3_jax.evaluation.diagnose_config import DiagnoseConfig
from sc3_jax.evaluation.diagnose_video import PREDICTORS


NOT_RUN_NOTE = "not run (--stages)"  # diagnose.NOT_RUN's note: how a skipped section and its gates read
NOT_MEASURED = "not measured"  # a gate whose section ran but could not measure it (no outcome scorer, no view)
SECTIONS = ("teacher_forced", "inverse_dynamics", "counterfactual", "drift", "tracking", "outcomes")
GATES = ("teacher-forced moving PSNR - copy-last, every third-person view (dB)",
         "teacher-forced moving PSNR - temporal median, every third-person view (dB)",
         "true - shuffled actions, moving PSNR, every view (dB)",
         "offline per-object outcome reproduction",
         "drift curve reported per view")


def ran(section: dict) -> bool:
    """Whether a result's section was computed (``sc3 diagnose --stages`` leaves the others as a note)."""
    return section.get("available", True) or section.get("note") != NOT_RUN_NOTE


def not_run(result: dict) -> list[str]:
    """The sections of ``result`` that ``--stages`` skipped."""
    return [k for k in SECTIONS if not ran(result.get(k, {}))]


def gates(result: dict, dc: DiagnoseConfig) -> list[dict]:
    """Each gate of ``GATES`` on a :func:`diagnose` result: value, ``dc``'s threshold, pass, note. A gate whose
    section was not run (``--stages``), or ran but could not measure it (value nan: no outcome scorer, no
    third-person view), reads value nan, pass None -- neither pass nor fail -- and its note says which."""
    third = result["third_person_views"] or result["views"]
    rows = []
    if ran(result["teacher_forced"]):
        tf = result["teacher_forced"]["views"]

        def margin(base):
            vals = [tf[v]["psnr"]["model"]["moving"] - tf[v]["psnr"][base]["moving"] for v in third]
            return min(vals) if vals else math.nan

        shuffled = min(tf[v]["true_minus_shuffled_moving"] for v in result["views"])
        rows += [(GATES[0], margin("copy_last"), dc.gate_margin_db, ""),
                 (GATES[1], margin("median"), dc.gate_margin_db, ""),
                 (GATES[2], shuffled, dc.gate_actions_db, "")]
    else:
        rows += [(g, None, t, "") for g, t in zip(GATES[:3], (dc.gate_margin_db, dc.gate_margin_db,
                                                               dc.gate_actions_db))]
    oc = result["outcomes"]
    if not ran(oc):
        rows.append((GATES[3], None, dc.gate_reproduction, ""))
    elif oc.get("available"):
        ref = oc["imagined_vs_physics"] or oc["imagined_vs_real_perception"]
        rows.append((GATES[3], ref["outcome"], dc.gate_reproduction,
                     f"outcome category vs {oc['reference']}, {ref['n_objects']} objects"))
    else:
        rows.append((GATES[3], math.nan, dc.gate_reproduction, oc.get("note", "")))
    out = [_gate(g, v, t, n) for g, v, t, n in rows]
    if ran(result["drift"]):
        drift_ok = all(r[0]["n_episodes"] > 0 for r in result["drift"]["views"].values())
        out.append({"gate": GATES[4], "value": float(drift_ok), "threshold": 1.0, "pass": drift_ok,
                    "note": "horizons " + ", ".join(f"{h:g} s" for h in result["drift"]["horizons_s"])})
    else:
        out.append({"gate": GATES[4], "value": math.nan, "threshold": 1.0, "pass": None, "note": NOT_RUN_NOTE})
    return out


def _gate(gate: str, value, threshold: float, note: str) -> dict:
    """One gate's row: a value measured passes or fails; None (its section not run) or nan (not measurable: a FAIL
    once, which read as the model's fault) neither."""
    if value is None or math.isnan(value):
        note = NOT_RUN_NOTE if value is None else NOT_MEASURED + (f": {note}" if note else "")
        return {"gate": gate, "value": math.nan, "threshold": threshold, "pass": None, "note": note}
    return {"gate": gate, "value": value, "threshold": threshold, "pass": bool(value >= threshold), "note": note}


def word(g: dict) -> str:
    """A gate's verdict in a word: PASS, FAIL, not run (--stages) or not measured."""
    if g["pass"] is not None:
        return "PASS" if g["pass"] else "FAIL"
    return "not run" if g.get("note") == NOT_RUN_NOTE else NOT_MEASURED


def _f(x, fmt="{:.2f}") -> str:
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "n/a"
    if isinstance(x, float) and math.isinf(x):
        return "inf"
    return fmt.format(x)


def _pct(x) -> str:
    return "n/a" if x is None or math.isnan(x) else f"{100 * x:.1f}%"


def render_table(result: dict) -> str:
    """Markdown of a :func:`diagnose` result (every number comes from ``result``); a section ``--stages`` skipped
    reads as one line."""
    st = result["settings"]
    L = [f"## World-model diagnostics: {result['world_model']}", "",
         f"held-out data {result['data']} ({len(result['episodes'])} episodes), K={st['context_frames']} "
         f"context, l'={st['future_frames']} predicted, l={st['keep_frames']} kept frames per chunk at "
         f"{st['control_hz']:g} Hz (stride {st['stride']}), {st['sample_steps']} sampler steps"
         + (f" (U re-read in {st['inverse_steps']})" if st.get("inverse_steps") else "") +
         f", moving pixels: any channel > {st['moving_threshold']:g} from the last real context frame; PSNR in dB "
         f"of pooled errors; {_f(result['seconds'], '{:.0f}')} s"]
    if "tracking" in result or "readouts" in result.get("counterfactual", {}):  # (results from before: no headline)
        from sc3_jax.evaluation import diagnose_headline
        L += ["", "### Where the imagined arm and objects go (the headline measures)", ""] + \
            diagnose_headline.lines(result)
    for key, heading, body in (
            ("teacher_forced", "One chunk ahead from real context (teacher-forced{})", _teacher_forced_lines),
            ("drift", "Drift (open loop from the first real frames, recorded actions){}", _drift_lines),
            ("counterfactual", "Counterfactual actions{}", _counterfactual_lines),
            ("inverse_dynamics", "Inverse dynamics on real frames{}", _inverse_lines),
            ("outcomes", "Offline outcome reproduction (perception scorer on the open-loop rollout){}",
             _outcome_lines),
            ("permanence", "Objects kept, stage by stage (the benchmark's measures, imagined over real){}",
             _kept_lines)):
        sec = result.get(key)
        if sec is None:  # a diagnose.json from before the section existed
            continue
        if ran(sec):
            detail, lines = body(sec)
            L += ["", f"### {heading.format(detail)}", ""] + lines
        else:
            L += ["", f"### {heading.format('')}", "", NOT_RUN_NOTE]
    if ran(result.get("dense", {"available": False, "note": NOT_RUN_NOTE})):  # asked for, not a default stage
        from sc3_jax.evaluation import diagnose_dense
        detail, lines = diagnose_dense.lines(result["dense"])
        L += ["", f"### Dense probe: the object after real context, where the real arm carries it{detail}", ""] + lines
    L += ["", "### Gates", "", "| gate | value | threshold | pass | note |", "|---|---|---|---|---|"]
    for g in result["gates"]:
        L.append(f"| {g['gate']} | {_f(g['value'])} | {g['threshold']:g} | {word(g)} | {g['note']} |")
    return "\n".join(L) + "\n"


def _kept_lines(sec: dict) -> tuple[str, list[str]]:
    from sc3_jax.evaluation import diagnose_kept
    if "times" in sec:  # a diagnose.json from before the stages: open loop only
        sec = {"seconds": [float(k[:-2]) for k in sec["times"]], "closed_loop": "not measured",
               "rows": [{"stage": "open loop", "measure": "objects", "times": sec["times"]}]}
    return diagnose_kept.lines(sec)


def _teacher_forced_lines(tf: dict) -> tuple[str, list[str]]:
    L = ["| view | moving px | whole: model | copy-last | copy-first | median | moving: model | copy-last | "
         "copy-first | median | shuffled actions | true - shuffled |", "|" + "---|" * 12]
    for v, r in tf["views"].items():
        p = r["psnr"]
        L.append(f"| {v} | {_pct(r['moving_fraction'])} | " +
                 " | ".join(_f(p[k]["whole"]) for k in PREDICTORS) + " | " +
                 " | ".join(_f(p[k]["moving"]) for k in PREDICTORS) +
                 f" | {_f(p['shuffled']['moving'])} | {_f(r['true_minus_shuffled_moving'], '{:+.2f}')} |")
    return f", {tf['horizon_s']:g} s, {tf['n_chunks']} chunks, mean U {_f(tf['u_mean'], '{:.3f}')}", L


def _drift_lines(drift: dict) -> tuple[str, list[str]]:
    L = ["| view | horizon | episodes | moving px | whole: model | copy-last | copy-first | median | moving: model | "
         "copy-last | copy-first | median |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for v, rows in drift["views"].items():
        for r in rows:
            p = r["psnr"]
            L.append(f"| {v} | {r['horizon_s']:g} s | {r['n_episodes']} | {_pct(r['moving_fraction'])} | " +
                     " | ".join(_f(p[k]["whole"]) for k in PREDICTORS) + " | " +
                     " | ".join(_f(p[k]["moving"]) for k in PREDICTORS) + " |")
    return "", L


def _counterfactual_lines(cf: dict) -> tuple[str, list[str]]:
    if "readouts" not in cf:  # a diagnose.json from before the measure (or a skip note)
        return "", [cf.get("note", "not measured")]
    from sc3_jax.evaluation.diagnose_headline import cell
    L = [f"- {n}" for n in cf["notes"]]
    L += [f"- state map (what a real chunk commands -> how far the recorded state moved), R^2 per entry: "
          f"{', '.join(_f(x) for x in m['r2'])} over {m['n']} chunks" if v == "state" else
          f"- image map (what a real chunk commands -> how far the arm moved in the image), R^2 (row, col) in "
          f"{v}: {_f(m['r2'][0])}, {_f(m['r2'][1])} over {m['n']} chunks" for v, m in cf["image_map"].items()]
    L += ["", "| read-out | axis | cosine | gain | pairs |", "|---|---|---|---|---|"]
    for name, r in cf["readouts"].items():
        L.append(f"| {name} | every shifted axis | {cell(r['cosine'])} | {cell(r['gain'])} | {r['cosine']['n']} |")
        L += [f"| | {a} | {cell(x['cosine'])} | {cell(x['gain'])} | {x['cosine']['n']} |" for a, x in r["axes"].items()]
    if not cf["readouts"]:
        L.append("| none | | | | 0 |")
    shifts = ", ".join(f"{a} {v:.3g}" for a, v in cf["shift_raw"].items())
    return f" (recorded chunk shifted by +- {cf['fraction_of_std']:g} std per axis: {shifts or 'no axis'})", L


def _inverse_lines(idr: dict) -> tuple[str, list[str]]:
    return " (normalised action units, MSE per dimension)", [
        "| ID (1 step, conditional mean) | floor: zero (training mean) | floor: held-out mean | ratio to floor | "
        "steps |", "|---|---|---|---|---|",
        f"| {_f(idr['mse'], '{:.3f}')} | {_f(idr['zero'], '{:.3f}')} | {_f(idr['mean_floor'], '{:.3f}')} | "
        f"{_f(idr['ratio_to_floor'], '{:.3f}')} | {idr['n_steps']} |"]


def _outcome_lines(oc: dict) -> tuple[str, list[str]]:
    if not oc.get("available"):
        return "", [f"not available: {oc.get('note')}"]
    rows = [(label, oc[k]) for k, label in (("imagined_vs_physics", "imagined vs physics"),
                                            ("imagined_vs_real_perception", "imagined vs perception(real)"),
                                            ("real_perception_vs_physics", "perception(real) vs physics (scorer ceiling)"))
            if oc[k]]
    # the benchmark's criteria, in their order, then the last two together where there are more than two
    cols = [k for k in (rows[0][1] if rows else {}) if k not in ("outcome", "n_objects")]
    L = ["| comparison | objects | " + " | ".join(c.replace("_", " ") for c in cols) + " | outcome category |",
         "|---|---|" + "---|" * (len(cols) + 1)]
    for label, r in rows:
        L.append(f"| {label} | {r['n_objects']} | " + " | ".join(_f(r.get(c)) for c in cols) +
                 f" | {_f(r['outcome'])} |")
    if oc.get("physics_reproduction"):
        L += [""] + _reproduction_lines(oc["physics_reproduction"], oc.get("category_names") or {})
    return "", L


def _ci(s: dict) -> str:
    ci = s.get("ci95")
    return _f(s["agreement"]) + (f" [{ci[0]:.2f}, {ci[1]:.2f}]" if ci else "")


def _reproduction_lines(r: dict, names: dict) -> list[str]:
    """Imagined vs physics with intervals: agreement overall and per criterion, then per physics category with the
    imagined categories it became (``diagnose_outcomes.physics_reproduction``), each category in the benchmark's
    words (``names``, e.g. a placing failure as "dropped / off target"), else by its own name."""
    how = (f"95% bootstrap interval over the {r['n_episodes']} episodes ({r['draws']} draws, seed {r['seed']})"
           if r["draws"] else "no interval: a single episode")
    cats = list(r["categories"])
    L = [f"Imagined vs physics, {r['n_objects']} objects; value [{how}]", "",
         "| agreement with physics | objects | imagined = physics |", "|---|---|---|",
         f"| outcome category | {r['outcome']['n_objects']} | {_ci(r['outcome'])} |"]
    L += [f"| {c} | {s['n_objects']} | {_ci(s)} |" for c, s in r["criteria"].items()]
    L += ["", "| physics category | objects | imagined same category | " +
          " | ".join(f"imagined {names.get(c, c)}" for c in cats) + " |", "|---|---|---|" + "---|" * len(cats)]
    for c, s in r["categories"].items():
        L.append(f"| {names.get(c, c)} | {s['n_objects']} | {_ci(s)} | " +
                 " | ".join(str(r["confusion"][c][k]) for k in cats) + " |")
    return L


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
    """The gates in a few lines: how many pass, each failed one with its value against its threshold; the passes
    ``--stages`` skipped in one line; whether the outcome set is large enough to read per category."""
    g = [x for x in result["gates"] if x["pass"] is not None]
    failed = [x for x in g if not x["pass"]]
    unmeasured = [x for x in result["gates"] if word(x) == NOT_MEASURED]
    skipped = len(result["gates"]) - len(g) - len(unmeasured)
    aside = [f"{skipped} not run: --stages skipped {', '.join(not_run(result))}"] * bool(skipped) + \
        [f"{len(unmeasured)} not measured"] * bool(unmeasured)
    if aside:
        out = [f"gates: {len(g) - len(failed)} of the {len(g)} measured pass ({'; '.join(aside)})"
               + ("; failed:" if failed else "")]
    else:
        out = [f"gates: {len(g) - len(failed)} of {len(g)} pass" + (" (the checkpoint passes every gate)"
                                                                     if not failed else "; failed:")]
    out += [f"  FAIL {x['gate']}: {_f(x['value'])}, needs >= {x['threshold']:g}" + (f" ({x['note']})" if x["note"]
                                                                                      else "") for x in failed]
    out += [f"  not measured {x['gate']}: {x['note'].removeprefix(NOT_MEASURED + ': ') or 'no value'}"
            for x in unmeasured]
    oc = result["outcomes"]
    r = oc.get("physics_reproduction")
    if "physics_reproduction" in oc and not r:  # (results from before it existed say nothing)
        out.append("outcome set: no episode's rollout covered it with physics labels (reproduction read against "
                   "the perception scorer on real frames)")
    elif r:
        out.append(f"outcome set: {r['n_objects']} objects with physics labels in {r['n_episodes']} episodes: " +
                   ("large enough to read per category" if r["n_objects"] >= r["min_objects"] else
                    f"too few to tell 0.67 from 0.75 (needs >= {r['min_objects']})"))
    return out


def beside_sweep(world_model: str) -> dict | None:
    """The headline rows (``diagnose_headline.summary_rows``) of the world model's own ``diagnose.json`` (``sc3 diagnose --world-model WM --out
    WM/diagnose.json``: held-out episodes, not the sweep's rollouts), for a sweep's report; None without one."""
    path = Path(world_model) / "diagnose.json"
    if not path.is_file():
        return None
    from sc3_jax.evaluation import diagnose_headline

    res = load_result(path)
    return {"path": str(path), "episodes": len(res.get("episodes", [])), "rows": diagnose_headline.summary_rows(res)}

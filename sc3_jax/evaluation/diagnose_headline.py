"""The headline rows of ``sc3 diagnose``: where the imagined arm and objects go, which is what a ranking of policies
rests on (docs/world_model.md#diagnostics) -- the counterfactual cosine and gain, the imagined end effector against
the real one over time, the objects' positions and carries -- each with its 95% interval over episodes, then the
objects-kept pixel count as a secondary row. :func:`summary_rows` gives the same rows as data, for a report that
shows a diagnose result beside a sweep. Reads a result dict (``diagnose.diagnose`` or ``load_result``); numpy
free."""
from __future__ import annotations

import math

KEPT_AT = "4 s"  # the secondary objects-kept row: its open-loop value at this time (the latest reached, if earlier)


def _ok(x) -> bool:
    return x is not None and isinstance(x, (int, float)) and math.isfinite(x)


def cell(s: dict | None, fmt: str = "{:.2f}") -> str:
    """"value [lo, hi]" of an ``episode_mean`` (no interval: one episode; "n/a": nothing measured)."""
    if not s or not _ok(s.get("value")):
        return "n/a"
    v = fmt.format(s["value"])
    return v + (f" [{fmt.format(s['lo'])}, {fmt.format(s['hi'])}]" if _ok(s.get("lo")) else " (one episode)")


def summary_rows(result: dict) -> list[dict]:
    """The headline rows as data: each {"measure", "readout", "time" (None: not over time), "units", "value", "lo",
    "hi", "n", "reference": {name: value} (what the value is read against), "note"}; secondary rows say so in
    "measure". A section not run (``--stages``) gives no rows."""
    rows = []
    cf = result.get("counterfactual") or {}
    if cf.get("readouts"):
        name = cf["headline"]
        r = cf["readouts"][name]
        for m in ("cosine", "gain"):
            rows.append(_row(f"counterfactual {m}", name, None, "", r[m],
                             {"action-blind": 0.0, "follows exactly": 1.0},
                             f"shifts of {cf['fraction_of_std']:g} std along {', '.join(cf['axes'])}"))
    elif cf.get("notes") is not None:
        rows.append({"measure": "counterfactual cosine", "readout": None, "time": None, "units": "", "value": math.nan,
                     "lo": math.nan, "hi": math.nan, "n": 0, "reference": {},
                     "note": "no read-out: " + "; ".join(cf["notes"])})
    tr = result.get("tracking") or {}
    for group, measure in (("end effector", "end-effector error"), ("arm", "arm position error"),
                           ("objects", "object position error")):
        for name, g in _pooled(tr.get(group) or {}).items():
            if group == "arm" and tr.get("end effector"):
                continue  # the end effector in robot units stands for the arm
            for t, refs in g["times"].items():
                rows.append(_row(measure, name, t, g["units"], refs["imagined"],
                                 {k: v["value"] for k, v in refs.items() if k != "imagined"},
                                 f"{refs['imagined'].get('lost', 0)} episodes lost it" if
                                 refs["imagined"].get("lost") else ""))
    for name, c in _pooled(tr.get("carried") or {}).items():
        rows.append(_row("carried in imagination", name, None, "fraction of real carried steps",
                         c["carried_in_imagination"], {},
                         f"the real arm carries it in {c['episodes_carrying']} of {c['episodes']} episodes "
                         f"({c['real_steps']} steps)"))
    kept = _kept(result.get("permanence") or {})
    if kept:
        rows.append(kept)
    return rows


def _pooled(by_name: dict) -> dict:
    """The "every object" entries where there are several objects (each one's stays in the JSON), else all."""
    pooled = {k: v for k, v in by_name.items() if k.startswith("every object")}
    return pooled or by_name


def _row(measure, readout, time, units, s, reference, note) -> dict:
    return {"measure": measure, "readout": readout, "time": time, "units": units, "value": s.get("value", math.nan),
            "lo": s.get("lo", math.nan), "hi": s.get("hi", math.nan), "n": s.get("n", 0), "reference": reference,
            "note": note}


def _kept(sec: dict) -> dict | None:
    """The objects-kept pixel count, open loop, at KEPT_AT (or the latest time reached before it)."""
    for r in sec.get("rows", []):
        if r["stage"] == "open loop" and r["measure"] == "objects" and r["times"]:
            labels = [t for t in r["times"] if float(t[:-2]) <= float(KEPT_AT[:-2])] or list(r["times"])
            c = r["times"][labels[-1]]["kept"]["all views"]
            return {"measure": "objects kept (secondary: colour pixels, imagined over real)", "readout": "every view",
                    "time": labels[-1], "units": "", "value": c["value"], "lo": c["lo"], "hi": c["hi"],
                    "n": r["times"][labels[-1]]["rollouts"], "reference": {"kept": 1.0},
                    "note": "counts colour, not where the object is"}
    return None


def lines(result: dict) -> list[str]:
    """The markdown table of :func:`summary_rows`."""
    rows = summary_rows(result)
    if not rows:
        return ["not run (--stages)"]
    L = ["| measure | read-out | time | value [95% interval over episodes] | read against | n | note |",
         "|---|---|---|---|---|---|---|"]
    for r in rows:
        ref = ", ".join(f"{k} {v:.3g}" if _ok(v) else f"{k} n/a" for k, v in r["reference"].items())
        fmt = "{:.3f}" if r["units"].startswith("robot") else "{:.2f}"
        L.append(f"| {r['measure']} | {r['readout'] or '-'} | {r['time'] or '-'} | {cell(r, fmt)}"
                 f"{' ' + _unit(r['units']) if _ok(r['value']) and _unit(r['units']) else ''} | {ref or '-'} | {r['n']} | {r['note']} |")
    L += ["", "cosine: of the imagined arm's displacement (shifted commands minus recorded ones, same noise) with the "
          "commanded one, 0 where the arm does not move; gain: the fraction of the commanded displacement made along "
          "it. Position errors: open loop from the first real frames under the recorded actions, against the real "
          "frames / recorded state; pixels are image positions of the locator's centroid (third-person views)."]
    return L


def _unit(units: str) -> str:
    if units == "px":
        return "px"
    if units.startswith("robot"):
        return "(" + units + ")"
    return ""


def report_table(d: dict | None):
    """(title, header, rows) of ``diagnose_report.beside_sweep``'s rows, or None where there are none."""
    if not d or not d.get("rows"):
        return None
    rows = []
    for r in d["rows"]:
        value = cell(r) + (f" {r['units']}" if r.get("units") and _ok(r.get("value")) else "")
        ref = ", ".join(f"{k} {v:.3g}" for k, v in (r.get("reference") or {}).items() if _ok(v))
        rows.append([r["measure"], r.get("readout") or "-", r.get("time") or "-", value, ref or "-", str(r["n"]),
                     r.get("note") or ""])
    return (f"Where the imagined arm and objects go (the world model's diagnose.json, {d['episodes']} held-out "
            "episodes; value [95% interval over episodes])",
            ["measure", "read-out", "time", "value", "read against", "n", "note"], rows)

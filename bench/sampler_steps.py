"""Closed-loop faithfulness against the forward sampler's Euler steps, paired on one fixed subset of conditions.

    python bench/sampler_steps.py --real docs/stores/sweep72_gpu --steps 8=docs/stores/sweep72_gpu \
        2=~/sc3-runs/steps_2_1 1=~/sc3-runs/steps_1_1 [--conditions 12] [--draws 2000]

Each ``LABEL=STORE`` holds online rollouts of the same world model on the same evaluation seeds (same rollout
seed, same batches), differing only in ``--sample-steps``; ``--real`` holds the simulator's rollouts of those seeds.
The subset is the first ``--conditions`` evaluation seeds of every in-distribution policy that every store has.
Per label: online r and MMRV against physics with paired-bootstrap 95% intervals, the paired difference to the
policy-blind floor, and the paired difference to the first label (the reference sampler) on the same resamples
(``evaluate.intervals``: one resample of conditions serves every row). Prints a markdown table; the last line is
``sampler_steps: <label>:r=<r>,dr=<paired r difference to the first label>[lo,hi] ...``.
"""
from __future__ import annotations

import argparse
from pathlib import Path

from sc3_jax.evaluation import intervals
from sc3_jax.evaluation.merged import open_store
from sc3_jax.evaluation.results import seed_blocks


def _by(store, mode: str, seeds: set[int]) -> dict:
    return {(r["policy"], r["seed"]): r for r in store.records() if r["mode"] == mode and r["seed"] in seeds}


def compute(real: str, stores: dict[str, str], conditions: int, draws: int, seed: int = 0) -> dict:
    rs = open_store(Path(real).expanduser())
    seeds = seed_blocks(rs.config())["evaluation"][:conditions]
    online = {k: _by(open_store(Path(v).expanduser()), "online", set(seeds)) for k, v in stores.items()}
    reals = _by(rs, "real", set(seeds))
    pols = sorted({p for p, _ in reals if all((p, s) in o for o in online.values() for s in seeds)
                   and reals[p, seeds[0]]["split"] == "in_distribution"})
    if len(pols) < 2:
        raise SystemExit(f"fewer than 2 in-distribution policies have all {conditions} conditions in every store")
    split_of = ["in_distribution"] * len(pols)
    ref = intervals.grid(reals, pols, seeds)
    grids = {k: intervals.grid(o, pols, seeds) for k, o in online.items()}
    rows = intervals.evaluator_rows(ref, grids, split_of, draws, seed)
    first = next(iter(grids))
    vs = {k: intervals.versus(ref, g, grids[first], split_of, draws, seed)["in_distribution"]
          for k, g in grids.items() if k != first}
    return {"policies": pols, "conditions": len(seeds), "rows": rows, "vs_first": vs, "first": first}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--real", required=True, help="store with the real rollouts of the evaluation seeds")
    ap.add_argument("--steps", nargs="+", required=True, metavar="LABEL=STORE", help="first: the reference")
    ap.add_argument("--conditions", type=int, default=12)
    ap.add_argument("--draws", type=int, default=2000)
    a = ap.parse_args(argv)
    c = compute(a.real, dict(s.split("=", 1) for s in a.steps), a.conditions, a.draws)
    split = "in_distribution"
    f = lambda cell: f"{cell['value']:.3f} [{cell['lo']:.3f}, {cell['hi']:.3f}]"  # noqa: E731
    print(f"{len(c['policies'])} in-distribution policies x {c['conditions']} conditions, paired bootstrap "
          f"({a.draws} draws, seed 0)\n")
    print(f"| forward steps | r | MMRV | r - floor (paired) | r - {c['first']} steps (paired) | "
          f"MMRV - {c['first']} steps (paired) |\n|---|---|---|---|---|---|")
    floor = c["rows"]["policy_blind"]["splits"][split]
    last = []
    for k in c["rows"]:
        if k in ("policy_blind", "ceiling"):
            continue
        cell = c["rows"][k]["splits"][split]
        vf = c["rows"][k]["vs_floor"][split]["pearson"]
        vs = c["vs_first"].get(k)
        print(f"| {k} | {f(cell['pearson'])} | {f(cell['mmrv'])} | {f(vf)} | "
              f"{f(vs['pearson']) if vs else '-'} | {f(vs['mmrv']) if vs else '-'} |")
        d = vs["pearson"] if vs else {"value": 0.0, "lo": 0.0, "hi": 0.0}
        last.append(f"{k}:r={cell['pearson']['value']:.3f},dr={d['value']:+.3f}[{d['lo']:+.3f},{d['hi']:+.3f}]")
    print(f"| policy-blind floor | {f(floor['pearson'])} | {f(floor['mmrv'])} | | | |")
    print(f"| noise ceiling ({c['rows']['ceiling']['method']}) | {f(c['rows']['ceiling']['splits'][split]['pearson'])}"
          f" | {f(c['rows']['ceiling']['splits'][split]['mmrv'])} | | | |")
    print("\nsampler_steps: " + " ".join(last))


if __name__ == "__main__":
    main()

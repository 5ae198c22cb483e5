"""``sc3 sweep bench|so101|episodes [--OPTION VALUE ...]``: policies x initial conditions inside the world model, then
the report. ``bench``: the simulated benchmark's seeds, real rollouts in its simulator and its scorer
(sc3_jax/benchmarks/bussing/sweep.py). ``so101``: the SO-101 benchmark's (sc3_jax/benchmarks/so101/sweep.py: the
simulator's outcomes, a success detector on the imagined frames). ``episodes``: held-out episodes of any robot, a lab's scorer and (``--real``)
real outcomes from labels (sc3_jax/evaluate/ic_sweep.py, docs/your_robot.md). One store format and one report."""
from __future__ import annotations

import json

from sc3_jax.benchmarks.bussing.sweep import SweepConfig
from sc3_jax.benchmarks.so101.sweep import So101SweepConfig
from sc3_jax.commands import run_group
from sc3_jax.commands.flags import respell
from sc3_jax.errors import UserError
from sc3_jax.evaluate.ic_sweep import ICSweepConfig

SUMMARY = "policies x initial conditions inside the world model, then the report"  # the line `sc3 --help` shows
SUBCOMMANDS: dict[str, type] = {"bench": SweepConfig, "so101": So101SweepConfig, "episodes": ICSweepConfig}


# numeric options every sweep may have: (lowest, highest, what it counts); a value outside is one line, before
# anything is loaded or written (--episode-seconds 1e9 grew without bound, -1 was an IndexError)
BOUNDS = {"episodes": (1, 100_000, "initial conditions per policy"),
          "calibration_episodes": (0, 100_000, "initial conditions for tau"),
          "ceiling_episodes": (0, 100_000, "second real set"), "start": (0, 10**7, "a frame index"),
          "batch": (1, 4096, "rollouts per batch"), "workers": (0, 256, "processes"),
          "episode_seconds": (1e-3, 3600, "seconds of one episode"), "sample_steps": (1, 1000, "sampler steps"),
          "inverse_steps": (1, 1000, "sampler steps")}


def check_options(cfg) -> None:
    """``cfg``'s numeric options within ``BOUNDS`` and its taus non-negative (inf: never stop)."""
    from sc3_jax import validate

    for name, (low, high, what) in BOUNDS.items():
        value = getattr(cfg, name, None)
        if value is not None:
            validate.in_range(f"--{name.replace('_', '-')}", value, low, high, what)
    validate.taus(getattr(cfg, "taus", None))


def bench(cfg: SweepConfig) -> int:
    from pathlib import Path

    from sc3_jax.benchmarks.bussing import sweep
    from sc3_jax.benchmarks.bussing.hooks import object_pixels
    from sc3_jax.evaluate import report

    check_options(cfg)
    out = sweep.run_sweep(cfg)
    if out != Path(cfg.out):  # one shard of several: the report reads them all once every shard has finished
        print(f"shard done: {out}; once every shard has finished: sc3 report {cfg.out}")
        return 0
    try:
        md = report.render(out, out / "report", scene=object_pixels)
    except UserError as e:  # e.g. --modes online alone: the rollouts are kept, the report waits for real ones
        print(f"rollouts: {out}; no report: {e}")
        return 0
    t = json.loads((out / "report" / "report.json").read_text())
    print("\n".join(report.closing_lines(t)))
    print(f"report: {md} (and report.html, report.json, correlation.png)")
    return 0


def so101(cfg: So101SweepConfig) -> int:
    from sc3_jax.atomic import read_json
    from sc3_jax.benchmarks.so101 import sweep
    from sc3_jax.evaluate import report

    check_options(cfg)
    out = sweep.run(cfg)
    from sc3_jax.benchmarks.so101.hooks import object_pixels
    md = report.render(out, out / "report", real=[str(out / sweep.REAL_FILE)], scene=object_pixels)
    t = read_json(out / "report" / "report.json")
    c = read_json(out / sweep.CHECK_FILE)
    what = f"the detector {cfg.detector}" if cfg.detector else f"the scorer {cfg.scorer}"
    print(f"SO-101: {cfg.episodes} simulator seeds per policy, real in the simulator, imagined inside "
          f"{cfg.world_model}, scored by {what}")
    print(f"{what} on the real episodes agrees with the simulator on {c['agreement']:.2f} of {c['all']['n']}")
    print("\n".join(report.closing_lines(t)))
    print(f"report: {md} (and report.html, report.json)")
    return 0


def episodes(cfg: ICSweepConfig) -> int:
    from sc3_jax.benchmarks.bussing.hooks import named_policy
    from sc3_jax.evaluate import ic_sweep, report

    check_options(cfg)
    out = ic_sweep.run(cfg, named=named_policy)
    md = report.render(out, out / "report", real=cfg.real or None)
    t = json.loads((out / "report" / "report.json").read_text())
    print(f"sweep: {len(cfg.policies)} policies x {cfg.episodes} held-out initial conditions (+ "
          f"{cfg.calibration_episodes} for tau) of {cfg.initial_conditions}, closed loop inside {cfg.world_model}, "
          f"scored by {cfg.scorer}; records: {out}/results.jsonl")
    served = ic_sweep.families(cfg)
    if served:
        print("openpi policy servers (ws://) and the observation mapping each speaks: "
              + ", ".join(f"{n} ({fam})" for n, (fam, _) in served.items()))
    print("\n".join(report.closing_lines(t)))
    print(f"report: {md} (and report.html, report.json)")
    return 0


def main(argv: list[str]) -> int:
    if argv and argv[0].startswith("-") and argv[0] not in ("-h", "--help"):  # the spelling before the subcommands
        argv = respell(argv)  # and the options' spellings before the one set (commands/flags.py)
        job = "episodes" if any(a.split("=")[0] == "--data" for a in argv) else "bench"
        raise UserError(f"name the sweep: `sc3 sweep {job} {' '.join(argv)}` (bench: the simulated benchmark; "
                        "episodes: held-out episodes of any robot)")
    return run_group("sweep", "Policies x initial conditions inside the world model, then the report "
                     "(docs/sweep.md, docs/your_robot.md).", SUBCOMMANDS, {"bench": bench, "so101": so101, "episodes": episodes},
                     argv)

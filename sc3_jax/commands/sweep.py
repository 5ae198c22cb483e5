"""``sc3 sweep BENCHMARK|episodes [--OPTION VALUE ...]``: policies x initial conditions inside the world model, then
the report. ``BENCHMARK``: a benchmark's own sweep, looked up by name (``sc3_jax/evaluation/benchmark.py``: ``bussing``, alias
``bench``, the simulated benchmark's seeds, real rollouts in its simulator and its scorer; ``so101``, the SO-101
simulator's outcomes and a success detector on the imagined frames; or ``package.module:attr`` naming any
``Benchmark``); the store records its name (``benchmark.json``) for ``sc3 report``. ``episodes``: held-out episodes
of any robot, a lab's scorer and (``--real``) real outcomes from labels (sc3_jax/evaluation/ic_sweep.py,
docs/your_robot.md). One store format and one report."""
from __future__ import annotations

import json
from functools import partial
from pathlib import Path

from sc3_jax.evaluation import benchmark
from sc3_jax.commands import parse, run_group
from sc3_jax.core.errors import UserError
from sc3_jax.evaluation.ic_sweep import ICSweepConfig

SUMMARY = "policies x initial conditions inside the world model, then the report"  # the line `sc3 --help` shows
# the line Ctrl-C ends with (cli.py; every writer is atomic)
RESUME = "the same command resumes it (finished rollouts are kept)"
# every built-in benchmark's own sweep, by its names (the registry's: README command 1's alias first), then the
# benchmark-free one; any other benchmark by ``package.module:attr`` (``main``). `sc3 --help` reads this line
# (cli.describe): the registry lists the sweeps' names without importing a benchmark
SUBCOMMANDS: dict[str, type] = {**benchmark.sweep_configs(), "episodes": ICSweepConfig}


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
    from sc3_jax.core import validate

    for name, (low, high, what) in BOUNDS.items():
        value = getattr(cfg, name, None)
        if value is not None:
            validate.in_range(f"--{name.replace('_', '-')}", value, low, high, what)
    validate.taus(getattr(cfg, "taus", None))


def sweep(name: str, cfg) -> int:
    """The sweep of the benchmark ``name`` (a registered name or package.module:attr), then its report, read with the
    benchmark's scene measure; the store records the name for ``sc3 report``."""
    from sc3_jax.evaluation import report

    bm = benchmark.get(name)
    check_options(cfg)
    out = bm.run_sweep(cfg)
    benchmark.record(cfg.out, name)
    if out != Path(cfg.out):  # one shard of several: the report reads them all once every shard has finished
        print(f"shard done: {out}; once every shard has finished: sc3 report {cfg.out}")
        return 0
    try:
        md = report.render(out, out / "report", scene=bm.scene)
    except UserError as e:  # e.g. --modes online alone: the rollouts are kept, the report waits for real ones
        print(f"rollouts: {out}; no report: {e}")
        return 0
    t = json.loads((out / "report" / "report.json").read_text())
    if bm.describe_sweep is not None:
        print("\n".join(bm.describe_sweep(cfg, out)))
    print("\n".join(report.closing_lines(t)))
    also = ["report.html", "report.json"] + ["correlation.png"] * (out / "report" / "correlation.png").exists()
    print(f"report: {md} (and {', '.join(also)}{_eval_infos(out)})")
    return 0


def _eval_infos(out: Path) -> str:
    """OUT/report/eval_info/<mode>/<policy>/eval_info.json in lerobot-eval's shape, as `sc3 report` writes them, so a
    lab's dashboards read every sweep; what the report line says of them."""
    from sc3_jax.evaluation import eval_info

    try:
        n = len(eval_info.write(out))
    except UserError as e:  # the report is written; only LeRobot's shape of it is missing
        return f"; no eval_info.json: {e}"
    return f"; {n} eval_info.json in lerobot-eval's shape under {out / 'report' / 'eval_info'}"


def episodes(cfg: ICSweepConfig) -> int:
    from sc3_jax.evaluation import ic_sweep, report

    check_options(cfg)
    named = benchmark.get(cfg.benchmark).named_policy if cfg.benchmark else None  # a benchmark's own policy names
    out = ic_sweep.run(cfg, named=named)
    md = report.render(out, out / "report")  # the real outcomes as the store keeps them (read once, by the sweep)
    t = json.loads((out / "report" / "report.json").read_text())
    print(f"sweep: {len(cfg.policies)} policies x {cfg.episodes} held-out initial conditions (+ "
          f"{cfg.calibration_episodes} for tau) of {cfg.initial_conditions}, closed loop inside {cfg.world_model}, "
          f"scored by {cfg.scorer}; records: {out}/results.jsonl")
    served = ic_sweep.families(cfg)
    if served:
        print("openpi policy servers (ws://) and the observation mapping each speaks: "
              + ", ".join(f"{n} ({fam})" for n, (fam, _) in served.items()))
    print("\n".join(report.closing_lines(t)))
    print(f"report: {md} (and report.html, report.json{_eval_infos(out)})")
    return 0


def main(argv: list[str]) -> int:
    if argv and argv[0].startswith("-") and argv[0] not in ("-h", "--help"):  # no job named: say the one implied
        job = "episodes" if any(a.split("=")[0] == "--data" for a in argv) else "bench"
        raise UserError(f"name the sweep: `sc3 sweep {job} {' '.join(argv)}` (bench: the simulated benchmark; "
                        "episodes: held-out episodes of any robot)")
    if argv and argv[0] not in SUBCOMMANDS and ":" in argv[0]:  # a benchmark defined outside sc3_jax
        bm = benchmark.get(argv[0])
        if bm.run_sweep is None:
            raise UserError(f"benchmark {argv[0]!r} has no sweep of its own: `sc3 sweep episodes` ranks policies on "
                            "held-out episodes of any robot")
        return sweep(argv[0], parse(bm.sweep_config, argv[1:], f"sweep {argv[0]}"))
    run = {name: partial(sweep, name) for name in SUBCOMMANDS if name != "episodes"}
    return run_group("sweep", "Policies x initial conditions inside the world model, then the report "
                     "(docs/sweep.md, docs/your_robot.md). SUBCOMMAND: a benchmark's sweep, or any benchmark as "
                     f"{benchmark.FORM}, or episodes (any robot's held-out episodes).", SUBCOMMANDS,
                     {**run, "episodes": episodes}, argv)

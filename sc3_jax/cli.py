"""The ``sc3`` command: one subcommand per stage (data -> train -> checkpoint -> rollout -> sweep -> report)."""
from __future__ import annotations

import importlib
import sys

USAGE = """usage: sc3 <command> [args]

commands:
  demo           generate the synthetic multi-view data, train the tiny model, report how far it got
  train          sc3 train --config NAME_OR_PATH[:ARG] [--section.field VALUE ...]
  train-tokenizer  sc3 train-tokenizer --data STORE --workdir DIR: the learned latent tokenizer (conv autoencoder)
  diagnose       sc3 diagnose WORLD_MODEL --data HELDOUT_STORE: checkpoint gates (PSNR vs baselines, drift, actions)
  diagnose-table sc3 diagnose-table DIR ... [--baseline NAME]: several models' diagnostics side by side (ablations)
  rollout        closed-loop / offline rollouts of a policy inside a trained world model
  sweep          policies x initial conditions x {real, offline, online} on the simulated benchmark -> report
  report         sc3 report RESULTS ... [--out DIR]: tables, plots and videos from a sweep's results store
  curve          sc3 curve SPEC.json --out DIR: faithfulness against training compute over several sweeps
  rescore        sc3 rescore RESULTS [--perception WEIGHTS]: re-score a store's stored frames with other scorer weights
  data           LeRobot datasets: sc3 data import-lerobot ROOT --out DIR | export-lerobot STORE --out DIR
  sim            the simulated table-bussing benchmark: sc3 sim demos|eval ...
  serve-policy   serve one of our policies over the openpi websocket protocol
  configs        list the named configs with their parameter counts
  convert        Cosmos3 weights: sc3 convert --from diffusers DIR --to OUT | --from sc3 RUN --to DIR
  plan           sc3 plan --config NAME --mesh data=..,fsdp=..,tensor=.. --device h100|h200|gb200|v5p: memory/FLOPs

`sc3 <command> --help` for the arguments of each."""


def _split_config(argv: list[str]) -> tuple[str, list[str]]:
    """Pull ``--config X`` / ``--config=X`` out of argv; the rest are field overrides."""
    name, rest, i = "tiny", [], 0
    while i < len(argv):
        if argv[i] == "--config" and i + 1 < len(argv):
            name, i = argv[i + 1], i + 2
            continue
        if argv[i].startswith("--config="):
            name = argv[i].split("=", 1)[1]
        else:
            rest.append(argv[i])
        i += 1
    return name, rest


def config_from_argv(argv: list[str]):
    import tyro

    from sc3_jax.config import Config, load_config

    name, overrides = _split_config(argv)
    return tyro.cli(Config, default=load_config(name), args=overrides, prog="sc3 train",
                    description="Any field can be overridden, e.g. --train.steps 100 --data.batch-size 16.")


def cmd_train(argv: list[str]) -> int:
    from sc3_jax import train

    cfg = config_from_argv(argv)
    last = train.train(cfg)
    print(f"done: step {last.get('step')} loss {last.get('loss', float('nan')):.4f} -> {cfg.train.workdir}")
    return 0


def cmd_demo(argv: list[str]) -> int:
    from sc3_jax import demo

    return demo.main(argv)


def cmd_data(argv: list[str]) -> int:
    from sc3_jax.data import lerobot_cli

    return lerobot_cli.main(argv)


def cmd_sim(argv: list[str]) -> int:
    from sc3_jax.sim import cli as sim_cli

    return sim_cli.main(argv) or 0


def cmd_serve_policy(argv: list[str]) -> int:
    from sc3_jax.policies import serve_cli

    return serve_cli.serve_policy_main(argv) or 0


def cmd_sweep(argv: list[str]) -> int:
    """Run (or resume) a sweep, then write its report to OUT/report."""
    import json
    from pathlib import Path

    import tyro

    from sc3_jax.evaluate import report, sweep

    cfg = tyro.cli(sweep.SweepConfig, args=argv, prog="sc3 sweep",
                   description="Evaluate policies in the simulator and inside the world model; resumable (rerun the "
                               "same command). Ends with OUT/report/report.md.")
    out = sweep.run_sweep(cfg)
    if out != Path(cfg.out):  # one shard of several: the report reads them all once every shard has finished
        print(f"shard done: {out}; once every shard has finished: sc3 report {cfg.out}")
        return 0
    md = report.render(out, out / "report")
    t = json.loads((out / "report" / "report.json").read_text())
    title, header, rows = next(x for x in report.tables(t) if x[0].startswith("Faithfulness, end to end"))
    print(f"## {title}\n\n| " + " | ".join(header) + " |\n" + "".join("| " + " | ".join(r) + " |\n" for r in rows))
    print("\n".join(report.verdict(t) + t.get("warnings", [])))
    print(f"report: {md} (and report.html, report.json, correlation.png)")
    return 0


def cmd_plan(argv: list[str]) -> int:
    from sc3_jax import plan

    return plan.main(argv) or 0


def cmd_convert(argv: list[str]) -> int:
    from sc3_jax import convert_cli

    return convert_cli.main(argv)


def cmd_train_tokenizer(argv: list[str]) -> int:
    from sc3_jax import tokenizer_train

    return tokenizer_train.main(argv)


def cmd_diagnose(argv: list[str]) -> int:
    from sc3_jax.evaluate import diagnose

    return diagnose.main(argv) or 0


def cmd_rollout(argv: list[str]) -> int:
    from sc3_jax import rollout_cli

    return rollout_cli.main(argv) or 0


def _command(module: str):
    """The `main` of `sc3_jax/commands/MODULE.py`, imported when the command runs: `sc3 --help` and the other
    commands load none of its libraries."""
    def run(argv: list[str]) -> int:
        return importlib.import_module(f"sc3_jax.commands.{module}").main(argv)

    return run


COMMANDS = {"demo": cmd_demo, "train": cmd_train, "rollout": cmd_rollout, "sweep": cmd_sweep,
            "report": _command("report"), "curve": _command("curve"), "rescore": _command("rescore"),
            "data": cmd_data, "sim": cmd_sim, "serve-policy": cmd_serve_policy, "configs": _command("configs"),
            "plan": cmd_plan, "convert": cmd_convert, "train-tokenizer": cmd_train_tokenizer,
            "diagnose": cmd_diagnose, "diagnose-table": _command("diagnose_table")}


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if not argv or argv[0] in ("-h", "--help"):
        print(USAGE)
        return 0
    cmd = COMMANDS.get(argv[0])
    if cmd is None:
        print(f"sc3: unknown command {argv[0]!r}\n\n{USAGE}", file=sys.stderr)
        return 2
    from sc3_jax.errors import UserError

    try:
        return cmd(argv[1:])
    except (FileNotFoundError, FileExistsError, UserError) as e:  # expected faults: the one-line message says it all
        print(f"sc3 {argv[0]}: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())

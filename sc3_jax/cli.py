"""The ``sc3`` command: one subcommand per stage (data -> train -> checkpoint -> rollout -> sweep -> report)."""
from __future__ import annotations

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
  report         sc3 report RESULTS --out DIR: tables, plots and videos from a sweep's results store
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


def cmd_configs(argv: list[str]) -> int:
    """Each named config with its parameter count (from abstract shapes: nothing is allocated)."""
    from sc3_jax import checkpoint
    from sc3_jax.config import available_configs, configs_dir, load_config
    from sc3_jax.model import dit
    from sc3_jax.model.tokenizer import tokens_per_sample

    print(f"named configs in {configs_dir()}:")
    for name in available_configs():
        cfg = load_config(name)
        try:  # a config whose tokenizer weights are missing here is listed, not fatal
            n = dit.count_params(checkpoint.param_shapes(cfg))
            tokens = tokens_per_sample(cfg)
        except (FileNotFoundError, ValueError) as e:
            print(f"  {name:24s} (not sized here: {e})")
            continue
        print(f"  {name:24s} {n / 1e6:10.2f}M params  {tokens:6d} tokens/sample  batch {cfg.data.batch_size}")
    return 0


def cmd_sweep(argv: list[str]) -> int:
    """Run (or resume) a sweep, then write its report to OUT/report."""
    import tyro

    from sc3_jax.evaluate import report, sweep

    cfg = tyro.cli(sweep.SweepConfig, args=argv, prog="sc3 sweep",
                   description="Evaluate policies in the simulator and inside the world model; resumable (rerun the "
                               "same command). Ends with OUT/report/report.md.")
    out = sweep.run_sweep(cfg)
    md = report.render(out, out / "report")
    sections = md.read_text().split("\n## ")
    print("## " + sections[1] if len(sections) > 1 else "")  # the main table
    print(f"report: {md} (and report.html, report.json)")
    return 0


def cmd_report(argv: list[str]) -> int:
    import argparse

    from sc3_jax.evaluate import report

    ap = argparse.ArgumentParser(prog="sc3 report", description="Report of a sweep's results store.")
    ap.add_argument("results", help="the sweep's --out directory")
    ap.add_argument("--out", default=None, help="report directory (default RESULTS/report)")
    ap.add_argument("--videos", type=int, default=3, help="side-by-side example videos")
    ap.add_argument("--taus", type=float, nargs="+", default=None, help="termination thresholds (default: the "
                    "sweep's candidates); evaluated from the stored U_chunk, no new rollouts. U_chunk is in the "
                    "sweep's units (rollout.tau_units)")
    ap.add_argument("--draws", type=int, default=2000, help="paired bootstrap draws for the 95%% intervals")
    a = ap.parse_args(argv)
    md = report.render(a.results, a.out or f"{a.results}/report", a.videos, a.taus, a.draws)
    print(f"report: {md}")
    return 0


def cmd_curve(argv: list[str]) -> int:
    import argparse

    from sc3_jax.evaluate import curve

    ap = argparse.ArgumentParser(prog="sc3 curve", description="Faithfulness against training compute: one table "
                                 "and one plot over several checkpoints' sweeps (sc3_jax/evaluate/curve.py).")
    ap.add_argument("spec", help='JSON: {"title": ..., "points": [{"label", "store", "steps", "batch", "device", '
                    '"hours"}, ...]}')
    ap.add_argument("--out", required=True, help="directory for curve.md, curve.png, curve.json")
    ap.add_argument("--draws", type=int, default=2000, help="paired bootstrap draws for the 95%% intervals")
    a = ap.parse_args(argv)
    print(f"curve: {curve.render(a.spec, a.out, a.draws)}")
    return 0


def cmd_rescore(argv: list[str]) -> int:
    from sc3_jax.evaluate import rescore

    return rescore.main(argv)


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


def cmd_diagnose_table(argv: list[str]) -> int:
    from sc3_jax.evaluate import diagnose_table

    return diagnose_table.main(argv)


def cmd_rollout(argv: list[str]) -> int:
    from sc3_jax import rollout_cli

    return rollout_cli.main(argv) or 0


COMMANDS = {"demo": cmd_demo, "train": cmd_train, "rollout": cmd_rollout, "sweep": cmd_sweep, "report": cmd_report,
            "curve": cmd_curve, "rescore": cmd_rescore, "data": cmd_data, "sim": cmd_sim,
            "serve-policy": cmd_serve_policy, "configs": cmd_configs, "plan": cmd_plan,
            "convert": cmd_convert, "train-tokenizer": cmd_train_tokenizer, "diagnose": cmd_diagnose,
            "diagnose-table": cmd_diagnose_table}


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if not argv or argv[0] in ("-h", "--help"):
        print(USAGE)
        return 0
    cmd = COMMANDS.get(argv[0])
    if cmd is None:
        print(f"sc3: unknown command {argv[0]!r}\n\n{USAGE}", file=sys.stderr)
        return 2
    from sc3_jax.data.episodes import EpisodeError

    try:
        return cmd(argv[1:])
    except (FileNotFoundError, FileExistsError, EpisodeError) as e:  # user-facing input problems: the message says it all
        print(f"sc3 {argv[0]}: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())

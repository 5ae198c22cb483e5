"""The ``sc3`` command: one subcommand per stage (data -> train -> checkpoint -> rollout -> sweep -> report)."""
from __future__ import annotations

import errno
import importlib
import sys

USAGE = """usage: sc3 <command> [args]

commands:
  demo           generate the synthetic multi-view data, train the tiny model, report how far it got
  train          sc3 train --config NAME_OR_PATH[:ARG] [--section.field VALUE ...]
  train-tokenizer  sc3 train-tokenizer --data STORE --workdir DIR: the learned latent tokenizer (conv autoencoder)
  train-perception sc3 train-perception --store STORE ... | --validate RESULTS ... --init WEIGHTS: the perception scorer
  diagnose       sc3 diagnose WORLD_MODEL --data HELDOUT_STORE: checkpoint gates (PSNR vs baselines, drift, actions)
  diagnose-table sc3 diagnose-table DIR ... [--baseline NAME]: several models' diagnostics side by side (ablations)
  rollout        closed-loop / offline rollouts of a policy inside a trained world model
  sweep          policies x initial conditions x {real, offline, online} on the simulated benchmark, or
                 (--initial-conditions) held-out episodes of any robot with your own scorer -> report
  report         sc3 report RESULTS ... [--out DIR]: tables, plots and videos from a sweep's results store
  curve          sc3 curve SPEC.json --out DIR: faithfulness against training compute over several sweeps
  rescore        sc3 rescore RESULTS [--perception WEIGHTS]: re-score a store's stored frames with other scorer weights
  data           LeRobot datasets: sc3 data import-lerobot ROOT --out DIR | export-lerobot STORE --out DIR
  sim            the simulated table-bussing benchmark: sc3 sim demos|demos-stats|eval|zoo-train|zoo-eval|zoo-list|
                 zoo-manifest|measure
  serve-policy   serve one of our policies over the openpi websocket protocol
  configs        list the named configs with their parameter counts
  convert        Cosmos3 weights: sc3 convert --from diffusers DIR --to OUT | --from sc3 RUN --to DIR
  plan           sc3 plan --config NAME --mesh data=..,fsdp=..,tensor=.. --device h100|h200|gb200|v5p: memory/FLOPs

`sc3 <command> --help` for the arguments of each."""


# what Ctrl-C leaves, per command: the one line it ends with (every writer here is atomic, so nothing is half-written)
RESUME = {"train": "the same command resumes from its last checkpoint",
          "sweep": "the same command resumes it (finished rollouts are kept)",
          "data": "the same command resumes it (imported episodes are kept)",
          "sim": "the same command resumes it where it writes a store (finished parts are kept)"}

CANNOT_WRITE = {errno.EACCES, errno.EPERM, errno.EROFS, errno.ENOSPC, errno.EDQUOT}


def _command(module: str):
    """The `main` of `sc3_jax/commands/MODULE.py`, imported when the command runs: `sc3 --help` and the other
    commands load none of its libraries."""
    def run(argv: list[str]) -> int:
        return importlib.import_module(f"sc3_jax.commands.{module}").main(argv)

    return run


# command -> its module in sc3_jax/commands/
MODULES = {"demo": "demo", "train": "train", "train-tokenizer": "train_tokenizer",
           "train-perception": "train_perception", "diagnose": "diagnose", "diagnose-table": "diagnose_table", "rollout": "rollout", "sweep": "sweep", "report": "report",
           "curve": "curve", "rescore": "rescore", "data": "data", "sim": "sim", "serve-policy": "serve_policy",
           "configs": "configs", "convert": "convert", "plan": "plan"}
COMMANDS = {name: _command(m) for name, m in MODULES.items()}


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
    except KeyboardInterrupt:  # Ctrl-C: one line, not a traceback from wherever the command was
        print(f"\nsc3 {argv[0]}: interrupted; nothing half-written is left; "
              f"{RESUME.get(argv[0], 'run it again to redo it')}", file=sys.stderr)
        return 130
    except (FileNotFoundError, FileExistsError, UserError) as e:  # expected faults: the one-line message says it all
        print(f"sc3 {argv[0]}: error: {e}", file=sys.stderr)
        return 2
    except OSError as e:  # a place the command cannot write (permissions, read-only, full): the user's to fix
        if e.errno not in CANNOT_WRITE:
            raise
        print(f"sc3 {argv[0]}: error: cannot write {e.filename or ''}: {e.strerror}; choose another place (or free "
              "space there)", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())

"""Multi-host entry point: initialise jax.distributed, then run any `sc3` command on every process.

    # SLURM (GPU): coordinator, process count and id are read from the SLURM environment by JAX itself
    srun python launch/multihost.py train --config paper
    # explicit (TPU VM pods, plain SSH, or localhost tests)
    python launch/multihost.py --coordinator 10.0.0.1:8476 --num-processes 4 --process-id $RANK -- train --config paper

Every process feeds its own slice of the global batch (the grain pipeline shards by process) and the global batch
is assembled with jax.make_array_from_process_local_data (sc3_jax/sharding.py)."""
from __future__ import annotations

import argparse
import sys


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--coordinator", help="host:port of process 0 (default: auto-detected, e.g. SLURM / TPU)")
    ap.add_argument("--num-processes", type=int)
    ap.add_argument("--process-id", type=int)
    ap.add_argument("--init-timeout", type=int, default=300)
    ap.add_argument("command", nargs=argparse.REMAINDER, help="the sc3 command and its arguments")
    args = ap.parse_args(argv)

    import jax

    # Must be the very first JAX call of the process.
    jax.distributed.initialize(coordinator_address=args.coordinator, num_processes=args.num_processes,
                               process_id=args.process_id, initialization_timeout=args.init_timeout)
    print(f"process {jax.process_index()}/{jax.process_count()}: {jax.local_device_count()} local of "
          f"{jax.device_count()} devices", flush=True)
    from sc3_jax.cli import main as sc3_main

    command = args.command[1:] if args.command[:1] == ["--"] else args.command
    return sc3_main(command)


if __name__ == "__main__":
    sys.exit(main())

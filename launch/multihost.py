"""Multi-host entry point: initialise jax.distributed, then run any `sc3` command on every process.

    # SLURM (GPU): coordinator, process count and id from SLURM's environment (launch/slurm_env.py)
    srun python launch/multihost.py train --config paper
    # explicit (plain SSH, localhost tests)
    python launch/multihost.py --coordinator 10.0.0.1:8476 --num-processes 4 --process-id $RANK -- train --config paper
    # TPU VM pods: JAX discovers the pod itself
    python launch/multihost.py --auto train --config paper

Without --coordinator/--num-processes/--process-id: SLURM's variables when present (SLURM_PROCID...), else JAX's
own cluster auto-detection (TPU pods, ...). Every process feeds its own slice of the global batch (the grain pipeline
shards by process) and the global batch is assembled with jax.make_array_from_process_local_data
(sc3_jax/model/sharding.py)."""
from __future__ import annotations

import argparse
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(1, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # the repo (sc3_jax) w/o install

import slurm_env  # noqa: E402


def distributed_kwargs(args, environ=None) -> tuple[dict, str]:
    """(kwargs for jax.distributed.initialize, where they came from)."""
    environ = os.environ if environ is None else environ
    explicit = any(v is not None for v in (args.coordinator, args.num_processes, args.process_id))
    if explicit:
        kw = {"coordinator_address": args.coordinator, "num_processes": args.num_processes,
              "process_id": args.process_id}
        source = "arguments"
    elif not args.auto and slurm_env.is_slurm(environ):
        kw, source = slurm_env.from_env(environ).initialize_kwargs(), "SLURM environment"
    else:
        kw, source = {}, "JAX cluster auto-detection"
    kw.update(initialization_timeout=args.init_timeout, heartbeat_timeout_seconds=args.heartbeat_timeout)
    return kw, source


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--coordinator", help="host:port of process 0 (default: from SLURM, else auto-detected)")
    ap.add_argument("--num-processes", type=int)
    ap.add_argument("--process-id", type=int)
    ap.add_argument("--auto", action="store_true", help="ignore SLURM variables; let JAX detect the cluster (TPU)")
    ap.add_argument("--init-timeout", type=int, default=300, help="seconds to wait for every process to join")
    ap.add_argument("--heartbeat-timeout", type=int, default=100,
                    help="seconds after which a silent peer is declared dead (and this process aborts)")
    ap.add_argument("command", nargs=argparse.REMAINDER, help="the sc3 command and its arguments")
    args = ap.parse_args(argv)
    kwargs, source = distributed_kwargs(args)

    import jax

    # Must be the very first JAX call of the process.
    jax.distributed.initialize(**kwargs)
    print(f"process {jax.process_index()}/{jax.process_count()} ({source}, coordinator "
          f"{kwargs.get('coordinator_address') or 'auto'}): {jax.local_device_count()} local of "
          f"{jax.device_count()} devices", flush=True)
    from sc3_jax.cli import main as sc3_main

    command = args.command[1:] if args.command[:1] == ["--"] else args.command
    try:
        return sc3_main(command)
    finally:
        jax.distributed.shutdown()


if __name__ == "__main__":
    sys.exit(main())

"""One process of the two-process jax.distributed test: one train step on a global 8-device mesh, loss to stdout."""
import os
import sys

process_id, port = int(sys.argv[1]), int(sys.argv[2])
os.environ["JAX_PLATFORMS"] = "cpu"
os.environ["XLA_FLAGS"] = "--xla_force_host_platform_device_count=4"
import jax  # noqa: E402

jax.distributed.initialize(coordinator_address=f"127.0.0.1:{port}", num_processes=2, process_id=process_id,
                           initialization_timeout=60, heartbeat_timeout_seconds=20)
sys.path.insert(0, os.path.dirname(__file__))
from test_sharding import random_batch, small_config  # noqa: E402

from sc3_jax.model import sharding  # noqa: E402
from sc3_jax.train import train

cfg = small_config((8, 1, 1))
mesh = sharding.make_mesh(cfg.mesh)
step, _ = train.compile_train_step(cfg, mesh)
state = train.create_state(cfg, mesh)
n = cfg.data.batch_size // jax.process_count()
local = {k: v[process_id * n:(process_id + 1) * n] for k, v in random_batch(cfg).items()}
state, metrics = step(state, sharding.global_batch(mesh, local))
print(f"LOSS {float(metrics['loss']):.10f}", flush=True)
jax.distributed.shutdown()

"""Mesh, logical-axis rules and helpers to place params and batches. The rules table is the one place that says
how every logical axis maps onto the mesh ("data", "fsdp", "tensor")."""
from __future__ import annotations

import math

import jax
import numpy as np
from jax.sharding import AxisType, Mesh, NamedSharding, PartitionSpec as P

from sc3_jax.config import MeshConfig

AXES = ("data", "fsdp", "tensor")

# logical axis -> mesh axes (None or absent = replicated)
RULES: dict[str, str | tuple[str, ...] | None] = {
    "batch": ("data", "fsdp"),
    "embed": "fsdp",  # FSDP: every weight with a model dimension is split over fsdp, gathered per layer by XLA
    "mlp": "tensor",
    "heads": "tensor",
    "kv_heads": "tensor",
}


def mesh_shape(cfg: MeshConfig, num_devices: int) -> tuple[int, int, int]:
    shape = [cfg.data, cfg.fsdp, cfg.tensor]
    known = math.prod(s for s in shape if s != -1)
    if shape.count(-1) > 1:
        raise ValueError(f"at most one mesh axis may be -1, got {shape}")
    if -1 in shape:
        if num_devices % known:
            raise ValueError(f"{num_devices} devices do not divide by fsdp*tensor = {known}")
        shape[shape.index(-1)] = num_devices // known
    if math.prod(shape) != num_devices:
        raise ValueError(f"mesh {dict(zip(AXES, shape))} needs {math.prod(shape)} devices, have {num_devices}")
    return tuple(shape)


def make_mesh(cfg: MeshConfig, devices=None) -> Mesh:
    devices = jax.devices() if devices is None else devices
    shape = mesh_shape(cfg, len(devices))
    return jax.make_mesh(shape, AXES, axis_types=(AxisType.Auto,) * 3, devices=devices)


def logical_spec(axes: tuple[str | None, ...], shape: tuple[int, ...] | None = None, mesh: Mesh | None = None) -> P:
    """PartitionSpec for logical ``axes``. With ``shape`` and ``mesh``, a dimension that does not divide by its
    mesh axes is replicated instead (small biases, odd head counts) rather than failing to compile."""
    spec = []
    used: set[str] = set()
    for i, name in enumerate(axes):
        target = RULES.get(name) if name else None
        names = (target,) if isinstance(target, str) else tuple(target or ())
        names = tuple(n for n in names if n not in used)
        if names and shape is not None and mesh is not None:
            if shape[i] % math.prod(mesh.shape[n] for n in names):
                names = ()
        used.update(names)
        spec.append(names[0] if len(names) == 1 else (names or None))
    return P(*spec)


def named(mesh: Mesh, axes: tuple[str | None, ...], shape: tuple[int, ...]) -> NamedSharding:
    return NamedSharding(mesh, logical_spec(axes, shape, mesh))


def batch_sharding(mesh: Mesh) -> NamedSharding:
    return NamedSharding(mesh, P(RULES["batch"]))


def replicated(mesh: Mesh) -> NamedSharding:
    return NamedSharding(mesh, P())


def global_batch(mesh: Mesh, local_batch: dict[str, np.ndarray]) -> dict[str, jax.Array]:
    """Assemble the global batch from this process's slice (leading axis); every process calls this."""
    sharding = batch_sharding(mesh)
    return {k: jax.make_array_from_process_local_data(sharding, np.asarray(v)) for k, v in local_batch.items()}

"""Mesh, logical-axis rules and helpers to place params and batches. The rules table is the one place that says
how every logical axis maps onto the mesh ("data", "fsdp", "tensor" and, with context parallelism, "context")."""
from __future__ import annotations

import math

import jax
import numpy as np
from jax.sharding import AxisType, Mesh, NamedSharding, PartitionSpec as P

from sc3_jax.core.config import MeshConfig

AXES = ("data", "fsdp", "tensor")
CONTEXT_AXES = AXES + ("context",)  # MeshConfig.context > 1: the token sequence is split over "context"

# logical axis -> mesh axes (None or absent = replicated; a mesh axis the mesh does not have is dropped)
RULES: dict[str, str | tuple[str, ...] | None] = {
    "batch": ("data", "fsdp"),
    "embed": "fsdp",  # FSDP: every weight with a model dimension is split over fsdp, gathered per layer by XLA
    "mlp": "tensor",
    "heads": "tensor",
    "kv_heads": "tensor",
    "seq": "context",  # the token axis of activations (context parallelism); no parameter has it
}


def mesh_axes(cfg: MeshConfig) -> tuple[str, ...]:
    """The mesh's axis names: the three classic ones, plus "context" only when it is used (so every existing mesh,
    program and checkpoint stays exactly as it was)."""
    return CONTEXT_AXES if cfg.context != 1 else AXES


def mesh_shape(cfg: MeshConfig, num_devices: int) -> tuple[int, ...]:
    """Axis sizes in ``mesh_axes(cfg)`` order: (data, fsdp, tensor) or (data, fsdp, tensor, context)."""
    if cfg.context < 1:
        raise ValueError(f"mesh context must be >= 1, got {cfg.context}")
    shape = [cfg.data, cfg.fsdp, cfg.tensor] + ([cfg.context] if cfg.context != 1 else [])
    names = mesh_axes(cfg)
    known = math.prod(s for s in shape if s != -1)
    if shape.count(-1) > 1:
        raise ValueError(f"at most one mesh axis may be -1, got {shape}")
    if -1 in shape:
        if num_devices % known:
            others = "*".join(n for n, s in zip(names, shape) if s != -1)
            raise ValueError(f"{num_devices} devices do not divide by {others} = {known}")
        shape[shape.index(-1)] = num_devices // known
    if math.prod(shape) != num_devices:
        raise ValueError(f"mesh {dict(zip(names, shape))} needs {math.prod(shape)} devices, have {num_devices}")
    return tuple(shape)


def make_mesh(cfg: MeshConfig, devices=None) -> Mesh:
    devices = jax.devices() if devices is None else devices
    shape = mesh_shape(cfg, len(devices))
    names = mesh_axes(cfg)
    return jax.make_mesh(shape, names, axis_types=(AxisType.Auto,) * len(names), devices=devices)


def logical_spec(axes: tuple[str | None, ...], shape: tuple[int, ...] | None = None, mesh: Mesh | None = None) -> P:
    """PartitionSpec for logical ``axes``. With ``shape`` and ``mesh``, a dimension that does not divide by its
    mesh axes is replicated instead (small biases, odd head counts) rather than failing to compile."""
    spec = []
    used: set[str] = set()
    for i, name in enumerate(axes):
        target = RULES.get(name) if name else None
        names = (target,) if isinstance(target, str) else tuple(target or ())
        names = tuple(n for n in names if n not in used and (mesh is None or n in mesh.shape))
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


# ----------------------------------------------------------------------------------------------------------------
# Context parallelism: programs whose model code calls ``jax.shard_map`` over the "context" axis must be traced and
# run with that mesh set (``jax.set_mesh``); inside ``jax.jit`` the model reads it with ``jax.sharding.
# get_abstract_mesh()``.
# ----------------------------------------------------------------------------------------------------------------
def has_context(mesh) -> bool:
    return mesh is not None and "context" in mesh.shape and mesh.shape["context"] > 1


class MeshBound:
    """A jitted function whose calls, ``lower`` and ``trace`` run under ``jax.set_mesh(mesh)``. Everything else
    (attributes of the jitted function) passes through."""

    def __init__(self, fn, mesh: Mesh):
        self.fn, self.mesh = fn, mesh

    def __call__(self, *args, **kwargs):
        with jax.set_mesh(self.mesh):
            return self.fn(*args, **kwargs)

    def lower(self, *args, **kwargs):
        with jax.set_mesh(self.mesh):
            return self.fn.lower(*args, **kwargs)

    def trace(self, *args, **kwargs):
        with jax.set_mesh(self.mesh):
            return self.fn.trace(*args, **kwargs)

    def __getattr__(self, name):
        return getattr(self.fn, name)


def bind_mesh(fn, mesh: Mesh):
    """``fn`` unchanged for a mesh without a context axis (nothing changes for existing runs), else a
    :class:`MeshBound` so context-parallel attention finds the mesh while tracing and running."""
    return MeshBound(fn, mesh) if has_context(mesh) else fn

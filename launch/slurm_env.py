"""jax.distributed parameters from the environment SLURM gives every task (pure functions of ``os.environ``).

    SLURM_PROCID        -> process id                (global rank of this task)
    SLURM_NTASKS        -> number of processes
    SLURM_LOCALID       -> rank of this task on its node
    SLURM_STEP_NODELIST -> the coordinator host: the first node of the step (else SLURM_JOB_NODELIST /
                           SLURM_NODELIST), in SLURM's compressed syntax ("gpu[001-004,007],login2")
    SLURM_JOB_ID        -> the coordinator port: 61440 + job id % 4096, so every task of a job agrees on it
    SLURM_TASKS_PER_NODE ("8(x4)") / SLURM_NTASKS_PER_NODE -> tasks per node

Overrides: ``SC3_COORDINATOR`` (host:port) or ``SC3_COORDINATOR_PORT``.

Devices: with one task per node (launch/slurm.sbatch) every task drives all of its node's accelerators, so no
``local_device_ids`` are passed -- and JAX's own SLURM auto-detection must be switched off, because it restricts
every task to the single GPU numbered SLURM_LOCALID. With several tasks per node on a GPU job each task gets GPU
SLURM_LOCALID, unless SLURM already narrowed CUDA_VISIBLE_DEVICES to one GPU per task (--gpus-per-task / --gpu-bind).
"""
from __future__ import annotations

import dataclasses
import os
import re
from collections.abc import Mapping

PORT_BASE, PORT_RANGE = 61440, 4096


@dataclasses.dataclass(frozen=True)
class DistributedEnv:
    coordinator: str  # host:port of process 0
    num_processes: int
    process_id: int
    local_process_id: int
    tasks_per_node: int
    local_device_ids: tuple[int, ...] | None  # None: every device the process can see

    def initialize_kwargs(self) -> dict:
        """Keyword arguments for ``jax.distributed.initialize`` (auto-detection off: everything is explicit)."""
        return {"coordinator_address": self.coordinator, "num_processes": self.num_processes,
                "process_id": self.process_id,
                "local_device_ids": list(self.local_device_ids) if self.local_device_ids is not None else None,
                "cluster_detection_method": "deactivate"}


def is_slurm(environ: Mapping[str, str] | None = None) -> bool:
    environ = os.environ if environ is None else environ
    return all(k in environ for k in ("SLURM_PROCID", "SLURM_NTASKS"))


def _split_top(text: str) -> list[str]:
    """Split at commas that are not inside brackets."""
    parts, depth, cur = [], 0, ""
    for ch in text:
        if ch == "," and depth == 0:
            parts.append(cur)
            cur = ""
            continue
        depth += ch == "["
        depth -= ch == "]"
        cur += ch
    parts.append(cur)
    return [p.strip() for p in parts if p.strip()]


def expand_nodelist(text: str) -> list[str]:
    """SLURM's compressed host list -> host names: "a[01-03,7]b,c" -> ["a01b", "a02b", "a03b", "a7b", "c"]
    (zero padding kept; several bracket groups per name expand as a product)."""
    hosts: list[str] = []
    for item in _split_top(text):
        m = re.search(r"\[([^\]]*)\]", item)
        if m is None:
            hosts.append(item)
            continue
        head, tail = item[:m.start()], item[m.end():]
        for rng in m.group(1).split(","):
            lo, _, hi = rng.partition("-")
            if not hi:
                values = [lo]
            else:
                values = [str(i).zfill(len(lo)) for i in range(int(lo), int(hi) + 1)]
            for value in values:
                hosts.extend(expand_nodelist(head + value + tail))
    return hosts


def _tasks_per_node(environ: Mapping[str, str]) -> int:
    for key in ("SLURM_NTASKS_PER_NODE", "SLURM_TASKS_PER_NODE", "SLURM_STEP_TASKS_PER_NODE"):
        value = environ.get(key)
        if value:
            m = re.match(r"\s*(\d+)", value)
            if m:
                return int(m.group(1))
    nodes = int(environ.get("SLURM_NNODES", environ.get("SLURM_JOB_NUM_NODES", "1")))
    return max(1, int(environ["SLURM_NTASKS"]) // max(nodes, 1))


def _coordinator(environ: Mapping[str, str]) -> str:
    if environ.get("SC3_COORDINATOR"):
        return environ["SC3_COORDINATOR"]
    nodelist = next((environ[k] for k in ("SLURM_STEP_NODELIST", "SLURM_JOB_NODELIST", "SLURM_NODELIST")
                     if environ.get(k)), None)
    if nodelist is None:
        raise KeyError("no SLURM_STEP_NODELIST / SLURM_JOB_NODELIST / SLURM_NODELIST: cannot find the coordinator "
                       "(or set SC3_COORDINATOR=host:port)")
    host = expand_nodelist(nodelist)[0]
    if environ.get("SC3_COORDINATOR_PORT"):
        port = int(environ["SC3_COORDINATOR_PORT"])
    elif environ.get("SLURM_JOB_ID"):
        port = PORT_BASE + int(environ["SLURM_JOB_ID"]) % PORT_RANGE
    else:
        raise KeyError("no SLURM_JOB_ID to derive the coordinator port from (or set SC3_COORDINATOR_PORT)")
    return f"{host}:{port}"


def from_env(environ: Mapping[str, str] | None = None) -> DistributedEnv:
    environ = os.environ if environ is None else environ
    if not is_slurm(environ):
        raise KeyError("not a SLURM task: SLURM_PROCID and SLURM_NTASKS are not both set")
    num, pid = int(environ["SLURM_NTASKS"]), int(environ["SLURM_PROCID"])
    if not 0 <= pid < num:
        raise ValueError(f"SLURM_PROCID={pid} is not in [0, SLURM_NTASKS={num})")
    local = int(environ.get("SLURM_LOCALID", "0"))
    per_node = _tasks_per_node(environ)
    gpu_job = any(environ.get(k) for k in ("SLURM_GPUS_ON_NODE", "SLURM_JOB_GPUS", "SLURM_STEP_GPUS"))
    visible = [d for d in environ.get("CUDA_VISIBLE_DEVICES", "").split(",") if d.strip()]
    one_each = per_node > 1 and gpu_job and len(visible) != 1
    return DistributedEnv(_coordinator(environ), num, pid, local, per_node, (local,) if one_each else None)

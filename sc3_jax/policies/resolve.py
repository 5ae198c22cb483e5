"""One way to name a policy, for every command that takes one (``sc3 rollout``, ``sc3 sweep``, ``sc3 serve-policy``).

    NAME                     a benchmark's own policy (``named``; e.g. a zoo policy of the simulated benchmark,
                             ``benchmarks/bussing/zoo.py``, acting on its zoo entry's task)
    zero | random | linear   a built-in JAX policy (``policies/simple.py``), built for the world model's action space
                             and views where the command passes them (else the benchmark's: 7-D delta_ee, 3 views)
    package.module:attr      a JaxPolicy / HostPolicy, or a zero-argument factory of one
    ws://HOST:PORT           a policy server speaking openpi's protocol (``policies/openpi_client.py``)
    lerobot:PATH             a LeRobot pretrained_model directory, run by lerobot in its own environment
                             (``policies/lerobot_policy.py``; SC3_LEROBOT_PYTHON=VENV/bin/python)
    NAME=SPEC                any of the above, called NAME (the sweep's record and directory name)
    SPEC@TASK                any of the above, acting on TASK (one of the benchmark's tasks: its sweep checks)

e.g. ``served=ws://10.0.0.2:8000@TASK``. A benchmark's sweep needs a task for every policy but its own named ones.
"""
from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, Any

from sc3_jax.core import module_attr
from sc3_jax.data.action_space import ActionSpace
from sc3_jax.policies.openpi_mappings import ObsMapping

if TYPE_CHECKING:
    from sc3_jax.policies.base import HostPolicy, JaxPolicy

LEROBOT = "lerobot:"
SPELLINGS = ("a zoo name, zero | random | linear, package.module:attr, ws://HOST:PORT or lerobot:PATH, as "
             "[NAME=]SPEC[@TASK]")


@dataclasses.dataclass(frozen=True)
class Resolved:
    name: str
    task: str | None  # None: not given and not a zoo policy
    policy: Any  # JaxPolicy | HostPolicy


def parse(spec: str) -> tuple[str | None, str, str | None]:
    """``[NAME=]SPEC[@TASK]`` -> (NAME or None, SPEC, TASK or None)."""
    name = None
    head, eq, rest = spec.partition("=")
    if eq and head and not any(c in head for c in ":/@"):
        name, spec = head, rest
    task = None
    if "@" in spec:
        spec, _, task = spec.rpartition("@")
        if not spec or not task.replace("_", "").replace("-", "").isalnum():
            raise ValueError(f"policy {name + '=' if name else ''}{spec}@{task}: expected [NAME=]SPEC@TASK with "
                             "TASK a word, one of the benchmark's tasks (e.g. NAME=ws://HOST:PORT@TASK)")
    if not spec:
        raise ValueError(f"policy {spec!r}: empty; expected {SPELLINGS}")
    return name, spec, task


def resolve(spec: str, chunk: int | None = None, family: str | ObsMapping | None = None,
            action_space: ActionSpace | None = None, num_views: int | None = None, named=None) -> Resolved:
    """The policy ``spec`` names (see the module docstring). ``chunk``: a built-in policy's actions per call
    (default its own); ``family``: the openpi observation mapping of a ``ws://`` server (None / "native": ours);
    ``action_space`` and ``num_views``: what a built-in policy acts in and sees, the world model's
    (``NormStats.action_space``, ``len(cfg.data.views)``; None: the benchmark's 7-D delta_ee and 3 views);
    ``named(NAME) -> (policy, its task)``: a benchmark's own policy names (the simulated benchmark's zoo:
    ``benchmarks/bussing/zoo.named_policy``), which this layer below the benchmarks does not know."""
    from sc3_jax.policies import simple

    name, body, task = parse(spec)
    if body in simple.BUILTIN:
        policy = simple.builtin(body, chunk, action_space, num_views)
    elif body.startswith(("ws://", "wss://")):
        from sc3_jax.policies.openpi_client import WebsocketClientPolicy
        policy = WebsocketClientPolicy(body, port=None, mapping=None if family in (None, "native") else family)
    elif body.startswith(LEROBOT):
        from sc3_jax.policies.lerobot_policy import LeRobotPolicy
        policy = LeRobotPolicy(body[len(LEROBOT):])
    elif ":" in body:
        policy = load_object(body)
    else:
        if named is None:
            raise ValueError(f"unknown policy {body!r}: expected {SPELLINGS}")
        policy, own_task = named(body)
        task = task or own_task
    return Resolved(name or body, task, policy)


def load_object(spec: str) -> JaxPolicy | HostPolicy:
    """``package.module:attr``: attr is a JaxPolicy / HostPolicy, or a zero-argument factory returning one."""
    obj: Any = module_attr.load(spec, "policy")
    if not _is_policy(obj):
        if not callable(obj):
            raise TypeError(f"{spec} is neither a policy nor a factory")
        obj = obj()
    if not _is_policy(obj):
        raise TypeError(f"{spec} produced {type(obj).__name__}, which is neither a JaxPolicy nor a HostPolicy")
    return obj


def _is_policy(obj) -> bool:
    from sc3_jax.policies.base import JaxPolicy  # here: a name is parsed (a report reads a store's) without JAX

    return isinstance(obj, JaxPolicy) or callable(getattr(obj, "infer", None))


def name_of(spec: str) -> str:
    """The name a policy spec gives its records (``NAME=`` or the spec itself): what a store's ``policy_names``
    says, derived from its ``policies`` without building any policy."""
    name, body, _ = parse(spec)
    return name or body

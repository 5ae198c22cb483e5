"""A benchmark, as the commands see it, and the registry that names them.

A benchmark (``sc3_jax/benchmarks/NAME/``, or any package outside this one) is a plug-in of the evaluation core: the
core ranks policies inside a world model and reports; a benchmark adds what only it knows -- its own sweep (its
simulator's real outcomes beside the imagined ones), its scene measures (which pixels are its objects), its outcome
scorer on imagined frames, its policies' names and the words for its tasks and outcomes. :class:`Benchmark` holds
exactly what ``sc3 sweep``, ``sc3 report``, ``sc3 diagnose``, ``sc3 rollout`` and ``sc3 serve-policy`` take from one;
every field but ``name`` may be absent, and no command uses one unless named (``--benchmark``, ``sc3 sweep NAME``).

:func:`get` resolves a name: a built-in short one (``BUILTIN``: the folders of ``sc3_jax/benchmarks/``; ``ALIASES``:
the other names their benchmark.py declare, e.g. README command 1's "bench"), or ``package.module:attr`` naming a
``Benchmark`` anywhere on the path, as policies (``--policies NAME=module:attr``) and scorers (``--scorer
module:attr``) are named. The table holds strings, imported on lookup: this module imports no benchmark and names
none (docs/architecture.md, "Adding a benchmark")."""
from __future__ import annotations

import ast
import dataclasses
import types
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from sc3_jax.core import module_attr
from sc3_jax.core.errors import UserError


@dataclasses.dataclass(frozen=True, kw_only=True)
class Locators:
    """Where things are in a benchmark's frames. A locator is ``locate(frames uint8 [V, T, H, W, 3], views) ->
    float [V, T, 2]``: (row, col) image position in pixels per view and frame, nan where it cannot tell (too few
    pixels, or a view it does not read, e.g. a wrist camera that moves with the arm)."""

    arm: Callable | None = None
    """the arm's image position (None: the pixels that differ from the episode's temporal median)"""
    objects: Mapping[str, Callable] = dataclasses.field(default_factory=dict)
    """the objects' image positions by name (e.g. SO-101's block)"""
    moves: Mapping[str, str] = dataclasses.field(default_factory=dict)
    """action name -> the recorded-state entry it moves (e.g. ``{"dx": "ee_x"}``), for a model whose action space
    does not say (``ActionSpace.measured``)"""

    def __post_init__(self):
        bad = [k for k, f in {"arm": self.arm, **self.objects}.items() if f is not None and not callable(f)]
        if bad:
            raise TypeError(f"Locators: {bad} are not callable")
        object.__setattr__(self, "objects", types.MappingProxyType(dict(self.objects)))
        object.__setattr__(self, "moves", types.MappingProxyType(dict(self.moves)))


@dataclasses.dataclass(frozen=True, kw_only=True)
class Benchmark:
    """What the commands take from a benchmark. ``frames`` below are uint8 [V, T, H, W, 3]."""

    name: str
    """the name its stores record and the commands print (a built-in's short name)"""
    sweep_config: type | None = None
    """the frozen (tyro) dataclass of its sweep's options, with ``out`` (the store) among them; ``sc3 sweep NAME
    --help`` lists its fields. None: no sweep of its own (``sc3 sweep episodes`` ranks any robot's policies)"""
    run_sweep: Callable[[Any], Path] | None = None
    """``run_sweep(cfg) -> Path``: run (or resume) the sweep of ``cfg`` (a ``sweep_config``), return the results
    store it wrote (the core's: ``evaluation/results.py``; a shard of ``cfg.out`` when it ran one shard)"""
    describe_sweep: Callable[[Any, Path], list[str]] | None = None
    """``describe_sweep(cfg, store) -> lines``: what the sweep did, printed before the report's closing lines"""
    measures: Mapping[str, Callable] = dataclasses.field(default_factory=dict)
    """scene measures by name, frames -> [V, T] (the fraction of a thing's pixels): ``sc3 diagnose`` follows each
    through its stages; "objects" is also the report's "objects kept" (``scene``)"""
    outcome_scorer: Callable | None = None
    """``outcome_scorer(views, image_size, weights) -> (scorer, None) | (None, why not)``: the scorer of imagined
    episodes that ``sc3 diagnose`` (outcome reproduction) and ``sc3 rollout`` (success estimate) use"""
    named_policy: Callable[[str], tuple] | None = None
    """``named_policy(NAME) -> (policy, its task or None)``: its own policy names (``policies.resolve``'s
    ``named``), for ``sc3 rollout --policy NAME``"""
    locators: Locators | None = None
    """where the arm and the objects are in frames, and what the actions move (:class:`Locators`): ``sc3
    diagnose``'s action-following and position measures. None: the arm is what the temporal median erases"""
    prompts: Mapping[int, str] = dataclasses.field(default_factory=dict)
    """task id -> its instruction, for an openpi policy where the episodes carry none (``sc3 rollout --family`` on an
    .npz of initial conditions, ``sc3 serve-policy``'s table). Empty: no prompt is sent (the server's default)"""
    category_names: Mapping[str, str] = dataclasses.field(default_factory=dict)
    """an outcome category (a criterion first failed, or "no_failure") -> the words ``sc3 diagnose``'s tables
    print for it (e.g. a placing failure as "dropped / off target"); a category not named prints as itself"""

    def __post_init__(self):
        if not self.name or not isinstance(self.name, str):
            raise TypeError(f"Benchmark.name: a non-empty string, not {self.name!r}")
        if (self.sweep_config is None) != (self.run_sweep is None):
            raise TypeError(f"benchmark {self.name}: sweep_config and run_sweep go together (both, or neither)")
        bad = [k for k, f in self.measures.items() if not callable(f)]
        if bad:
            raise TypeError(f"benchmark {self.name}: measures {bad} are not callable")
        for field in ("measures", "prompts", "category_names"):  # read-only, as the rest
            object.__setattr__(self, field, types.MappingProxyType(dict(getattr(self, field))))
        if self.locators is not None and not isinstance(self.locators, Locators):
            raise TypeError(f"benchmark {self.name}: locators is a {type(self.locators).__name__}, not a Locators")

    @property
    def scene(self) -> Callable | None:
        """The scene measure of the report's "objects kept" row: ``measures["objects"]`` (None: no such row)."""
        return self.measures.get("objects")


BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"  # the built-in ones: a folder each


def _builtin() -> dict[str, str]:
    """Short name -> "package.module:attr" of each built-in Benchmark: every ``sc3_jax/benchmarks/NAME/benchmark.py``
    (its ``BENCHMARK``), found on disk and imported on lookup, so the core names (and imports) none."""
    return {p.name: f"sc3_jax.benchmarks.{p.name}.benchmark:BENCHMARK" for p in sorted(BENCHMARKS.iterdir())
            if (p / "benchmark.py").is_file()}


def _declared(name: str) -> tuple[tuple[str, ...], bool]:
    """(its ``ALIASES = ("...",)``, whether its ``BENCHMARK = Benchmark(...)`` is given a ``sweep_config``) of the
    built-in ``name``, read from its benchmark.py's source (as ``sc3 --help`` reads a command's SUMMARY) so that no
    benchmark is imported to learn its other names or whether ``sc3 sweep`` takes it."""
    aliases, sweeps = (), False
    for node in ast.parse((BENCHMARKS / name / "benchmark.py").read_text()).body:
        target = node.targets[0] if isinstance(node, ast.Assign) else getattr(node, "target", None)
        if isinstance(target, ast.Name) and target.id == "ALIASES":
            aliases = tuple(ast.literal_eval(node.value))
        elif isinstance(target, ast.Name) and target.id == "BENCHMARK" and isinstance(node.value, ast.Call):
            sweeps = any(k.arg == "sweep_config" and not (isinstance(k.value, ast.Constant) and k.value.value is None)
                         for k in node.value.keywords)
    return aliases, sweeps


BUILTIN = _builtin()
_DECLARED = {name: _declared(name) for name in BUILTIN}
ALIASES = {alias: name for name, (aliases, _) in _DECLARED.items() for alias in aliases}  # alias -> short name
FORM = "package.module:attr (a Benchmark on the path)"


def names() -> list[str]:
    """The built-in benchmarks' short names."""
    return list(BUILTIN)


def sweeps() -> list[str]:
    """The names ``sc3 sweep`` takes for the built-ins' own sweeps: of each built-in with one, its aliases, then its
    name (README command 1's "bench" first, as the commands listed it before they came from here). From the sources:
    ``sc3 --help`` lists them importing no benchmark."""
    return [n for name, (aliases, swept) in _DECLARED.items() if swept for n in (*aliases, name)]


def sweep_configs() -> dict[str, type]:
    """:func:`sweeps`' names -> each one's ``sweep_config`` (importing the benchmarks): ``sc3 sweep``'s subcommands."""
    return {name: get(name).sweep_config for name in sweeps()}


def canonical(name: str) -> str:
    """The spelling a store records for ``name``: an alias's benchmark (e.g. "bench"'s), else ``name``."""
    return ALIASES.get(name, name)


def get(name: str) -> Benchmark:
    """The benchmark ``name`` names: a built-in short name or alias, or ``package.module:attr``. One-line
    UserError for an unknown name (listing the known ones and the module:attr form) or an attr that is no Benchmark."""
    spec = BUILTIN.get(canonical(name))
    if spec is None and ":" not in name:
        known = ", ".join(names() + [f"{a} (= {b})" for a, b in ALIASES.items()])
        raise UserError(f"unknown benchmark {name!r}: known are {known}, or {FORM}")
    obj = module_attr.load(spec or name, "benchmark")
    if not isinstance(obj, Benchmark):
        raise UserError(f"benchmark {name!r}: {type(obj).__name__} is not a sc3_jax.evaluation.benchmark.Benchmark")
    return obj


def get_or_none(name: str) -> Benchmark:
    """:func:`get`, except that "none" (the commands' ``--benchmark`` default) is a benchmark that adds nothing: no
    scorer, measures, locators, policy names, prompts or category words, for a model of any robot."""
    return Benchmark(name="none") if name == "none" else get(name)


# the benchmark a results store was swept by: OUT/benchmark.json {"benchmark": NAME}, its short name or module:attr
STORE_FILE = "benchmark.json"


def record(out: str | Path, name: str) -> None:
    """Write ``name`` (canonical) as the benchmark of the store ``out``, for ``sc3 report`` to read its measures."""
    from sc3_jax.core import atomic  # here, not above: `sc3 --help` reads the registry and loads no numpy

    atomic.write_json(Path(out) / STORE_FILE, {"benchmark": canonical(name)})


def recorded(results: str | Path) -> str | None:
    """The benchmark name the store ``results`` recorded (:func:`record`), or None (a store from before, or of
    ``sc3 sweep episodes``). A damaged file is a one-line UserError naming it."""
    from sc3_jax.core import atomic
    from sc3_jax.core.validate import json_object

    path = Path(results) / STORE_FILE
    if not path.is_file():
        return None
    name = json_object(atomic.read_json(path), str(path), "delete it and rerun the sweep").get("benchmark")
    if not isinstance(name, str) or not name:
        raise UserError(f"{path}: 'benchmark' is {name!r}, expected a benchmark name; delete it and rerun the sweep")
    return name

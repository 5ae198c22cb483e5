"""No import cycle between the modules of ``sc3_jax/``, and no import that climbs a floor: the folders are the floors.

The graph is read from the source (``ast``), not by importing: every ``import x`` / ``from x import y`` statement
counts, *including those inside functions*. A function-level import is still a dependency (it runs on the first
call), and the loops this guards against were all lazy ones (sim/zoo -> demos -> evaluate -> zoo); a lazy import
that only exists to dodge a cycle is the smell, not the fix. Imports under ``if TYPE_CHECKING:`` never run and are
skipped. ``from pkg import name`` is an edge to ``pkg.name`` when that is a module, else to ``pkg``.

The floors are the folders of ``sc3_jax/``, lowest first in ``FLOORS`` (only their order is data here): a module's
floor is its folder's, and the few modules loose at ``sc3_jax/`` (``LOOSE``) stand above them all. A new folder fails
until it is placed. docs/architecture.md's table has one row per floor, tied to the list by
``test_floors_match_the_documented_stages`` (same names, same order).
"""
from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _modules(pkg_dir: Path) -> dict[str, Path]:
    out = {}
    for p in sorted(pkg_dir.rglob("*.py")):
        parts = list(p.relative_to(pkg_dir.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = p
    return out


def _is_type_checking(node: ast.If) -> bool:
    t = node.test
    return (isinstance(t, ast.Name) and t.id == "TYPE_CHECKING") or \
        (isinstance(t, ast.Attribute) and t.attr == "TYPE_CHECKING")


def _imports(tree: ast.AST):
    """Every Import / ImportFrom node, skipping ``if TYPE_CHECKING:`` bodies."""
    stack = [tree]
    while stack:
        node = stack.pop()
        if isinstance(node, ast.If) and _is_type_checking(node):
            stack.extend(node.orelse)
            continue
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            yield node
        stack.extend(ast.iter_child_nodes(node))


def import_graph(pkg_dir: Path) -> dict[str, set[str]]:
    """module -> the package's modules it imports (absolute and relative imports, at any depth)."""
    mods = _modules(pkg_dir)
    top = pkg_dir.name

    def owner(name: str) -> str | None:  # the module that defines ``name`` (a module, or an attribute of one)
        while name and name not in mods:
            name = name.rpartition(".")[0]
        return name or None

    graph: dict[str, set[str]] = {}
    for mod, path in mods.items():
        here = mod.split(".") if path.name == "__init__.py" else mod.split(".")[:-1]
        edges = graph.setdefault(mod, set())
        for node in _imports(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            else:
                base = node.module or ""
                if node.level:
                    prefix = here[:len(here) - node.level + 1]
                    base = ".".join(prefix + ([base] if base else []))
                targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in mods else base for a in node.names]
            for t in targets:
                if t.split(".")[0] == top and (o := owner(t)) and o != mod:
                    edges.add(o)
    return graph


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import cycle as [a, b, ..., a], or None (depth-first search, white/grey/black)."""
    state: dict[str, int] = {}
    path: list[str] = []

    def visit(m: str) -> list[str] | None:
        state[m] = 1
        path.append(m)
        for n in sorted(graph.get(m, ())):
            if state.get(n) == 1:
                return path[path.index(n):] + [n]
            if n not in state and (c := visit(n)):
                return c
        path.pop()
        state[m] = 2
        return None

    for m in sorted(graph):
        if m not in state and (c := visit(m)):
            return c
    return None


def test_sc3_jax_has_no_import_cycle():
    graph = import_graph(ROOT / "sc3_jax")
    # the walk sees the package
    assert len(graph) > 50 and "sc3_jax.rollout.rollout" in graph["sc3_jax.benchmarks.bussing.sweep"]
    cycle = find_cycle(graph)
    assert cycle is None, "import cycle: " + " -> ".join(cycle)


def _write(root: Path, files: dict[str, str]) -> Path:
    for rel, text in files.items():
        p = root / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(text)
    return root / "pkg"


def test_a_cycle_through_function_level_and_relative_imports_is_found(tmp_path):
    pkg = _write(tmp_path, {
        "pkg/__init__.py": "",
        "pkg/sub/__init__.py": "",
        "pkg/a.py": "from pkg.sub import b\n",
        "pkg/sub/b.py": "def f():\n    from .c import g\n    return g\n",
        "pkg/sub/c.py": "import numpy\n\ndef g():\n    from .. import a\n",
    })
    graph = import_graph(pkg)
    assert graph["pkg.a"] == {"pkg.sub.b"} and graph["pkg.sub.b"] == {"pkg.sub.c"}
    assert graph["pkg.sub.c"] == {"pkg.a"}  # numpy is outside the package
    assert find_cycle(graph) == ["pkg.a", "pkg.sub.b", "pkg.sub.c", "pkg.a"]


@pytest.mark.parametrize("closing", ["if TYPE_CHECKING:\n    from pkg import a\n", "x = 1\n"])
def test_type_checking_imports_and_acyclic_graphs_pass(tmp_path, closing):
    pkg = _write(tmp_path, {
        "pkg/__init__.py": "",
        "pkg/a.py": "from pkg import b\nfrom pkg.b import VALUE\n",
        "pkg/b.py": "from typing import TYPE_CHECKING\nVALUE = 1\n" + closing,
    })
    graph = import_graph(pkg)
    assert graph == {"pkg": set(), "pkg.a": {"pkg.b"}, "pkg.b": set()}
    assert find_cycle(graph) is None


# The floors, lowest first: the folders of sc3_jax/ (docs/architecture.md "Modules in data-flow order", one row
# each). A module's floor is its folder's index: it may import its own folder and those below it, never one above.
FLOORS: list[str] = ["core", "stats", "measures", "data", "model", "policies", "rollout", "train", "evaluation",
                     "benchmarks", "commands"]
# The modules loose at sc3_jax/ (at most MAX_LOOSE): above every folder, so no folder imports one.
LOOSE: list[str] = ["cli"]  # the console entry point (`sc3`), dispatching to commands/ by name
MAX_LOOSE = 5


def own_command(mod: str, top: str = "sc3_jax") -> bool:
    """``mod`` is a benchmark's own command (``benchmarks/NAME/commands/``): a command, found there by ``cli.py``."""
    parts = mod.split(".")
    return len(parts) > 3 and parts[:2] == [top, "benchmarks"] and parts[3] == "commands"


def floor_of(mod: str, graph, floors=FLOORS, top: str = "sc3_jax") -> tuple[int, str] | None:
    """(index, name) of ``mod``'s floor: its folder's (a benchmark's own commands: the commands'), or
    ``(len(floors), "loose")`` for a module loose at the top of the package; None for the package's own ``__init__``
    and for a folder that is no floor."""
    parts = mod.split(".")
    if parts[0] != top or len(parts) < 2:
        return None
    if own_command(mod, top) and "commands" in floors:
        return floors.index("commands"), "commands"
    if parts[1] in floors:
        return floors.index(parts[1]), parts[1]
    is_folder = any(m.startswith(f"{top}.{parts[1]}.") for m in graph)
    return None if is_folder or len(parts) > 2 else (len(floors), "loose")


def layer_violations(graph: dict[str, set[str]], floors=FLOORS, top: str = "sc3_jax") -> list[str]:
    """Every import from a lower floor to a higher one, and every module no floor places (a folder
    not in ``floors``)."""
    out = []
    for mod in sorted(graph):
        if mod == top:
            continue  # the package's own __init__: nothing to place
        if (lm := floor_of(mod, graph, floors, top)) is None:
            out.append(f"{mod}: in no floor (add its folder to FLOORS and docs/architecture.md)")
            continue
        for dep in sorted(graph[mod]):
            ld = floor_of(dep, graph, floors, top)
            if ld is not None and ld[0] > lm[0]:
                out.append(f"{mod} (floor {lm[1]!r}) imports {dep} (higher floor {ld[1]!r})")
    return out


def loose_modules(pkg_dir: Path) -> list[str]:
    return sorted(p.stem for p in pkg_dir.glob("*.py") if p.stem != "__init__")


def test_sc3_jax_imports_follow_the_floors():
    problems = layer_violations(import_graph(ROOT / "sc3_jax"))
    assert not problems, "imports against the floors (FLOORS, docs/architecture.md):\n" + "\n".join(problems)


def test_every_folder_is_a_floor_and_few_modules_are_loose():
    pkg = ROOT / "sc3_jax"
    folders = sorted(p.name for p in pkg.iterdir() if (p / "__init__.py").is_file())
    assert folders == sorted(FLOORS), "the folders of sc3_jax/ are the floors: add a new one to FLOORS"
    assert loose_modules(pkg) == sorted(LOOSE) and len(LOOSE) <= MAX_LOOSE, \
        f"modules loose at sc3_jax/: {loose_modules(pkg)} (named in LOOSE, at most {MAX_LOOSE}; put one in a folder)"


def test_floors_match_the_documented_stages():
    text = (ROOT / "docs" / "architecture.md").read_text()
    table = text.split("## Modules in data-flow order", 1)[1].split("\n## ", 1)[0]
    stages = [m.group(1).strip() for m in re.finditer(r"^\|([^|]+)\|", table, re.M)][2:]  # past header, rule
    assert stages == [f"{f}/" for f in FLOORS] + [f"{m}.py" for m in LOOSE]


def test_an_import_against_the_floors_is_reported(tmp_path):
    pkg = _write(tmp_path, {
        "pkg/__init__.py": "",
        "pkg/low/__init__.py": "",
        "pkg/low/a.py": "def f():\n    from pkg.high.b import g\n",  # function-level, still an edge
        "pkg/high/__init__.py": "",
        "pkg/high/b.py": "from pkg.low import a\nfrom pkg import top\n\ndef g():\n    pass\n",
        "pkg/stray/__init__.py": "",
        "pkg/stray/c.py": "",
        "pkg/top.py": "from pkg.high import b\n",
    })
    floors = ["low", "high"]
    assert find_cycle(graph := import_graph(pkg)) is not None  # (and a cycle, which the other test reports)
    assert layer_violations(graph, floors, "pkg") == [
        "pkg.high.b (floor 'high') imports pkg.top (higher floor 'loose')",
        "pkg.low.a (floor 'low') imports pkg.high.b (higher floor 'high')",
        "pkg.stray: in no floor (add its folder to FLOORS and docs/architecture.md)",
        "pkg.stray.c: in no floor (add its folder to FLOORS and docs/architecture.md)"]
    assert loose_modules(pkg) == ["top"]
    assert layer_violations({"pkg.low.a": set(), "pkg.high.b": {"pkg.low.a"}, "pkg.top": {"pkg.high.b"}},
                            floors, "pkg") == []


def folder_violations(graph: dict[str, set[str]], top: str = "sc3_jax") -> list[str]:
    """The folders' rules: a benchmark (``benchmarks/NAME/``) is a plug-in of the evaluation core, so nothing but the
    commands imports one, no benchmark imports another, and none imports the commands but its own commands
    (``benchmarks/NAME/commands/``, which are commands: they use the commands' helpers)."""
    def bench(m: str) -> str | None:
        parts = m.split(".")
        return parts[2] if len(parts) > 2 and parts[1] == "benchmarks" else None

    def command(m: str) -> bool:
        return m == f"{top}.cli" or m.startswith(f"{top}.commands") or own_command(m, top)
    out = []
    for mod in sorted(graph):
        for dep in sorted(graph[mod]):
            b, d = bench(mod), bench(dep)
            if d and not b and not command(mod):
                out.append(f"{mod} imports the benchmark {dep}: pass what it needs in from the command instead")
            elif b and d and b != d:
                out.append(f"{mod} (benchmark {b}) imports {dep} (benchmark {d})")
            elif b and command(dep) and not command(mod):
                out.append(f"{mod} (benchmark {b}) imports the command {dep}")
    return out


def test_nothing_below_the_commands_imports_a_benchmark():
    graph = import_graph(ROOT / "sc3_jax")
    assert any(m.startswith("sc3_jax.benchmarks.bussing.") for m in graph)  # the walk sees the benchmark
    problems = folder_violations(graph)
    assert not problems, "\n".join(problems)


def test_the_folder_check_catches_the_core_importing_a_benchmark():
    graph = {"sc3_jax.evaluation.report": {"sc3_jax.benchmarks.bussing.zoo"},
             "sc3_jax.benchmarks.so101.zoo": {"sc3_jax.benchmarks.bussing.zoo", "sc3_jax.evaluation.results"},
             "sc3_jax.commands.sweep": {"sc3_jax.benchmarks.bussing.sweep"},
             "sc3_jax.benchmarks.bussing.zoo": {"sc3_jax.commands.sweep", "sc3_jax.benchmarks.bussing.commands.sim"},
             "sc3_jax.benchmarks.bussing.commands.sim": {"sc3_jax.commands", "sc3_jax.benchmarks.bussing.zoo"},
             "sc3_jax.benchmarks.so101.commands.so101": {"sc3_jax.benchmarks.bussing.zoo"}}
    assert len(folder_violations(graph)) == 5  # a benchmark's own command may use the commands' helpers, no other's


def test_a_benchmarks_own_commands_sit_on_the_commands_floor():
    graph = {"sc3_jax.benchmarks.bussing.commands.sim": {"sc3_jax.commands"}, "sc3_jax.commands": set(),
             "sc3_jax.benchmarks.bussing.zoo": {"sc3_jax.benchmarks.bussing.commands.sim"}}
    assert layer_violations(graph) == ["sc3_jax.benchmarks.bussing.zoo (floor 'benchmarks') imports "
                                       "sc3_jax.benchmarks.bussing.commands.sim (higher floor 'commands')"]


def test_the_benchmarks_hooks_load_no_simulator_for_a_labs_robot():
    """The commands pass the simulated benchmark's hooks on every run; for a lab's robot (other views, its own
    policies) they must not load MuJoCo or the perception network (the ``[sim]`` extra may be absent)."""
    import subprocess
    import sys
    code = ("import sys, numpy as np; from sc3_jax.benchmarks.bussing import hooks; "
            "assert hooks.perception_scorer(['front'], (96, 128))[0] is None; "
            "hooks.object_pixels(np.zeros((1, 2, 4, 4, 3), np.uint8)); "
            "print(sorted(m for m in ('mujoco', 'sc3_jax.benchmarks.bussing.perception') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]", out


def test_the_benchmark_registry_imports_no_benchmark():
    """``sc3_jax/evaluation/benchmark.py`` names the benchmarks by "module:attr" strings, imported on lookup: neither
    its source nor importing it loads ``sc3_jax.benchmarks``."""
    import subprocess
    import sys
    graph = import_graph(ROOT / "sc3_jax")
    assert not {d for d in graph["sc3_jax.evaluation.benchmark"] if d.startswith("sc3_jax.benchmarks")}
    code = ("import sys, sc3_jax.evaluation.benchmark; "
            "print(sorted(m for m in sys.modules if m.startswith('sc3_jax.benchmarks')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]", out

"""No import cycle between the modules of ``sc3_jax/``, and no import against the layer order of docs/architecture.md.

The graph is read from the source (``ast``), not by importing: every ``import x`` / ``from x import y`` statement
counts, *including those inside functions*. A function-level import is still a dependency (it runs on the first
call), and the loops this guards against were all lazy ones (sim/zoo -> demos -> evaluate -> zoo); a lazy import
that only exists to dodge a cycle is the smell, not the fix. Imports under ``if TYPE_CHECKING:`` never run and are
skipped. ``from pkg import name`` is an edge to ``pkg.name`` when that is a module, else to ``pkg``.

The layers live here as data (``LAYERS``), not parsed out of the doc's table: the table's cells are prose for
readers (``(+ ...)``, paths relative to the row), and a parser of them would be the fragile part. The doc and this
list are tied by ``test_layers_match_the_documented_stages`` (same stage names, same order).
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
    assert len(graph) > 50 and "sc3_jax.rollout" in graph["sc3_jax.benchmarks.bussing.sweep"]  # the walk sees the package
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


# docs/architecture.md "Modules in data-flow order", lowest first: a module may import its own layer and those above
# it in this list. Entries are module prefixes under sc3_jax; the longest one that matches places a module.
LAYERS: list[tuple[str, tuple[str, ...]]] = [
    ("stats", ("stats",)),  # the bottom floor: the statistics import no other sc3_jax module
    ("utilities", ("errors", "atomic", "xla_cost", "safe_names", "locks", "validate", "module_attr")),
    ("video", ("video",)),
    ("metrics", ("evaluate.metrics", "evaluate.permanence", "evaluate.locate", "evaluate.moved",
                 "evaluate.action_following", "evaluate.tracking")),
    ("episodes", ("data",)),
    ("normalisation", ("data.norm_stats",)),
    ("pipeline", ("data.pipeline", "data.latent_cache")),
    ("config", ("config", "tokenizer_config")),
    ("tokenizer", ("model.tokenizer", "model.autoencoder", "model.wan_tokenizer", "model.wan_vae",
                   "model.wan_vae_convert", "model.shapes")),
    ("model", ("model",)),
    ("training modes, flow", ("modes", "flow")),
    ("named configs", ("configs",)),
    ("checkpoint", ("checkpoint",)),
    ("train", ("train", "sharding", "tokenizer_train", "distill")),
    ("policies", ("policies",)),
    ("policy names", ("policies.resolve",)),
    ("rollout", ("rollout", "imagination_state", "state_head", "rollout_io")),
    ("results", ("evaluate.results",)),
    ("scoring", ("evaluate.scorers", "evaluate.degrade", "evaluate.labels", "evaluate.success_detector",
                 "evaluate.scorer_check")),
    ("diagnostics", ("evaluate.world_model", "evaluate.world_model_defaults", "evaluate.diagnose",
                     "evaluate.diagnose_config", "evaluate.diagnose_video", "evaluate.diagnose_actions",
                     "evaluate.diagnose_outcomes", "evaluate.diagnose_report", "evaluate.diagnose_table",
                     "evaluate.diagnose_kept", "evaluate.diagnose_follow", "evaluate.diagnose_headline",
                     "evaluate.rollout_summary", "plan", "plan_vae", "sizing")),
    ("sweep", ("evaluate.worker_pool", "evaluate.engine", "evaluate.ic_sweep", "evaluate.gym_env")),
    ("report", ("evaluate.report", "evaluate.report_html", "evaluate.calibrate", "evaluate.intervals", "evaluate.bootstrap",
                "evaluate.merged", "evaluate.curve", "evaluate.report_episodes", "evaluate.report_figures",
                "evaluate.eval_info")),
    ("benchmarks", ("benchmark", "benchmarks")),  # the interface and its registry (by name: it imports none), then each
    ("commands", ("cli", "commands", "convert_cli", "demo")),
]


def layer_of(mod: str, layers=LAYERS, top: str = "sc3_jax") -> tuple[int, str] | None:
    """(index, stage) of the longest prefix in ``layers`` matching ``mod``; None for packages' bare ``__init__``."""
    rel = mod[len(top) + 1:] if mod.startswith(top + ".") else None
    best = None
    for i, (stage, prefixes) in enumerate(layers):
        for p in prefixes:
            if rel is not None and (rel == p or rel.startswith(p + ".")) and (best is None or len(p) > best[0]):
                best = (len(p), i, stage)
    return best and best[1:]


def layer_violations(graph: dict[str, set[str]], layers=LAYERS, top: str = "sc3_jax") -> list[str]:
    """Every import from a lower layer to a higher one, and every module no layer places."""
    out = []
    for mod in sorted(graph):
        if mod in (top, f"{top}.evaluate", f"{top}.benchmarks"):
            continue  # empty package __init__s: nothing to place (the others match their package's prefix)
        if (lm := layer_of(mod, layers, top)) is None:
            out.append(f"{mod}: in no layer (add it to LAYERS and docs/architecture.md)")
            continue
        for dep in sorted(graph[mod]):
            ld = layer_of(dep, layers, top)
            if ld is not None and ld[0] > lm[0]:
                out.append(f"{mod} (layer {lm[1]!r}) imports {dep} (higher layer {ld[1]!r})")
    return out


def test_sc3_jax_imports_follow_the_documented_layers():
    problems = layer_violations(import_graph(ROOT / "sc3_jax"))
    assert not problems, "imports against docs/architecture.md's order:\n" + "\n".join(problems)


def test_layers_match_the_documented_stages():
    text = (ROOT / "docs" / "architecture.md").read_text()
    table = text.split("## Modules in data-flow order", 1)[1].split("\n## ", 1)[0]
    stages = [m.group(1).strip() for m in re.finditer(r"^\|([^|]+)\|", table, re.M)][2:]  # past header, rule
    assert stages == [s for s, _ in LAYERS]


def test_an_import_against_the_layers_is_reported(tmp_path):
    pkg = _write(tmp_path, {
        "pkg/__init__.py": "",
        "pkg/low.py": "def f():\n    from pkg.high import g\n",  # function-level, still an edge
        "pkg/high.py": "from pkg import low\n\ndef g():\n    pass\n",
        "pkg/stray.py": "",
    })
    layers = [("bottom", ("low",)), ("top", ("high",))]
    assert find_cycle(graph := import_graph(pkg)) is not None  # (and a cycle, which the other test reports)
    assert layer_violations(graph, layers, "pkg") == [
        "pkg.low (layer 'bottom') imports pkg.high (higher layer 'top')",
        "pkg.stray: in no layer (add it to LAYERS and docs/architecture.md)"]
    assert layer_violations({"pkg.low": set(), "pkg.high": {"pkg.low"}}, layers, "pkg") == []


def folder_violations(graph: dict[str, set[str]], top: str = "sc3_jax") -> list[str]:
    """The folders' rules: a benchmark (``benchmarks/NAME/``) is a plug-in of the evaluation core, so nothing but the
    commands imports one, and no benchmark imports another or the commands."""
    def bench(m: str) -> str | None:
        parts = m.split(".")
        return parts[2] if len(parts) > 2 and parts[1] == "benchmarks" else None

    def command(m: str) -> bool:
        return m == f"{top}.cli" or m.startswith(f"{top}.commands")
    out = []
    for mod in sorted(graph):
        for dep in sorted(graph[mod]):
            b, d = bench(mod), bench(dep)
            if d and not b and not command(mod):
                out.append(f"{mod} imports the benchmark {dep}: pass what it needs in from the command instead")
            elif b and d and b != d:
                out.append(f"{mod} (benchmark {b}) imports {dep} (benchmark {d})")
            elif b and command(dep):
                out.append(f"{mod} (benchmark {b}) imports the command {dep}")
    return out


def test_nothing_below_the_commands_imports_a_benchmark():
    graph = import_graph(ROOT / "sc3_jax")
    assert any(m.startswith("sc3_jax.benchmarks.bussing.") for m in graph)  # the walk sees the benchmark
    problems = folder_violations(graph)
    assert not problems, "\n".join(problems)


def test_the_folder_check_catches_the_core_importing_a_benchmark():
    graph = {"sc3_jax.evaluate.report": {"sc3_jax.benchmarks.bussing.zoo"},
             "sc3_jax.benchmarks.so101.zoo": {"sc3_jax.benchmarks.bussing.zoo", "sc3_jax.evaluate.results"},
             "sc3_jax.commands.sweep": {"sc3_jax.benchmarks.bussing.sweep"},
             "sc3_jax.benchmarks.bussing.zoo": {"sc3_jax.commands.sim"}}
    assert len(folder_violations(graph)) == 3


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
    """``sc3_jax/benchmark.py`` names the benchmarks by "module:attr" strings, imported on lookup: neither its source
    nor importing it loads ``sc3_jax.benchmarks``."""
    import subprocess
    import sys
    graph = import_graph(ROOT / "sc3_jax")
    assert not {d for d in graph["sc3_jax.benchmark"] if d.startswith("sc3_jax.benchmarks")}
    code = "import sys, sc3_jax.benchmark; print(sorted(m for m in sys.modules if m.startswith('sc3_jax.benchmarks')))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]", out

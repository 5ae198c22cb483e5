"""The commands in ``sc3_jax/commands/``: each option of ``sc3 COMMAND [SUB] --help`` (and of ``sc3 train
--help-config``, the world-model config) carries its own field's docstring, the spellings from before the move still
parse, and no module of the library falls back to argparse or keeps a ``__main__`` block."""
from __future__ import annotations

import ast
import dataclasses
import importlib
import importlib.util
import re
import typing
from pathlib import Path

import docstring_parser
import pytest
import tyro

from sc3_jax import cli
from sc3_jax.cli import main
from sc3_jax.commands import parse
from sc3_jax.core.config import Config

ROOT = Path(__file__).resolve().parents[1]
# commands whose modules exist by now (cli.MODULES lists them all; the others still run their old code)
PRESENT = sorted(name for name, module in cli.MODULES.items() if importlib.util.find_spec(module) is not None)


def _module(command: str):
    return importlib.import_module(cli.MODULES[command])


def _args(command: str):
    return _module(command).Args


def _flag(cls, field: dataclasses.Field, prefix: str = "") -> str:
    """How --help names the field: a positional by its upper-case name, an option by --its-name (nested config
    fields by --SECTION.its-name), or by the name its ``tyro.conf.arg(name=...)`` gives it."""
    if "Positional" in str(field.type):
        return field.name.upper()
    try:
        hint = typing.get_type_hints(cls, include_extras=True)[field.name]
    except (NameError, TypeError):  # an annotation that does not resolve here: tyro names it after the field
        hint = None
    names = [m.name for m in getattr(hint, "__metadata__", ()) if isinstance(getattr(m, "name", None), str)]
    return "--" + prefix + (names[0] if names else field.name).replace("_", "-")


def _help_text(argv: list[str], capsys) -> str:
    """``sc3 ARGV`` (ending in a help option): its help as one line of words. The box borders and line wrapping are
    layout, not content; the caller sets COLUMNS so that boxes are not laid out side by side (whose lines would
    interleave) and no flag is hyphenated across lines."""
    with pytest.raises(SystemExit) as e:
        main(argv)
    assert e.value.code == 0, f"sc3 {' '.join(argv)} exited with {e.value.code}"
    return " ".join(re.sub(r"[│╭╮╰╯─]", " ", capsys.readouterr().out).split())


def _leaves(cls, prefix: str = ""):
    """(dataclass, field, flag) of every leaf option of ``cls``; nested dataclasses become --SECTION.FIELD."""
    for f in dataclasses.fields(cls):
        value = f.default
        if dataclasses.is_dataclass(value):
            yield from _leaves(type(value), f"{prefix}{f.name.replace('_', '-')}.")  # tyro dashes sections too
        else:
            yield cls, f, _flag(cls, f, prefix)


def _misplaced(text: str, leaves, where: str) -> list[str]:
    """Every leaf whose docstring is missing, or whose text does not follow its own flag in ``text`` (a docstring
    above / beside / below the wrong field lands under a neighbour's flag)."""
    # a field's docstring sits in the class that declares it: an inherited field's in a base class
    docs = {cls: {p.arg_name: p.description for base in reversed(cls.__mro__[:-1])
                  for p in docstring_parser.parse_from_object(base).params}
            for cls in {cls for cls, _, _ in leaves}}
    flags = [flag for _, _, flag in leaves]
    problems = []
    for cls, f, flag in leaves:
        doc = docs[cls].get(f.name)
        if not (doc and doc.strip()):
            problems.append(f"{where}: {flag} has no docstring ({cls.__name__}.{f.name})")
            continue
        start = " ".join(doc.split()[:5])
        # the flag named nearest before some occurrence of the text must be this field's
        nearest = []
        for m in re.finditer(re.escape(start), text):
            before = {fl: max((x.start() for x in re.finditer(re.escape(fl) + r"(?![\w-])", text[:m.start()])),
                              default=-1) for fl in flags}
            nearest.append(max(before, key=before.get))
        if not nearest:
            problems.append(f"{where} lacks {flag}'s text {start!r}")
        elif flag not in nearest:
            problems.append(f"{where}: {flag}'s text {start!r} is under {', '.join(sorted(set(nearest)))}")
    return problems


@pytest.mark.parametrize("command", PRESENT)
def test_help_gives_every_option_its_own_docstring(command, capsys, monkeypatch):
    """``sc3 COMMAND --help``, or for a command with subcommands ``sc3 COMMAND SUB --help`` for each of them."""
    monkeypatch.setenv("COLUMNS", "120")
    module = _module(command)
    subcommands = getattr(module, "SUBCOMMANDS", None)
    if subcommands is None:
        assert hasattr(module, "Args"), f"{cli.MODULES[command]} has neither Args nor SUBCOMMANDS"
        targets = {command: ([command], module.Args)}
    else:
        assert subcommands, f"sc3 {command}: SUBCOMMANDS is empty"
        targets = {f"{command} {sub}": ([command, sub], args) for sub, args in subcommands.items()}
    problems = []
    for where, (argv, args) in targets.items():
        assert dataclasses.is_dataclass(args) and args.__dataclass_params__.frozen, f"sc3 {where}: Args not frozen"
        text = _help_text([*argv, "--help"], capsys)
        if not (args.__doc__ and args.__doc__.split()[0] in text):  # the description
            problems.append(f"sc3 {where} --help lacks the description (the Args docstring)")
        problems += _misplaced(text, list(_leaves(args)), f"sc3 {where} --help")
    assert not problems, "\n".join(problems)


def test_help_config_gives_every_config_field_its_own_docstring(capsys, monkeypatch):
    """``sc3 train --help-config``: every --SECTION.FIELD of the world-model config, under its own docstring."""
    monkeypatch.setenv("COLUMNS", "120")  # < 130: one column of boxes (tyro lays boxes side by side at 65 each)
    text = _help_text(["train", "--config", "tiny", "--help-config"], capsys)
    leaves = list(_leaves(Config))
    assert len(leaves) > 60 and "--model.patch-size" in {flag for _, _, flag in leaves}
    problems = _misplaced(text, leaves, "sc3 train --help-config")
    assert not problems, "\n".join(problems)


def test_the_help_check_catches_a_docstring_under_the_wrong_flag():
    """The check itself: a text that follows the neighbour's flag (what tyro does with a comment above a field) is
    reported, and a missing docstring too."""
    @dataclasses.dataclass(frozen=True)
    class Two:
        first: int = 0
        """the first one"""
        second: int = 0
        """the second one"""

    leaves = list(_leaves(Two))
    assert _misplaced("--first INT the first one --second INT the second one", leaves, "x") == []
    assert _misplaced("--first INT the second one --second INT the first one", leaves, "x") == [
        "x: --first's text 'the first one' is under --second", "x: --second's text 'the second one' is under --first"]

    @dataclasses.dataclass(frozen=True)
    class Bare:
        lone: int = 0

    assert _misplaced("--lone INT", list(_leaves(Bare)), "x") == ["x: --lone has no docstring (Bare.lone)"]

    @dataclasses.dataclass(frozen=True)
    class Renamed:
        src_kind: typing.Annotated[str, tyro.conf.arg(name="from")] = "a"
        """where from"""

    assert [flag for _, _, flag in _leaves(Renamed)] == ["--from"]


@pytest.mark.parametrize("command, argv, expected", [
    ("report", ["a", "b", "--out", "o", "--videos", "1", "--taus", "0.02", "0.05", "--draws", "50"],
     dict(results=("a", "b"), out="o", videos=1, taus=(0.02, 0.05), draws=50, real=None, benchmark=None)),
    ("report", ["a"], dict(results=("a",), out=None, videos=None, taus=None, draws=2000, real=None, benchmark=None)),
    ("curve", ["spec.json", "--out", "o"], dict(spec="spec.json", out="o", draws=2000)),
    ("rescore", ["r", "--perception", "p.npz", "--state-reader", "s.npz", "--no-progress"],
     dict(results="r", perception="p.npz", state_reader="s.npz", progress=False)),
    ("rescore", ["r"], dict(results="r", perception=None, state_reader=None, progress=True)),
    ("diagnose-table", ["--world-model", "m1", "m2", "--baseline", "m1", "--out", "t.md"],
     dict(world_model=("m1", "m2"), baseline="m1", out="t.md")),
    ("configs", [], {}),
])
def test_the_spellings_from_before_still_parse(command, argv, expected):
    assert dataclasses.asdict(parse(_args(command), argv, command)) == expected


@pytest.mark.parametrize("command, argv", [("report", []), ("curve", ["spec.json"]), ("rescore", []),
                                           ("diagnose-table", []), ("configs", ["stray"])])
def test_missing_or_stray_arguments_are_usage_errors(command, argv, capsys):
    try:
        rc = main([command, *argv])  # a UserError: one line, exit status 2
    except SystemExit as e:  # tyro's usage error
        rc = e.code
    assert rc == 2 and capsys.readouterr().err


def _is_main_block(node: ast.AST) -> bool:
    """``if __name__ == "__main__":`` (either order of the comparison)."""
    if not (isinstance(node, ast.If) and isinstance(node.test, ast.Compare) and len(node.test.comparators) == 1):
        return False
    sides = [node.test.left, node.test.comparators[0]]
    return (any(isinstance(s, ast.Name) and s.id == "__name__" for s in sides)
            and any(isinstance(s, ast.Constant) and s.value == "__main__" for s in sides))


def test_no_module_uses_argparse_or_keeps_a_main_block():
    """Commands parse with tyro in sc3_jax/commands/; sc3_jax/cli.py is the one entry point. (Fails while modules
    are still being converted: it lists every one left.)"""
    problems = []
    for p in sorted((ROOT / "sc3_jax").rglob("*.py")):
        rel = p.relative_to(ROOT).as_posix()
        if rel == "sc3_jax/cli.py":
            continue
        tree = ast.parse(p.read_text(), rel)
        imported = {a.name.split(".")[0] for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
        imported |= {n.module.split(".")[0] for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.module}
        if "argparse" in imported:
            problems.append(f"{rel} imports argparse: parse with tyro (a dataclass in sc3_jax/commands/)")
        if any(_is_main_block(n) for n in ast.walk(tree)):
            problems.append(f"{rel} has an `if __name__ == \"__main__\"` block: run it as an `sc3` command")
    assert not problems, "\n".join(problems)


def test_libraries_whose_commands_moved_keep_no_main():
    for lib in ("benchmarks.bussing.rescore", "evaluation.diagnose_table"):  # their commands: modules of cli.MODULES
        assert not hasattr(importlib.import_module(f"sc3_jax.{lib}"), "main")


def _targets(command: str) -> list[list[str]]:
    subcommands = getattr(_module(command), "SUBCOMMANDS", None)
    return [[command]] if subcommands is None else [[command, sub] for sub in subcommands]


def _entries(text: str) -> list[str]:
    """The help's entries: each option (or positional) with the lines that continue it."""
    entries: list[str] = []
    for line in text.splitlines():
        inner = line.strip(" │")
        if re.match(r"(-\w|--\w|[A-Z][A-Z_]+\b)", inner) or not entries:
            entries.append(inner)
        else:
            entries[-1] += " " + inner
    return entries


@pytest.mark.parametrize("command", PRESENT)
def test_help_prints_each_default_once_and_no_path_or_measurement(command, capsys, monkeypatch):
    """A default said twice ("(default: all) (default: None)") reads as two; a path of this machine's install, or
    a measured interval, is not help (measurements live in docs/results.md)."""
    monkeypatch.setenv("COLUMNS", "300")
    home = str(Path.home())
    problems = []
    for argv in _targets(command):
        with pytest.raises(SystemExit):
            main([*argv, "--help"])
        text = capsys.readouterr().out
        for entry in _entries(text):
            if len(re.findall(r"\(default\b", entry)) > 1:
                problems.append(f"sc3 {' '.join(argv)}: two defaults in {' '.join(entry.split())[:120]!r}")
        for bad in {str(ROOT), "site-packages", home} - {"/"}:
            if bad in text:
                problems.append(f"sc3 {' '.join(argv)} --help names {bad!r}")
        if re.search(r"\[[-+]?\d\.\d+, [-+]?\d\.\d+\]", text):
            problems.append(f"sc3 {' '.join(argv)} --help quotes a measured interval")
    assert not problems, "\n".join(problems)


def test_the_default_check_catches_a_default_said_twice():
    entries = _entries("│ --steps {None}|INT  training steps (default: the config's) (default: None) │\n"
                       "│ --out STR  where (default: runs/x)  │\n│            more words │")
    assert [len(re.findall(r"\(default\b", e)) for e in entries] == [2, 1]


def test_the_top_level_usage_lists_every_command_and_subcommand(capsys):
    assert main(["--help"]) == 0
    text = " ".join(capsys.readouterr().out.split())
    for name, module in cli.MODULES.items():
        summary, subs = cli.describe(module)
        assert summary, f"{module} has no SUMMARY (the line `sc3 --help` shows)"
        assert f"{name} {summary.split()[0]}" in text, name
        imported = getattr(_module(name), "SUBCOMMANDS", {})
        assert subs == list(imported), f"sc3 {name}: usage lists {subs}, the module has {list(imported)}"
        for sub in subs:
            assert re.search(rf"[(|] ?{re.escape(sub)} ?[|)]", text), f"sc3 --help lacks {name} {sub}"


def test_the_top_level_usage_imports_no_command_no_benchmark_and_no_numpy():
    """`sc3 --help` reads every command's SUMMARY and subcommands (`sc3 sweep`'s benchmarks too) from the sources."""
    import subprocess
    import sys
    code = ("import sys; from sc3_jax import cli; cli.usage(); print(sorted(m for m in sys.modules if m.startswith("
            "('sc3_jax.commands', 'sc3_jax.benchmarks', 'numpy', 'tyro', 'jax'))))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]", out


def test_a_benchmarks_own_commands_are_found_on_disk_and_replace_no_other():
    """Each ``sc3_jax/benchmarks/NAME/commands/CMD.py`` is ``sc3 CMD``; cli.py names no benchmark, and no two command
    modules share a command's name (a later one would replace the other in cli.MODULES)."""
    from sc3_jax.evaluation import benchmark

    own = [p for p in sorted((ROOT / "sc3_jax" / "benchmarks").glob("*/commands/*.py")) if p.stem != "__init__"]
    assert {"sim", "so101"} <= {p.stem for p in own}
    found = {name: m for name, m in cli.MODULES.items() if m.startswith("sc3_jax.benchmarks.")}
    assert sorted(found.values()) == sorted(f"sc3_jax.benchmarks.{p.parents[1].name}.commands.{p.stem}" for p in own)
    assert not set(found) & set(cli.CORE)
    source = (ROOT / "sc3_jax" / "cli.py").read_text()
    assert not [name for name in benchmark.names() + list(benchmark.ALIASES) if re.search(rf"\b{name}\b", source)]

"""The commands in ``sc3_jax/commands/``: each option of ``sc3 COMMAND --help`` carries its own field's docstring, the
spellings from before the move still parse, and no command module falls back to argparse."""
from __future__ import annotations

import ast
import dataclasses
import importlib
import re
from pathlib import Path

import docstring_parser
import pytest

from sc3_jax.cli import main
from sc3_jax.commands import parse

ROOT = Path(__file__).resolve().parents[1]
CONVERTED = {"report": "report", "curve": "curve", "rescore": "rescore", "diagnose-table": "diagnose_table",
             "configs": "configs"}


def _args(command: str):
    return importlib.import_module(f"sc3_jax.commands.{CONVERTED[command]}").Args


def _flag(field: dataclasses.Field) -> str:
    """How --help names the field: a positional by its upper-case name, an option by --its-name."""
    return field.name.upper() if "Positional" in str(field.type) else "--" + field.name.replace("_", "-")


@pytest.mark.parametrize("command", sorted(CONVERTED))
def test_help_gives_every_option_its_own_docstring(command, capsys, monkeypatch):
    monkeypatch.setenv("COLUMNS", "200")  # wide enough that no flag is hyphenated across lines
    args = _args(command)
    docs = {p.arg_name: p.description for p in docstring_parser.parse_from_object(args).params}
    with pytest.raises(SystemExit) as e:
        main([command, "--help"])
    assert e.value.code == 0
    # one line of words: the help's box borders and line wrapping are layout, not content
    text = " ".join(re.sub(r"[│╭╮╰╯─]", " ", capsys.readouterr().out).split())
    fields = dataclasses.fields(args)
    flags = {f.name: _flag(f) for f in fields}
    assert args.__doc__.split()[0] in text  # the description
    for f in fields:
        doc = docs.get(f.name)
        assert doc and doc.strip(), f"sc3 {command}: {f.name} has no docstring"
        start = " ".join(doc.split()[:5])
        at = text.find(start)
        assert at >= 0, f"sc3 {command} --help lacks {f.name}'s text {start!r}"
        # the option named nearest before that text is this field's (a docstring above / below the wrong field
        # would land under its neighbour)
        before = {name: max((m.start() for m in re.finditer(re.escape(flag) + r"(?![\w-])", text[:at])), default=-1)
                  for name, flag in flags.items()}
        assert max(before, key=before.get) == f.name, f"sc3 {command}: {start!r} is not under {flags[f.name]}"


@pytest.mark.parametrize("command, argv, expected", [
    ("report", ["a", "b", "--out", "o", "--videos", "1", "--taus", "0.02", "0.05", "--draws", "50"],
     dict(results=("a", "b"), out="o", videos=1, taus=(0.02, 0.05), draws=50)),
    ("report", ["a"], dict(results=("a",), out=None, videos=3, taus=None, draws=2000)),
    ("curve", ["spec.json", "--out", "o"], dict(spec="spec.json", out="o", draws=2000)),
    ("rescore", ["r", "--perception", "p.npz", "--state-reader", "s.npz", "--no-progress"],
     dict(results="r", perception="p.npz", state_reader="s.npz", progress=False)),
    ("rescore", ["r"], dict(results="r", perception=None, state_reader=None, progress=True)),
    ("diagnose-table", ["m1", "m2", "--baseline", "m1", "--out", "t.md"],
     dict(models=("m1", "m2"), baseline="m1", out="t.md")),
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


def test_command_modules_do_not_use_argparse_or_keep_mains_in_the_library():
    paths = sorted((ROOT / "sc3_jax" / "commands").glob("*.py"))
    assert {p.stem for p in paths} >= set(CONVERTED.values())
    for p in paths + [ROOT / "sc3_jax/evaluate/rescore.py", ROOT / "sc3_jax/evaluate/diagnose_table.py"]:
        tree = ast.parse(p.read_text())
        imported = {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
        imported |= {n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)}
        assert "argparse" not in imported, f"{p.relative_to(ROOT)} imports argparse: parse with tyro"
    for lib in ("rescore", "diagnose_table"):  # their commands moved to sc3_jax/commands/
        assert not hasattr(importlib.import_module(f"sc3_jax.evaluate.{lib}"), "main")

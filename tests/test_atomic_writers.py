"""Every file the package writes is written atomically (sc3_jax/core/atomic.py: a temporary, then a rename), so a kill
leaves the old file or the new one, never half of one; and a damaged file it reads back is a one-line error.

The scan below finds every raw write call in sc3_jax (``open(..., "w")``, ``Path.write_text``, ``np.save*``,
``json.dump``, ``savefig``, ...) that is not aimed at the temporary of an ``atomic.replacing`` / ``replacing_dir`` /
``staged`` block around it. Each one left must be in ``ALLOWED`` with the reason it is safe: a new raw writer
fails here, and so does an entry whose call is gone (remove it)."""
from __future__ import annotations

import ast
import json
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

import sc3_jax
from sc3_jax.core import atomic
from sc3_jax.core.errors import UserError

PACKAGE = Path(sc3_jax.__file__).parent

# (file under sc3_jax/, enclosing function, writer) -> why it is safe
STAGED = "report.render passes a path inside its atomic.staged directory"
ALLOWED = {
    **{("evaluation/report_figures.py", fn, "savefig"): STAGED for fn in ("scatter", "u_plot", "filmstrip")},
    ("evaluation/results.py", "ResultsStore.append", "open(a)"):
        "the append-only results.jsonl (flushed, fsynced); ResultsStore._repair drops a line cut by a kill",
    ("train/trunk_state.py", "write.extra", "shutil.copyfile"):
        "into the temporary directory of checkpoint.save's atomic.replacing_dir: the state appears whole or not at all",
    ("train/train.py", "MetricsLog.write", "open(a)"):
        "the append-only metrics.jsonl; MetricsLog.__init__ drops a line cut by a kill (atomic.drop_cut_line)",
    ("train/train.py", "MetricsLog.__init__", "SummaryWriter"):
        "TensorBoard event files: a log for viewing, appended by tensorboardX, read by nothing here",
    ("train/tokenizer_train.py", "train", "open(a)"):
        "the append-only metrics.jsonl, flushed per line; atomic.drop_cut_line runs before it is reopened",
    ("benchmarks/bussing/sweep.py", "link_real", "shutil.copy2"):
        "arrays copied before their record is appended: a copy cut by a kill has no record, and is unlinked and "
        "copied again on resume",
    ("data/lerobot_write.py", "_VideoFile.__init__", "open(w)"):
        "PyAV encodes into the dataset's temporary directory, which lerobot_write renames into place whole",
    ("data/episodes.py", "EpisodeStore.write", "np.save"):
        "into the episode's temporary directory (mkdtemp in the store), renamed into place whole (os.replace)",
    ("data/episodes.py", "EpisodeStore.write", "write_text"):
        "into the episode's temporary directory (mkdtemp in the store), renamed into place whole (os.replace)",
    ("commands/convert_cli.py", "_write_atomically", "shutil.move"):
        "moves a finished temporary directory beside --to into place: a rename (same file system)",
    ("policies/lerobot_child.py", "main", "np.savez"):
        "into an in-memory buffer (io.BytesIO): a message on the pipe to the parent, no file",
    ("policies/lerobot_policy.py", "LeRobotPolicy.infer", "np.savez"):
        "into an in-memory buffer (io.BytesIO): a message on the pipe to the LeRobot child, no file",
}

NP_SAVERS = {"save", "savez", "savez_compressed", "savetxt"}
ANY_RECEIVER = {"to_csv", "to_parquet", "savefig", "imwrite", "imsave", "tofile", "save_file", "VideoWriter",
                "SummaryWriter"}
ATOMIC_BLOCKS = {"replacing", "replacing_dir", "staged"}


def _writer(call: ast.Call) -> str | None:
    """What ``call`` writes with, if it writes a file by itself (None: it does not)."""
    f = call.func
    name = f.attr if isinstance(f, ast.Attribute) else f.id if isinstance(f, ast.Name) else None
    owner = f.value.id if isinstance(f, ast.Attribute) and isinstance(f.value, ast.Name) else None
    if name == "open":  # open(p, "w"), Path.open("a"), av.open(p, mode="w"), gzip.open(p, "wb"), ...
        given = [k.value for k in call.keywords if k.arg == "mode"] + call.args[:2]
        modes = [m.value for m in given if isinstance(m, ast.Constant) and isinstance(m.value, str)
                 and 0 < len(m.value) <= 3 and set(m.value) <= set("rwxabt+")]  # a mode, not a path like "a.txt"
        mode = next((m for m in modes if set(m) & set("wax+")), None)
        return f"open({mode.replace('b', '').replace('t', '')})" if mode else None
    if name in ("write_text", "write_bytes"):
        return None if owner == "atomic" else name
    if name in NP_SAVERS and owner in ("np", "numpy"):
        return f"np.{name}"
    if name == "dump" and owner in ("json", "pickle", "yaml"):
        return f"{owner}.dump"
    if owner == "shutil" and name in ("copy", "copy2", "copyfile", "copytree", "move"):
        return f"shutil.{name}"
    return name if name in ANY_RECEIVER else None


def _atomic_targets(node: ast.With) -> set[str]:
    """The names an ``with atomic.replacing(...) as tmp`` (or replacing_dir / staged) binds."""
    out = set()
    for item in node.items:
        e = item.context_expr
        if isinstance(e, ast.Call) and isinstance(item.optional_vars, ast.Name):
            f = e.func
            name = f.attr if isinstance(f, ast.Attribute) else f.id if isinstance(f, ast.Name) else None
            owner = f.value.id if isinstance(f, ast.Attribute) and isinstance(f.value, ast.Name) else "atomic"
            if name in ATOMIC_BLOCKS and owner == "atomic":
                out.add(item.optional_vars.id)
    return out


def raw_writes(source: str) -> list[tuple[str, str, int]]:
    """(enclosing function, writer, line) of every raw write in ``source`` not aimed at an atomic temporary."""
    found = []

    def visit(node, scope: tuple[str, ...], targets: frozenset[str]):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            scope = scope + (node.name,)
        if isinstance(node, (ast.With, ast.AsyncWith)):
            targets = targets | _atomic_targets(node)
        if isinstance(node, ast.Call):
            w = _writer(node)
            # aimed at the temporary: the call names it (its receiver or an argument), e.g. np.save(tmp, ...),
            # (stage / "x.json").write_text(...), fig.savefig(tmp, ...)
            if w and not ({n.id for n in ast.walk(node) if isinstance(n, ast.Name)} & targets):
                found.append((".".join(scope) or "<module>", w, node.lineno))
        for child in ast.iter_child_nodes(node):
            visit(child, scope, targets)

    visit(ast.parse(source), (), frozenset())
    return found


def package_raw_writes() -> dict[tuple[str, str, str], list[int]]:
    out: dict[tuple[str, str, str], list[int]] = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(PACKAGE).as_posix()
        if rel == "core/atomic.py":  # where the temporaries are written and renamed
            continue
        for scope, writer, line in raw_writes(path.read_text()):
            out.setdefault((rel, scope, writer), []).append(line)
    return out


def test_the_scan_finds_raw_writes_and_passes_atomic_ones():
    src = textwrap.dedent('''
        import json, shutil
        import numpy as np
        from sc3_jax.core import atomic

        def raw(path, fig, df):
            path.write_text("x")
            with open(path, "w") as fh:
                json.dump({}, fh)
            with open(path, "ab") as fh:
                fh.write(b"x")
            np.savez_compressed(path, a=1)
            fig.savefig(path)
            df.to_csv(path)
            shutil.copy2(path, path)
            with atomic.replacing(path) as tmp:
                (path / "x").write_text("aimed past the temporary")

        def fine(path, fig):
            with open(path) as fh, open(path, "rb") as fb:
                fh.read(), fb.read()
            atomic.write_text(path, "x")
            with atomic.replacing(path) as tmp:
                np.save(tmp, 1)
                fig.savefig(tmp, format="png")
            with atomic.staged(path) as stage:
                (stage / "a.json").write_text("{}")
    ''')
    found = [(s, w) for s, w, _ in raw_writes(src)]
    assert found == [("raw", "write_text"), ("raw", "open(w)"), ("raw", "json.dump"), ("raw", "open(a)"),
                     ("raw", "np.savez_compressed"), ("raw", "savefig"), ("raw", "to_csv"), ("raw", "shutil.copy2"),
                     ("raw", "write_text")]


def test_the_package_writes_only_through_atomic_or_an_allowed_exception():
    found = package_raw_writes()
    new = {k: v for k, v in found.items() if k not in ALLOWED}
    assert not new, ("raw writes (a kill mid-write leaves half a file): write through sc3_jax.core.atomic (write_text, "
                     "write_json, save_npz, replacing(path) as tmp, staged(dir)), or add the call to ALLOWED with "
                     "why it is safe:\n" + "\n".join(f"  sc3_jax/{f}:{lines} in {s}: {w}"
                                                     for (f, s, w), lines in new.items()))
    gone = [k for k in ALLOWED if k not in found]
    assert not gone, f"ALLOWED entries whose call is gone (remove them): {gone}"
    assert all(r.strip() for r in ALLOWED.values())


# -- behaviour: a writer killed mid-write leaves the old file, and its temporary goes with the next writer ------
KILL_AT_FSYNC = "import os; os.fsync = lambda fd: os._exit(9)\n"  # dies after writing, before the rename
WRITERS = {  # (file name, code writing __V__ to __PATH__)
    "diagnose result": ("diagnose.json", "from sc3_jax.evaluation.diagnose_report import save_result\n"
                                         "save_result({'v': __V__, 'nan': float('nan')}, __PATH__)"),
    "zoo weights": ("run.npz", "import numpy as np; from sc3_jax.benchmarks.bussing import zoo\n"
                               "zoo.save_params(__PATH__, {'head': {'w': np.full((2, 2), __V__)}})"),
}


def _write(path: Path, code: str, v: int, kill: bool) -> subprocess.CompletedProcess:
    src = (KILL_AT_FSYNC if kill else "") + code.replace("__PATH__", repr(str(path))).replace("__V__", str(v))
    return subprocess.run([sys.executable, "-c", src], capture_output=True, text=True, timeout=120)


@pytest.mark.parametrize("what", sorted(WRITERS))
def test_a_writer_killed_mid_write_leaves_the_old_file(tmp_path, what):
    name, code = WRITERS[what]
    path = tmp_path / name
    assert _write(path, code, 1, kill=False).returncode == 0
    old = path.read_bytes()
    r = _write(path, code, 2, kill=True)
    assert r.returncode == 9, r.stderr
    left = sorted(p.name for p in tmp_path.iterdir())
    assert path.read_bytes() == old and len(left) == 2, left  # the old file, and the dead writer's temporary
    assert [p.name for p in atomic.remove_stale(tmp_path)] == [n for n in left if n != name]
    assert _write(path, code, 2, kill=False).returncode == 0 and path.read_bytes() != old


def test_a_curve_that_fails_half_way_leaves_the_old_one_and_its_neighbours(tmp_path, monkeypatch):
    from sc3_jax.evaluation import curve

    c = {"title": "t"}
    monkeypatch.setattr(curve, "read_spec", lambda p: {})
    monkeypatch.setattr(curve, "compute", lambda spec, draws: c)
    monkeypatch.setattr(curve, "markdown", lambda c: f"# {c['title']}\n")
    monkeypatch.setattr(curve, "plot", lambda c, path: Path(path).write_bytes(b"png " + c["title"].encode()))
    out = tmp_path / "curve"
    (out / "other").mkdir(parents=True)  # a directory the curve shares with other files
    curve.render("spec.json", out)
    before = {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()}
    assert sorted(before) == ["curve.json", "curve.md", "curve.png"]

    def broken(c, path):
        Path(path).write_bytes(b"half a plot")
        raise RuntimeError("plot failed")
    monkeypatch.setattr(curve, "plot", broken)
    c["title"] = "new"
    with pytest.raises(RuntimeError):
        curve.render("spec.json", out)
    assert {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()} == before
    assert sorted(p.name for p in out.iterdir()) == ["curve.json", "curve.md", "curve.png", "other"]


# -- behaviour: a damaged file read back is one line naming it -------------------------------------------------
def _damaged_readers(tmp_path: Path):
    import jax

    from sc3_jax.rollout import rollout_io
    from sc3_jax.evaluation import diagnose_report, diagnose_table
    from sc3_jax.benchmarks.bussing import perception
    from sc3_jax.benchmarks.bussing import zoo, zoo_train

    weights = tmp_path / "w.npz"
    perception.save(weights, perception.init(jax.random.key(0), n_kp=2, widths=(2, 2, 2), hidden=2))
    zoo.save_params(tmp_path / "run.npz", {"head": {"w": np.ones((2, 2))}})
    (tmp_path / "store").mkdir()
    (tmp_path / "store" / "dataset.json").write_text('{"fps": 2')
    (tmp_path / "wm").mkdir()
    (tmp_path / "wm" / "diagnose.json").write_text('{"gates": [')
    (tmp_path / "wm" / "config.json").write_text("{}")
    (tmp_path / "zoo").mkdir()
    (tmp_path / "zoo" / "zoo.json").write_text('{"policies"')
    for p in (weights, tmp_path / "run.npz"):
        p.write_bytes(p.read_bytes()[: p.stat().st_size // 2])
    return {"perception weights": (weights, lambda: perception.load(weights)),
            "zoo weights": (tmp_path / "run.npz", lambda: zoo.load_params(tmp_path / "run.npz")),
            "diagnose result": (tmp_path / "wm" / "diagnose.json",
                                lambda: diagnose_report.load_result(tmp_path / "wm" / "diagnose.json")),
            "diagnose-table model": (tmp_path / "wm" / "diagnose.json", lambda: diagnose_table.load(tmp_path / "wm")),
            "store fps": (tmp_path / "store" / "dataset.json",
                          lambda: rollout_io.data_fps(str(tmp_path / "store"), None)),
            "zoo manifest": (tmp_path / "zoo" / "zoo.json", lambda: zoo_train.write_manifest(tmp_path / "zoo"))}


def test_a_damaged_file_read_back_is_one_line_naming_it(tmp_path):
    for what, (path, read) in _damaged_readers(tmp_path).items():
        before = path.read_bytes()
        with pytest.raises(UserError) as e:
            read()
        msg = str(e.value)
        assert str(path) in msg and "\n" not in msg and "pickle" not in msg, (what, msg)
        assert path.read_bytes() == before, what  # reading (or refusing to rewrite) changed nothing


def test_a_diagnose_result_round_trips_its_non_finite_numbers(tmp_path):
    from sc3_jax.evaluation import diagnose_report
    path = diagnose_report.save_result({"a": [float("inf"), float("nan")], "b": np.float32(0.5)}, tmp_path / "d.json")
    assert json.loads(path.read_text()) == {"a": ["inf", "nan"], "b": 0.5}
    a = diagnose_report.load_result(path)["a"]
    assert a[0] == float("inf") and np.isnan(a[1])

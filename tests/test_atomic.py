"""Nothing lost: writes are whole or absent, and expected faults (a damaged store, params or frames, a changed
config) are one-line errors naming the file that change nothing."""
import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from sc3_jax.core import atomic
from sc3_jax.model import checkpoint
from sc3_jax.train import train
from sc3_jax.cli import main
from sc3_jax.core.config import load_config, replace
from sc3_jax.data.norm_stats import NormStats
from sc3_jax.core.errors import UserError
from sc3_jax.evaluation.results import ResultsStore

SWEEP = {"modes": ["real"], "episodes": 2, "seed0": 0}


def snapshot(root: Path) -> dict:
    """Every file under ``root`` with its bytes: equal snapshots mean nothing was written, renamed or left over."""
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def one_line(e) -> str:
    msg = str(e.value if hasattr(e, "value") else e)
    assert "\n" not in msg.strip() and "Traceback" not in msg and "allow_pickle" not in msg, msg
    return msg


def test_a_failed_write_leaves_the_old_file_and_no_temporary(tmp_path):
    path = tmp_path / "a.json"
    atomic.write_json(path, {"x": 1})
    with pytest.raises(RuntimeError), atomic.replacing(path) as tmp:
        tmp.write_text("half")
        raise RuntimeError
    assert json.loads(path.read_text()) == {"x": 1} and os.listdir(tmp_path) == ["a.json"]
    assert path.stat().st_mode & 0o044  # the umask's mode, not a temporary file's private one
    atomic.save_npz(tmp_path / "b.npz", a=np.arange(3))  # the temporary keeps the suffix numpy would add
    assert sorted(os.listdir(tmp_path)) == ["a.json", "b.npz"]


def test_a_store_without_sweep_json_refuses_to_resume(tmp_path):
    ResultsStore(tmp_path, SWEEP).append([{"id": "a", "mode": "real"}])
    (tmp_path / "sweep.json").unlink()
    before = snapshot(tmp_path)
    with pytest.raises(UserError, match="no sweep.json") as e:
        ResultsStore(tmp_path, dict(SWEEP, episodes=3))  # another protocol must not reuse the old records
    assert str(tmp_path / "results.jsonl") in one_line(e) and snapshot(tmp_path) == before


def test_a_corrupt_record_names_its_file_and_line_for_reading_and_resuming(tmp_path):
    store = ResultsStore(tmp_path, SWEEP)
    store.append([{"id": "a", "mode": "real"}])
    with open(store.path, "a") as fh:
        fh.write('{"id": "b", oops\n{"id": "c", "mode": "real"}\n')
    before = snapshot(tmp_path)
    for read in (lambda: ResultsStore(tmp_path).records(), lambda: ResultsStore(tmp_path, SWEEP)):
        with pytest.raises(UserError, match=f"{store.path}:2: not a rollout record") as e:
            read()
        assert "delete that line" in one_line(e) and snapshot(tmp_path) == before


def test_resuming_drops_a_cut_line_by_writing_a_new_file_and_says_so(tmp_path, capsys):
    store = ResultsStore(tmp_path, SWEEP)
    store.append([{"id": "a", "mode": "real"}])
    with open(store.path, "a") as fh:
        fh.write('{"id": "b", "mo')
    inode = store.path.stat().st_ino
    ResultsStore(tmp_path, SWEEP)
    assert store.path.read_text() == '{"id": "a", "mode": "real"}\n' and store.path.stat().st_ino != inode
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "dropped its last line" in err and str(store.path) in err


@pytest.mark.parametrize("keep", [0, 3, 0.5])  # empty, cut inside the zip magic (numpy's pickle branch), half
def test_truncated_frames_and_params_name_the_file(tmp_path, keep):
    def truncate(p):
        raw = p.read_bytes()
        p.write_bytes(raw[:int(len(raw) * keep) if isinstance(keep, float) else keep])

    store = ResultsStore(tmp_path / "s", SWEEP)
    store.save_arrays("p/0_real", frames=np.zeros((2, 4, 4, 3), np.uint8))
    truncate(store.array_path("p/0_real"))
    with pytest.raises(UserError, match="damaged or truncated") as e:
        store.load_arrays("p/0_real")
    assert str(store.array_path("p/0_real")) in one_line(e)

    cfg = replace(load_config("tiny"), model=dict(dim=32, depth=1, num_heads=2, num_kv_heads=1, head_dim=16,
                                                  mlp_dim=32, rope_axes_dim=(4, 2, 2)))
    params = {"w": np.ones((4, 4), np.float32)}
    stats = NormStats(np.zeros(7, np.float32), np.ones(7, np.float32))
    out = checkpoint.save(tmp_path / "wm", cfg, stats, params, np.float32)
    truncate(out / "params.npz")
    for read in (lambda: checkpoint.source_shapes(out), lambda: checkpoint.load_params(out, cfg)):
        with pytest.raises(UserError, match="damaged or truncated") as e:
            read()
        assert str(out / "params.npz") in one_line(e)


def test_train_refuses_a_changed_config_before_writing(tmp_path, capsys):
    workdir = tmp_path / "w"
    cfg = replace(load_config("tiny"), train=dict(workdir=str(workdir)))
    workdir.mkdir()
    atomic.write_json(workdir / "config.json", dataclasses.asdict(cfg))
    before = snapshot(workdir)
    rc = main(["train", "--config", "tiny", "--train.workdir", str(workdir), "--batch", "16",
               "--train.lr", "0.5", "--data", str(tmp_path / "none")])
    err = capsys.readouterr().err
    assert rc == 2 and err.startswith("sc3 train: error: ") and err.count("\n") == 1, err
    assert "data.batch_size 32 -> 16" in err and "train.lr" in err and "--train.workdir" in err
    assert snapshot(workdir) == before
    # how a run is driven may change on resume (here: more steps, no progress bar)
    train.check_workdir(dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, steps=10_000, progress=False)))


def test_a_damaged_config_json_is_one_line(tmp_path):
    (tmp_path / "config.json").write_text('{"name": "tiny",\n "model": }')
    with pytest.raises(UserError, match=r"config.json:2: not valid JSON") as e:
        checkpoint.read_config(tmp_path)
    one_line(e)


def test_a_directory_is_replaced_whole_keeping_what_others_put_there(tmp_path):
    out = tmp_path / "model"
    with atomic.replacing_dir(out) as d:
        (d / "a.json").write_text("old a")
        (d / "sub").mkdir()
        (d / "sub" / "x").write_text("old x")
    (out / "diagnose.json").write_text("another tool's")
    old = snapshot(tmp_path)
    with pytest.raises(RuntimeError), atomic.replacing_dir(out) as d:
        (d / "a.json").write_text("new a")
        raise RuntimeError  # a failure half-way: nothing changed, no temporary
    assert snapshot(tmp_path) == old and os.listdir(tmp_path) == ["model"]
    inode = out.stat().st_ino
    with atomic.replacing_dir(out) as d:
        (d / "a.json").write_text("new a")
        (d / "sub").mkdir()  # the block's own entries replace the old ones whole
    assert snapshot(tmp_path) == {"model/a.json": b"new a", "model/diagnose.json": b"another tool's"}
    assert out.stat().st_ino != inode and os.listdir(tmp_path) == ["model"]


def test_staged_files_move_in_last_named_last_and_a_failure_changes_nothing(tmp_path, monkeypatch):
    out = tmp_path / "a" / "report"
    with pytest.raises(UserError, match="damaged"), atomic.staged(out) as d:
        (d / "report.json").write_text("{}")
        raise UserError("frames: damaged")
    assert os.listdir(tmp_path) == []  # the directories it had made are gone again
    (out).mkdir(parents=True)
    (out / "report.md").write_text("old")
    (out / "keep.txt").write_text("mine")
    moved = []
    real_replace = os.replace
    monkeypatch.setattr(os, "replace", lambda a, b: (moved.append(Path(b).name), real_replace(a, b)))
    with atomic.staged(out, last=("report.md",)) as d:
        for name in ("report.md", "a.png", "report.json"):
            (d / name).write_text(f"new {name}")
    assert moved[-1] == "report.md" and sorted(moved) == ["a.png", "report.json", "report.md"]
    assert sorted(os.listdir(out)) == ["a.png", "keep.txt", "report.json", "report.md"]
    assert (out / "report.md").read_text() == "new report.md" and (out / "keep.txt").read_text() == "mine"


def test_only_the_temporaries_of_dead_writers_on_this_host_are_removed(tmp_path):
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    host = atomic._HOST
    names = {f".a.{host}-{dead.pid}.0123abcd.tmp.npz": False, f".b.{host}-{os.getpid()}.0123abcd.tmp": True,
             f".c.{host}x-{dead.pid}.0123abcd.tmp.json": True, f".d.other-{dead.pid}.0123abcd.tmp": True,
             "e.json": True}
    for n in names:
        (tmp_path / n).write_text("x")
    (tmp_path / f".dir.{host}-{dead.pid}.89abcdef.tmp").mkdir()  # an export's directory
    gone = atomic.remove_stale(tmp_path)
    assert sorted(p.name for p in gone) == sorted([f".a.{host}-{dead.pid}.0123abcd.tmp.npz",
                                                   f".dir.{host}-{dead.pid}.89abcdef.tmp"])
    assert sorted(os.listdir(tmp_path)) == sorted(n for n, keep in names.items() if keep)


def test_a_full_disk_is_one_line_and_keeps_the_old_file(tmp_path, monkeypatch):
    import errno
    store = ResultsStore(tmp_path, SWEEP)
    store.save_arrays("p/0_real", frames=np.zeros((1, 2, 2, 3), np.uint8))
    before = snapshot(tmp_path)

    def full(path, **_):
        Path(path).write_bytes(b"PK half")
        raise OSError(errno.ENOSPC, "No space left on device")
    monkeypatch.setattr(np, "savez_compressed", full)
    with pytest.raises(UserError, match="cannot write there .No space left on device.") as e:
        store.save_arrays("p/0_real", frames=np.ones((1, 2, 2, 3), np.uint8))
    assert str(store.array_path("p/0_real")) in one_line(e) and snapshot(tmp_path) == before


def test_an_export_that_fails_half_way_leaves_the_old_model_and_readers_write_nothing(tmp_path, monkeypatch):
    cfg = replace(load_config("tiny"), model=dict(dim=32, depth=1, num_heads=2, num_kv_heads=1, head_dim=16,
                                                  mlp_dim=32, rope_axes_dim=(4, 2, 2)))
    params = {"w": np.ones((4, 4), np.float32)}
    stats = NormStats(np.zeros(7, np.float32), np.ones(7, np.float32))
    out = checkpoint.save(tmp_path / "wm", cfg, stats, params, np.float32)
    (out / "diagnose.json").write_text("{}")
    before = snapshot(tmp_path)
    monkeypatch.setattr(NormStats, "save", lambda *a: (_ for _ in ()).throw(RuntimeError("killed here")))
    with pytest.raises(RuntimeError, match="killed here"):
        checkpoint.save(out, cfg, stats, {"w": np.zeros((4, 4), np.float32)}, "int8")
    assert snapshot(tmp_path) == before and os.listdir(tmp_path) == ["wm"]
    # a directory that is not a model: the reader says so, and creates nothing there (no checkpoints/)
    (tmp_path / "empty").mkdir()
    (tmp_path / "empty" / "config.json").write_bytes((out / "config.json").read_bytes())
    with pytest.raises(FileNotFoundError, match="no checkpoint under"):
        checkpoint.load_params(tmp_path / "empty", cfg)
    assert os.listdir(tmp_path / "empty") == ["config.json"]


def test_the_training_log_drops_a_cut_line_and_a_damaged_one_is_one_line(tmp_path):
    log = tmp_path / "metrics.jsonl"
    log.write_text('{"step": 1, "loss": 0.5}\n{"step": 2, "lo')  # a kill inside the second row
    assert list(train.read_metrics(tmp_path)) == [1]  # the cut line is left out while reading
    train.MetricsLog(tmp_path, tensorboard=False).write([{"step": 2, "loss": 0.25}])
    assert train.read_metrics(tmp_path) == {1: {"step": 1, "loss": 0.5}, 2: {"step": 2, "loss": 0.25}}
    log.write_text('{"step": 1}\n{"step": 2, oops\n{"step": 3}\n')
    before = snapshot(tmp_path)
    with pytest.raises(UserError, match=f"{log}:2: not a metrics row") as e:
        train.read_metrics(tmp_path)
    one_line(e)
    assert snapshot(tmp_path) == before

"""Nothing lost: writes are whole or absent, and expected faults (a damaged store, params or frames, a changed
config) are one-line errors naming the file that change nothing."""
import dataclasses
import json
import os
from pathlib import Path

import numpy as np
import pytest

from sc3_jax import atomic, checkpoint, train
from sc3_jax.cli import main
from sc3_jax.config import load_config, replace
from sc3_jax.data.norm_stats import NormStats
from sc3_jax.errors import UserError
from sc3_jax.evaluate.results import ResultsStore

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
    rc = main(["train", "--config", "tiny", "--train.workdir", str(workdir), "--data.batch-size", "16",
               "--train.lr", "0.5", "--data.path", str(tmp_path / "none")])
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

"""A results store knows what its rollouts came from: sweep.json records the world model's content hash and step,
the scorer's and the policies' file hashes (evaluation/engine.py with_identity); resuming it against a changed
model, scorer or policy file is refused in one line naming both, and a store from before the hash resumes with a
note, recording nothing new."""
import json

import jax
import numpy as np
import pytest

from sc3_jax.model import checkpoint
from sc3_jax.core.errors import UserError
from sc3_jax.evaluation import engine
from test_any_robot import bimanual  # noqa: F401  (the fixture: imported store + trained tiny model)
from test_ic_sweep import _conditions, _error, _sweep


def _store(root, **config):
    """A store holding one rollout record, whose sweep.json is ``config``."""
    root.mkdir(parents=True)
    (root / "sweep.json").write_text(json.dumps({"world_model": "wm", "scorer": "s:f", **config}))
    (root / "results.jsonl").write_text('{"id": "a/0_online"}\n')
    return root


IDENT = {"world_model_sha256": "a" * 64, "world_model_step": 120, "scorer_sha256": "c" * 64,
         "policies_sha256": {"p": "d" * 64}}


def test_a_resumed_sweep_against_another_model_is_refused_naming_both(tmp_path):
    out = _store(tmp_path / "s", **IDENT)
    config = {"world_model": "wm", "scorer": "s:f"}
    assert engine.with_identity(out, config, IDENT) == {**config, **IDENT}  # the same model: resumed
    trained_on = {**IDENT, "world_model_sha256": "b" * 64, "world_model_step": 240}
    with pytest.raises(UserError, match=r"world model wm \(step 120, sha256 a{16}\); wm is now step 240, sha256 b{16}"
                                        r": resuming would rank two models' rollouts together") as e:
        engine.with_identity(out, config, trained_on)
    assert "\n" not in str(e.value)
    with pytest.raises(UserError, match=r"--scorer s:f with sha256 c{16}; its files are now sha256 e{16}"):
        engine.with_identity(out, config, {**IDENT, "scorer_sha256": "e" * 64})
    with pytest.raises(UserError, match=r"policy 'p' with sha256 d{16}; its files are now sha256 f{16}"):
        engine.with_identity(out, config, {**IDENT, "policies_sha256": {"p": "f" * 64}})


def test_a_store_from_before_the_hash_resumes_with_a_note_recording_nothing_new(tmp_path, capsys):
    out = _store(tmp_path / "old")
    config = {"world_model": "wm", "scorer": "s:f"}
    assert engine.with_identity(out, config, IDENT) == config
    assert "predates recording the world model's content hash" in capsys.readouterr().out
    # a new store, or one whose sweep failed before its first rollout, records the identity
    assert engine.with_identity(tmp_path / "new", config, IDENT) == {**config, **IDENT}
    (out / "results.jsonl").write_text("")
    assert engine.with_identity(out, config, IDENT) == {**config, **IDENT}


def test_a_models_identity_is_its_files_and_a_workdirs_step(bimanual, tmp_path):  # noqa: F811
    run = bimanual[0] / "run"
    ident = checkpoint.identity(run)
    assert ident["step"] == 2 and len(ident["sha256"]) == 64 and checkpoint.identity(run) == ident
    wm = checkpoint.export(run, tmp_path / "wm")
    exported = checkpoint.identity(wm)
    assert exported["step"] is None and exported["sha256"] != ident["sha256"]
    (wm / "diagnose.json").write_text("{}")  # another tool's file beside the model: not the model
    assert checkpoint.identity(wm) == exported
    cfg, stats, params = checkpoint.load(wm)
    checkpoint.save(wm, cfg, stats, jax.tree.map(lambda x: np.asarray(x) + 1e-2, params))
    assert checkpoint.identity(wm)["sha256"] != exported["sha256"]


def test_sc3_sweep_records_its_model_and_refuses_to_resume_into_another(bimanual, tmp_path, capsys):  # noqa: F811
    ic = _conditions(bimanual[4], tmp_path / "heldout")
    wm = checkpoint.export(bimanual[0] / "run", tmp_path / "wm")
    out = tmp_path / "out"
    args = ("--episodes", "1", "--calibration-episodes", "0")
    assert _sweep(ic, wm, out, *args, policies=("hold",)) == 0
    saved = json.loads((out / "sweep.json").read_text())
    assert saved["world_model_sha256"] == checkpoint.identity(wm)["sha256"] and saved["world_model_step"] is None
    assert saved["scorer_sha256"] == engine.spec_sha256("test_ic_sweep:score")
    assert set(saved["policies_sha256"]) == {"hold"}
    capsys.readouterr()
    cfg, stats, params = checkpoint.load(wm)  # another model at the same path
    checkpoint.save(wm, cfg, stats, jax.tree.map(lambda x: np.asarray(x) * 0.5, params))
    assert _sweep(ic, wm, out, *args, policies=("hold",)) == 2
    err = _error(capsys)
    assert f"sha256 {saved['world_model_sha256'][:16]}" in err
    assert f"sha256 {checkpoint.identity(wm)['sha256'][:16]}" in err
    assert json.loads((out / "sweep.json").read_text()) == saved  # nothing rewritten

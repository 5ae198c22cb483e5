"""Data from outside stays outside (issue 66): a FIFO, a link out of a store or an oversized header is one line
before anything is read or allocated; a store's records are refused when they repeat a rollout or carry a negative
U; P(best) splits a tie instead of giving each tied policy every draw; a refused old spelling gives back the command
the report really takes. The command-level faults are the fault battery's (tests/test_fault_battery.py)."""
import os
import zipfile

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sc3_jax.core import atomic, validate
from sc3_jax.cli import main
from sc3_jax.core.errors import UserError
from sc3_jax.evaluation.results import check_records
from sc3_jax.stats.rank_first import p_first


@given(scores=st.lists(st.lists(st.sampled_from([0.0, 0.25, 0.5, 1.0, np.nan]), min_size=2, max_size=2),
                       min_size=1, max_size=30))
@settings(max_examples=60, deadline=None)
def test_p_best_sums_to_the_share_of_scored_draws_and_splits_ties(scores):
    s = np.array(scores)
    p = p_first(s)
    scored = (~np.isnan(s)).any(-1).mean()
    assert np.isclose(p.sum(), scored)  # never 200% between two policies
    both = ~np.isnan(s).any(-1)
    if both.all() and (s[:, 0] == s[:, 1]).all():  # tied in every draw: an even split
        np.testing.assert_allclose(p, [0.5, 0.5])
    assert ((p >= 0) & (p <= 1)).all()


def test_two_policies_at_zero_each_rank_first_in_half_the_draws_and_are_said_tied():
    from sc3_jax.evaluation import intervals, report_episodes

    point, draws = np.zeros((1, 2, 1)), np.zeros((50, 2, 1))
    rows = intervals.ranking(["a", "b"], ["success"], "success", point, draws, np.ones((2, 4)))
    assert [r["p_best"] for r in rows] == [0.5, 0.5] and [r["rank"] for r in rows] == [1, 1]
    t = {"policies": rows, "ranked_by": "success", "conditions": {"evaluation": 4}, "real": None, "warnings": []}
    said = " ".join(report_episodes.summary(t))
    assert "a and b tie for first" in said and "100%" not in said, said


def _record(i, **kw):
    return {"id": f"p/{i}_online", "mode": "online", "policy": "p", "seed": i, "outcomes": {"success": False},
            "u": [0.1, 0.2], "u_raw": [0.1, 0.2], **kw}


def test_a_rollout_recorded_twice_is_one_line_naming_both_records(tmp_path):
    with pytest.raises(UserError, match=r"record 3 \('p/0_online'\): the same rollout as record 1") as e:
        check_records([_record(0), _record(1), _record(0, outcomes={"success": True})], tmp_path / "r.jsonl", "fix")
    assert "\n" not in str(e.value)


@given(u=st.floats(-1e6, -1e-9))
@settings(max_examples=10, deadline=None)
def test_a_negative_u_is_refused_naming_the_record(u):
    with pytest.raises(UserError, match=r"record 1 .*u must be a list of finite numbers >= 0"):
        check_records([_record(0, u=[0.1, u])], "r.jsonl", "fix")
    check_records([_record(0, u=[0.0, 0.1])], "r.jsonl", "fix")  # zero is a U: the door is not shut on it


def test_a_fifo_in_place_of_a_json_or_npz_file_is_one_line_never_a_hang(tmp_path):
    fifo = tmp_path / "results.jsonl"
    os.mkfifo(fifo)
    for read in (lambda: atomic.read_json(fifo), lambda: atomic.read_jsonl(fifo, "a record", "fix"),
                 lambda: atomic.open_npz(fifo).__enter__(), lambda: validate.load_npy(fifo, "fix")):
        with pytest.raises(UserError, match="not a regular file"):
            read()


@pytest.mark.parametrize("rows", [10**11, 10**6, 7])
def test_an_array_header_claiming_more_than_its_file_is_refused_before_allocating(tmp_path, rows):
    x = np.arange(12, dtype=np.float32).reshape(6, 2)
    head = {"descr": "<f4", "fortran_order": False, "shape": (rows, 2)}
    p = tmp_path / "a.npy"
    with open(p, "wb") as f:
        np.lib.format.write_array_header_1_0(f, head)
        f.write(x.tobytes())
    with pytest.raises(UserError, match=r"its header declares float32 \[%d, 2\]" % rows):
        validate.load_npy(p, "fix")
    z = tmp_path / "a.npz"
    with zipfile.ZipFile(z, "w") as zf:
        zf.writestr("frames.npy", p.read_bytes())
    with pytest.raises(UserError, match="array frames.npy declares float32"), atomic.open_npz(z, "fix"):
        pass
    np.save(p, x)  # the honest file reads
    np.testing.assert_array_equal(validate.load_npy(p, "fix"), x)


def test_a_file_linked_out_of_its_store_is_refused_and_one_inside_reads(tmp_path):
    store, other = tmp_path / "store", tmp_path / "other"
    store.mkdir()
    other.mkdir()
    np.save(other / "a.npy", np.zeros(3))
    (store / "out.npy").symlink_to(other / "a.npy")
    with pytest.raises(UserError, match="a link to a file outside"):
        validate.load_npy(store / "out.npy", "fix", inside=store)
    np.save(store / "a.npy", np.zeros(3))
    (store / "in.npy").symlink_to(store / "a.npy")
    assert validate.load_npy(store / "in.npy", "fix", inside=store).shape == (3,)


def test_report_with_an_option_it_does_not_take_is_one_line_naming_it(capsys):
    assert main(["report", "--store", "runs/s", "--draws", "10"]) == 2
    err = capsys.readouterr().err.strip()
    assert "unknown option --store" in err and "sc3 report --help" in err and "\n" not in err, err


def test_a_report_directory_that_is_a_link_is_refused_and_its_target_kept(tmp_path):
    victim = tmp_path / "victim"
    victim.mkdir()
    (victim / "report.md").write_text("mine")
    (tmp_path / "report").symlink_to(victim)
    with pytest.raises(UserError, match="a symbolic link"):
        validate.out_dir(tmp_path / "report", "--out", links=False)
    assert (victim / "report.md").read_text() == "mine"


@pytest.mark.parametrize("where", ["file", "under"])
def test_an_out_that_is_a_file_or_under_one_is_refused(tmp_path, where):
    f = tmp_path / "f"
    f.write_text("x")
    with pytest.raises(UserError, match="not a directory"):
        validate.out_dir(f if where == "file" else f / "x" / "y", "--out")
    assert validate.out_dir(tmp_path / "new" / "dir", "--out") == tmp_path / "new" / "dir"


def test_every_named_config_passes_the_training_door():
    import dataclasses

    from sc3_jax.core.config import available_configs, load_config

    for name in available_configs():
        cfg = load_config(name)
        validate.train_config(dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, workdir="runs/x")))


def test_rollout_and_diagnose_read_benchmark_none_alike():
    from sc3_jax.commands import diagnose, rollout

    bm = rollout.benchmark_of("none")
    assert (bm.outcome_scorer, dict(bm.measures), bm.named_policy) == (None, {}, None)
    assert diagnose.benchmark_hooks("none") == (bm.outcome_scorer, dict(bm.measures))
    with pytest.raises(UserError, match="unknown benchmark"):
        rollout.benchmark_of("nonesuch")


def test_an_edited_policy_names_or_a_foreign_record_is_refused_naming_the_store(tmp_path):
    from sc3_jax.evaluation.report_episodes import check_against_sweep

    cfg = {"policies": ["a=zero", "b"], "policy_names": ["a", "b"], "conditions": ["e0", "e1"]}
    recs = [{"id": "a/0_online", "policy": "a", "seed": 0, "episode": "e0"}]
    check_against_sweep(cfg, recs, tmp_path)
    with pytest.raises(UserError, match=r"policy_names \['c', 'b'\] are not the names its policies give"):
        check_against_sweep(dict(cfg, policy_names=["c", "b"]), recs, tmp_path)
    with pytest.raises(UserError, match=r"record 1 \('a/0_online'\): episode 'e9' is not the sweep's condition 0"):
        check_against_sweep(cfg, [dict(recs[0], episode="e9")], tmp_path)
    with pytest.raises(UserError, match=r"condition 5 is none of the sweep's 2"):
        check_against_sweep(cfg, [dict(recs[0], seed=5)], tmp_path)


def test_a_sweep_whose_out_is_a_file_is_refused_before_its_first_rollout(tmp_path):
    from sc3_jax.evaluation.results import ResultsStore

    (tmp_path / "f").write_text("x")
    with pytest.raises(UserError, match="--out .*is under .*a file, not a directory"):
        ResultsStore(tmp_path / "f" / "sweep", {"modes": ["online"]})

import pytest

from sc3_jax.cli import main


def test_train_without_data_is_a_clear_error(tmp_path, capsys):
    rc = main(["train", "--config", "tiny", "--data", str(tmp_path / "none"),
               "--train.workdir", str(tmp_path / "w")])
    err = capsys.readouterr().err
    assert rc == 2 and "no dataset.json" in err and "sc3 demo" in err
    assert not (tmp_path / "w" / "checkpoints").exists()


def test_unknown_command_and_help(capsys):
    assert main(["nope"]) == 2
    assert "unknown command" in capsys.readouterr().err
    assert main([]) == 0 and "commands:" in capsys.readouterr().out


def test_configs_lists_parameter_counts(capsys):
    assert main(["configs"]) == 0
    out = capsys.readouterr().out
    paper = next(line for line in out.splitlines() if line.strip().startswith("paper "))
    assert 1800 < float(paper.split()[1].rstrip("M")) < 2400
    assert "ablation_no_id" in out and "tiny" in out


def test_a_sweep_names_its_job_and_options_without_one_get_the_job_they_imply(capsys):
    """`sc3 sweep bench` and `sc3 sweep episodes` are the two jobs; options without a job are refused in one line
    that gives the command back with the job the options imply, so nothing the user typed is lost."""
    assert main(["sweep", "--help"]) == 0
    out = capsys.readouterr().out
    assert "bench" in out and "episodes" in out
    assert main(["sweep", "--out", "x", "--episodes", "3"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "`sc3 sweep bench --out x --episodes 3`" in err
    assert main(["sweep", "--data", "ic", "--out", "y"]) == 2
    assert "`sc3 sweep episodes --data ic --out y`" in capsys.readouterr().err
    with pytest.raises(SystemExit):  # a usage error, as every command's: its required options are named
        main(["sweep", "episodes", "--out", "y"])
    assert "--data" in capsys.readouterr().err

from sc3_jax.cli import main


def test_train_without_data_is_a_clear_error(tmp_path, capsys):
    rc = main(["train", "--config", "tiny", "--data.path", str(tmp_path / "none"),
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

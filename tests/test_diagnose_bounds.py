"""``sc3 diagnose``'s options are checked at the door (issue 66): a count below 1, a non-finite amount, an output
path under a file are one UserError line naming the flag, before the store is opened or a rollout runs."""
import pytest
from test_diagnose import _copy_last_model

from sc3_jax.cli import main as cli
from sc3_jax.evaluation import diagnose as dg


@pytest.fixture(scope="module")
def model(tmp_path_factory):
    return _copy_last_model(tmp_path_factory.mktemp("bounds"))


@pytest.mark.parametrize("flags, says", [
    (["--episodes", "0"], "--episodes 0: at least 1 held-out episode"),
    (["--batch", "0"], "--batch 0: at least 1 rollout"),
    (["--cf-starts", "-1"], "--cf-starts -1: at least 1 counterfactual start"),
    (["--max-seconds", "nan"], "--max-seconds nan: a positive number of seconds"),
    (["--cf-fraction", "0"], "--cf-fraction 0.0: a positive fraction"),
    (["--horizons", "1", "inf"], "--horizons inf: positive numbers of seconds"),
    (["--filmstrips", "{file}"], "--filmstrips {file}: is a file, not a folder"),
    (["--out", "{file}/x.json"], "--out {file}/x.json: {file} is a file, not a folder"),
    (["--out", "{file}/x.json", "--filmstrips", "{dir}/strips"], "--out {file}/x.json: {file} is a file"),
    (["--out", "{dir}"], "--out {dir}: is a folder"),
    # past what any store or machine holds (a day of seconds overflowed, a huge batch asked numpy for 42 TiB)
    (["--max-seconds", "1e308"], "--max-seconds 1e+308: at most 86400 (seconds, a day)"),
    (["--batch", "10000000000"], "--batch 10000000000: at most 4096"),
    (["--episodes", "10000000000"], "--episodes 10000000000: at most 1000000"),
    (["--cf-starts", "10000000000"], "--cf-starts 10000000000: at most 10000"),
    (["--cf-fraction", "1e308"], "--cf-fraction 1e+308: at most 100"),
    (["--filmstrips", "{link}"], "--filmstrips {link}: a symbolic link"),
])
def test_a_bad_option_is_one_line_before_any_work(model, tmp_path, capsys, monkeypatch, flags, says):
    f = tmp_path / "a_file"
    f.write_text("x")
    (tmp_path / "elsewhere").mkdir()
    (tmp_path / "link").symlink_to(tmp_path / "elsewhere", target_is_directory=True)
    fill = lambda x: x.format(file=f, dir=tmp_path, link=tmp_path / "link")  # noqa: E731
    monkeypatch.setattr(dg, "diagnose", lambda *a, **k: pytest.fail("the diagnosis ran"))
    # the store does not exist: the option is refused before anything reads it
    rc = cli(["diagnose", "--world-model", str(model), "--data", str(tmp_path / "no_store"), "--no-progress"]
             + [fill(x) for x in flags])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and fill(says) in err[0], err


def test_good_options_reach_the_diagnosis(model, tmp_path, capsys, monkeypatch):
    called = {}

    def fake(wm, data, dc, **kw):
        called.update(dc=dc, locators=kw["locators"])
        raise SystemExit(0)
    monkeypatch.setattr(dg, "diagnose", fake)
    with pytest.raises(SystemExit):
        cli(["diagnose", "--world-model", str(model), "--data", str(tmp_path), "--episodes", "1", "--max-seconds",
             "2.5", "--cf-fraction", "0.25", "--benchmark", "so101", "--out", str(tmp_path / "new" / "d.json")])
    assert called["dc"].cf_fraction == 0.25 and called["dc"].max_seconds == 2.5 and called["dc"].episodes == 1
    assert set(called["locators"].objects) == {"block"} and called["locators"].moves["dx"] == "ee_x"


def test_diagnose_without_a_benchmark_reads_the_generic_measures_alone(model, tmp_path, monkeypatch):
    """No command defaults to a benchmark: without --benchmark the passes get no outcome scorer, no scene measure
    and no locators (the arm by the median rule), whatever robot the model is of."""
    called = {}

    def fake(wm, data, dc, **kw):
        called.update(kw)
        raise SystemExit(0)
    monkeypatch.setattr(dg, "diagnose", fake)
    with pytest.raises(SystemExit):
        cli(["diagnose", "--world-model", str(model), "--data", str(tmp_path), "--no-progress"])
    assert called["scorer_for"] is None and called["scene"] == {} and called["locators"] is None

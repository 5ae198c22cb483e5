"""A store carries its own truth (issue 76): the real outcomes a sweep was given are kept in its store (real.json,
``labels.keep``), and `sc3 report STORE` reads them from there alone (``labels.kept``) -- never a path resolved
against the current directory, where anyone may have put a file of that name: from a directory holding an all-true
``sweep/real.csv`` the report once showed every policy's real success as 1.000, exit 0. Each archived store under
docs/stores reports its published numbers from anywhere, with no option."""
import gzip
import json
import re
import shutil
from pathlib import Path

import pytest

from sc3_jax.cli import main
from sc3_jax.core.errors import UserError
from sc3_jax.evaluation import labels, report, report_episodes
from test_atomic import snapshot

STORES = Path(__file__).parent.parent / "docs" / "stores"
ARCHIVES = ["so101_sweep36", "so101_v3_sweep36", "so101_v7_sweep36"]  # every archive with real outcomes
POLICIES = ["so_full", "so_aim1", "so_aim2", "so_place", "so_noise2", "so_noise3", "so_shaky", "so_small", "act",
            "act20"]


def plant(path: Path) -> Path:
    """An all-true real.csv at ``path``: every policy of the archives succeeds in every episode."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("policy,episode,success\n" + "".join(f"{p},seed{20000000 + i},true\n" for p in POLICIES
                                                         for i in range(36)))
    return path


@pytest.fixture
def elsewhere(tmp_path, monkeypatch) -> Path:
    """An unrelated current directory holding an all-true ``sweep/real.csv`` (the path so101_sweep36's sweep was
    given), as the current directory."""
    cwd = tmp_path / "elsewhere"
    plant(cwd / "sweep" / "real.csv")
    monkeypatch.chdir(cwd)
    return cwd


def _dumps(x) -> str:
    return json.dumps(x, sort_keys=True)  # NaN == NaN as text: an undefined r is published as NaN


def _rows(md: str, heading: str) -> list[str]:
    """The table rows under the markdown heading that starts with ``heading``."""
    part = md.split("\n## " + heading, 1)[1].split("\n## ", 1)[0]
    return [x for x in part.splitlines() if x.startswith("| ")]


def _published_v7(t: dict) -> None:  # its report/report.json, as the sweep wrote it
    pub = json.loads((STORES / "so101_v7_sweep36" / "report" / "report.json").read_text())
    assert _dumps(t["policies"]) == _dumps(pub["policies"])
    mine = lambda r: {k: v for k, v in r.items() if k not in ("kept", "sources")}  # noqa: E731  (where: below)
    assert _dumps(mine(t["real"])) == _dumps(mine(pub["real"]))


def _published_v3(t: dict) -> None:  # its report.md, as the sweep wrote it (docs/results.md quotes it)
    pub, md = (STORES / "so101_v3_sweep36" / "report.md").read_text(), report.markdown(t)
    line = next(x for x in pub.splitlines() if x.startswith("against the real outcomes"))
    assert line == "against the real outcomes (288 episodes): r 0.724 [0.152, 0.961], MMRV 0.194 [0.049, 0.469]; " \
                   "policy-blind guess: r n/a, MMRV 0.278 [0.240, 0.316]; paired difference to it: r n/a, MMRV " \
                   "-0.083 [-0.236, 0.174]; real vs real (split-half ceiling): r 0.966 [0.873, 0.996]"
    assert line in report_episodes.summary(t)
    # (its ranking table's P(best) is from before ties for first were split: not the real outcomes' numbers)
    for heading in ("Real outcomes", "Faithfulness", "Per criterion"):
        assert _rows(md, heading) == _rows(pub, heading), heading


def _published_sweep36(t: dict) -> None:  # docs/history/results-2026-11.md, "SO-101: the sweep, 9 policies x 36"
    f = t["real"]["faithfulness"]
    cell = lambda x, d: [round(x[k], d) for k in ("value", "lo", "hi")]  # noqa: E731
    assert cell(f["online"]["pearson"], 2) == [-0.05, -0.70, 0.52]
    assert cell(f["online"]["mmrv"], 3) == [0.315, 0.231, 0.562]
    assert cell(f["policy_blind"]["mmrv"], 3) == [0.201, 0.167, 0.238]
    assert cell(f["online"]["vs_floor"]["mmrv"], 3) == [0.114, 0.052, 0.349]
    assert cell(f["ceiling"]["pearson"], 2) == [0.93, 0.77, 0.99]
    real = {p: round(v["rates"]["success"]["value"], 2) for p, v in t["real"]["policies"].items()}
    assert real == {"so_full": 0.53, "so_aim1": 0.50, "so_aim2": 0.47, "so_place": 0.28, "so_noise2": 0.0,
                    "so_noise3": 0.03, "so_shaky": 0.0, "so_small": 0.0, "act20": 0.0}


PUBLISHED = {"so101_sweep36": _published_sweep36, "so101_v3_sweep36": _published_v3,
             "so101_v7_sweep36": _published_v7}


@pytest.mark.parametrize("name", ARCHIVES)
def test_each_archive_reports_its_published_numbers_from_anywhere_with_no_option(name, elsewhere, monkeypatch):
    """From a directory holding an all-true sweep/real.csv: the store's own real outcomes, no path read."""
    def no_path(sources):
        raise AssertionError(f"read real outcomes from {sources}, not the store")
    monkeypatch.setattr(labels, "read", no_path)
    t = report.compute(STORES / name)
    assert t["real"]["kept"] and len(t["real"]["policies"]) >= 8
    assert t["real"]["sources"] == json.loads((STORES / name / "real.json").read_text())["given"]  # as typed there
    PUBLISHED[name](t)


def test_sc3_report_on_an_archive_writes_only_its_out_and_says_its_numbers(elsewhere, tmp_path, capsys):
    """The command as a user types it, from the planted directory: exit 0, the published r / MMRV, nothing read
    from or written to the current directory or the store."""
    store = STORES / "so101_v7_sweep36"
    before, kept = snapshot(elsewhere), snapshot(store)
    assert main(["report", str(store), "--out", str(tmp_path / "rep"), "--videos", "0"]) == 0
    assert snapshot(elsewhere) == before and snapshot(store) == kept
    _published_v7(json.loads((tmp_path / "rep" / "report.json").read_text()))
    said = capsys.readouterr().out
    assert "r 0.536 [0.152, 0.759], MMRV 0.333 [0.148, 0.441]" in said
    assert "(as the store keeps them, real.json)" in (tmp_path / "rep" / "report.md").read_text()


def _copy(name: str, dest: Path) -> Path:
    """A store with only what a sweep of held-out episodes reads: sweep.json, its records, real.csv."""
    dest.mkdir(parents=True)
    for f in ("sweep.json", "real.csv"):
        shutil.copy(STORES / name / f, dest / f)
    (dest / "results.jsonl").write_bytes(gzip.decompress((STORES / name / "results.jsonl.gz").read_bytes()))
    return dest


def _old_real_json(store: Path, *paths: str) -> None:
    """real.json as sweeps wrote it before the outcomes were kept: only the paths given, as typed."""
    (store / "real.json").write_text(json.dumps({"real": list(paths)}))


@pytest.mark.parametrize("name", ["so101_sweep36", "so101_v3_sweep36"])
def test_a_store_from_before_reads_its_own_real_csv_not_the_current_directorys(name, elsewhere, tmp_path):
    """Its real.json as the sweep wrote it (so101_sweep36: "sweep/real.csv", the sweep's --out "sweep"; v3: an
    absolute path under its --out on the sweep machine): the path under the sweep's own out is that file of the
    store, whatever the current directory holds under that name."""
    store = _copy(name, tmp_path / "copy")
    recorded = json.loads((STORES / name / "real.json").read_text())["given"]
    _old_real_json(store, *recorded)
    t = report_episodes.compute(store)
    assert t["real"]["sources"] == recorded
    PUBLISHED[name](t)


def test_a_recorded_path_outside_the_store_is_refused_in_one_line(elsewhere, tmp_path, capsys):
    """An absolute planted file, and the relative one a store moved from its sweep's directory names: refused, not
    read, and the report not written."""
    store = _copy("so101_sweep36", tmp_path / "copy")
    for path in (str(plant(tmp_path / "planted" / "real.csv")), "../sweep/real.csv"):
        _old_real_json(store, path)
        with pytest.raises(UserError, match="outside the store") as e:
            report_episodes.compute(store)
        assert path in str(e.value) and "\n" not in str(e.value)
        assert main(["report", str(store), "--out", str(tmp_path / "rep"), "--videos", "0"]) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("sc3 report: error: ") and "\n" not in err and "--real PATH" in err, err
        assert not (tmp_path / "rep").exists()


def test_a_kept_store_never_reads_the_paths_it_was_given(elsewhere, tmp_path, monkeypatch):
    """real.json naming the planted files (relative and absolute) as given: a record, never read; only --real typed
    reads a path."""
    store = _copy("so101_v7_sweep36", tmp_path / "copy")
    kept = json.loads((STORES / "so101_v7_sweep36" / "real.json").read_text())
    planted = str(plant(tmp_path / "planted.csv"))
    (store / "real.json").write_text(json.dumps({**kept, "given": ["sweep/real.csv", planted]}))
    (store / "real.csv").write_text("policy,success\nso_full,maybe\n")  # the store's CSV is not read either
    _published_v7(report_episodes.compute(store))
    typed = report_episodes.compute(store, real=("sweep/real.csv",))  # what the user types is what is read
    rates = {v["rates"]["success"]["value"] for v in typed["real"]["policies"].values()}
    assert not typed["real"]["kept"] and rates == {1.0}


@pytest.mark.parametrize("fault, says", [
    (lambda d: d.update(format=3), "format 3"),
    (lambda d: d.update(episodes=[]), "episodes is"),
    (lambda d: d["episodes"][5].update(outcomes={"success": "true"}), "episode 5: outcomes"),
    (lambda d: d["episodes"][0].update(policy=None), "episode 0: policy None"),
    (lambda d: d.update(given="real.csv"), "given is"),
    (lambda d: d.pop("format") and d.update(real=[3]), "real is"),
])
def test_a_damaged_real_json_is_one_line(tmp_path, fault, says):
    store = _copy("so101_v7_sweep36", tmp_path / "copy")
    d = json.loads((STORES / "so101_v7_sweep36" / "real.json").read_text())
    fault(d)
    (store / "real.json").write_text(json.dumps(d))
    with pytest.raises(UserError, match=re.escape(says)) as e:
        report_episodes.compute(store)
    assert "\n" not in str(e.value) and "real.json" in str(e.value)


def test_a_real_json_linked_out_of_the_store_is_refused(tmp_path):
    store = _copy("so101_v7_sweep36", tmp_path / "copy")
    other = tmp_path / "other.json"
    shutil.copy(STORES / "so101_v7_sweep36" / "real.json", other)
    (store / "real.json").symlink_to(other)
    with pytest.raises(UserError, match="outside"):
        report_episodes.compute(store)


def test_keep_and_kept_round_trip(tmp_path):
    """What a sweep keeps is what its report reads: the episodes in order (the bootstrap's draws follow it)."""
    eps = [labels.RealEpisode("a", "x.csv:e1", {"success": True, "moved": False}),
           labels.RealEpisode("b", "x.csv:e2", {"success": False})]
    labels.keep(tmp_path / "real.json", ("a=x.csv",), eps)
    assert labels.kept(tmp_path / "real.json", None) == (["a=x.csv"], eps)

"""The evaluation sweep end to end on a tiny random world model: results store, resume after SIGKILL, report numbers
recomputable from the store, blinded annotation round trip."""
import csv
import dataclasses
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import jax
import numpy as np
import pytest

import sc3_jax.benchmarks.bussing  # noqa: F401  (picks the GL backend before mujoco is imported)
from sc3_jax.model import checkpoint
from sc3_jax.rollout import rollout
from sc3_jax.train import train
from sc3_jax.core.config import load_config, replace
from sc3_jax.data.norm_stats import NormStats
from sc3_jax.evaluation import engine, report, report_bench_render
from sc3_jax.evaluation.report_html import ci
from sc3_jax.measures import metrics
from sc3_jax.benchmarks.bussing import annotation, perception, sweep
from sc3_jax.core.errors import UserError
from sc3_jax.evaluation.results import EVAL_MODES, ResultsStore, rollout_id, seed_blocks
from sc3_jax.evaluation.scorers import RolloutView
from sc3_jax.benchmarks.bussing.scorers import HumanScorer
from sc3_jax.benchmarks.bussing.tasks import CRITERIA, TASKS

def _one_per_split():
    """The zoo's first policy of each task (names come from the zoo, which may change)."""
    from sc3_jax.benchmarks.bussing.zoo import ZOO, zoo_names
    return tuple(next(n for n in zoo_names() if ZOO[n].task == task) for task in ("bussing", "reverse"))


POLICIES = _one_per_split()


def tiny_world_model(root):
    cfg = load_config("bussing_sim")
    cfg = replace(cfg, model=dict(dim=32, depth=1, num_heads=2, num_kv_heads=1, head_dim=16, mlp_dim=64,
                                  rope_axes_dim=(4, 2, 2)), sample=dict(steps=2),
                  data=dict(fps=20.0, state_dim=0))  # its data's facts, as `sc3 train` records them
    params = train.init_state(cfg)["params"]
    stats = NormStats(np.zeros(7, np.float32), np.full(7, 0.02, np.float32))
    return checkpoint.save(root / "wm", cfg, stats, jax.device_get(params), np.float32)


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    root = tmp_path_factory.mktemp("sweep")
    wm = tiny_world_model(root)
    perception.save(root / "perception.npz", perception.init(jax.random.key(1)))
    cfg = sweep.SweepConfig(out=str(root / "full"), world_model=str(wm), perception=str(root / "perception.npz"),
                            policies=POLICIES, episodes=2, episode_seconds=1.6, batch=2, progress=False,
                            taus=(math.inf, 1.0, 0.5), calibration_episodes=1, ceiling_episodes=1, modes=EVAL_MODES,
                            workers=1)
    sweep.run_sweep(cfg)
    return root, cfg


def test_sweep_writes_every_rollout(setup):
    root, cfg = setup
    recs = ResultsStore(cfg.out).records()
    # per policy: real on 2 evaluation + 1 calibration + 1 ceiling seed, offline on 2, online on 2 + 1 calibration
    count = lambda m: sum(r["mode"] == m for r in recs)  # noqa: E731
    assert (count("real"), count("offline"), count("online")) == (len(POLICIES) * 4, len(POLICIES) * 2,
                                                                 len(POLICIES) * 3)
    blocks = seed_blocks(cfg)
    assert {r["seed"] for r in recs if r["mode"] == "online"} == set(blocks["evaluation"] + blocks["calibration"])
    assert {r["seed"] for r in recs if r["mode"] == "offline"} == set(blocks["evaluation"])
    real = [r for r in recs if r["mode"] == "real"]
    # degraded copies are read on the calibration conditions' real rollouts only (SweepConfig.degradations)
    degraded = {r["seed"] for r in real if "perception_degraded" in r}
    assert degraded == set(blocks["calibration"])
    assert all(set(r["perception_degraded"]) == {"blur", "patch_noise", "colour_shift"} for r in real
               if "perception_degraded" in r)
    assert {r["split"] for r in recs} == {"in_distribution", "out_of_distribution"}
    for r in recs:
        assert len(r["objects"]) == 3 and all(set(CRITERIA) <= set(o) for o in r["objects"])
        arrays = ResultsStore(cfg.out).load_arrays(r["id"])
        if r["mode"] == "real":
            assert arrays["frames"].shape[:2] == (3, r["length"]) and r["length"] <= 32
        else:
            assert len(r["u"]) == r["num_chunks"] == 2
            assert arrays["frames"].shape == (3, 1 + 2 * 8, 64, 64, 3)
        if r["mode"] == "online":
            assert len(r["objects_by_cut"]) == 3 and r["objects_by_cut"][-1] == r["objects"]
        if r["mode"] == "offline":
            assert len(r["psnr_view"]) == 3 and all(np.isfinite(r["psnr_view"]))


def test_validate_rescores_real_rollouts_as_the_sweep_scored_them(setup):
    from sc3_jax.benchmarks.bussing.perception_train import validate
    from sc3_jax.evaluation.scorers import agreement
    root, cfg = setup
    real = [r for r in ResultsStore(cfg.out).records() if r["mode"] == "real"]
    robot = checkpoint.read_robot(cfg.world_model)
    stride = rollout.make_spec(checkpoint.read_config(cfg.world_model), robot.fps,
                               action_space=robot.action_space).stride
    got = validate(cfg.out, perception.load(root / "perception.npz"), score_stride=stride)
    truth = [r["objects"] for r in real]
    assert got["clean"] == agreement([r["perception"] for r in real], truth)
    # the sweep read degraded copies of the calibration rollouts only: rescored, they are what it recorded
    from sc3_jax.evaluation.scorers import RolloutView
    from sc3_jax.benchmarks.bussing.scorers import PerceptionScorer
    from sc3_jax.benchmarks.bussing.tasks import make_initial_condition
    scorer = PerceptionScorer(perception.load(root / "perception.npz"))
    degraded = [r for r in real if "perception_degraded" in r]
    # validate reads every rollout clean and degraded (and names the majority-guess floor beside them)
    assert degraded and set(got) - {"majority_guess"} == {"clean"} | set(degraded[0]["perception_degraded"])
    for r in degraded:
        ic = make_initial_condition(r["seed"], r["task"])
        view = RolloutView(r["id"], ResultsStore(cfg.out).load_arrays(r["id"])["frames"], ic.objects,
                           ic.destinations())
        assert scorer.score_real(view, r["seed"], stride, True)[1] == r["perception_degraded"]


def test_report_shows_the_world_models_diagnose_gates(setup):
    from sc3_jax.evaluation import diagnose
    root, cfg = setup
    gate_rows = lambda t: [x[2] for x in report_bench_render.tables(t)  # noqa: E731
                           if x[0].startswith("World-model checkpoint gates")]
    t = report.compute(cfg.out, draws=20)
    assert t["diagnose"]["gates"] is None and gate_rows(t)[0][0][0].startswith("not diagnosed")
    path = Path(cfg.world_model) / "diagnose.json"
    gates = [{"gate": "g1", "value": 3.5, "threshold": 3.0, "pass": True, "note": ""},
             {"gate": "g2", "value": float("nan"), "threshold": 0.75, "pass": False, "note": ""}]
    diagnose.save_result({"data": "heldout", "episodes": [0, 1], "gates": gates}, path)
    try:
        t = report.compute(cfg.out, draws=20)
        assert [g["gate"] for g in t["diagnose"]["gates"]] == ["g1", "g2"] and t["diagnose"]["episodes"] == 2
        assert gate_rows(t) == [[["g1", "3.50", "3", "PASS"], ["g2", "n/a", "0.75", "FAIL"]]]
    finally:
        path.unlink()


def test_the_report_answers_first_in_a_real_browser_and_every_image_loads(setup, tmp_path):
    import browser
    _, cfg = setup
    report.render(cfg.out, tmp_path / "rep", videos=1, draws=50)
    dom = browser.dump_dom(tmp_path / "rep" / "report.html", tmp_path / "profile")
    browser.answers_first(dom)
    shown = {i.split('src="')[1].split('"')[0] for i in browser.images(dom)}
    assert {"correlation.png", "u_chunk.png"} <= shown and sum(s.startswith("filmstrip_") for s in shown) == 2
    assert '<details><summary>Faithfulness, end to end</summary>' in dom and "Videos" in dom
    # the check can fail: a page whose image is missing is caught
    (tmp_path / "rep" / "correlation.png").unlink()
    with pytest.raises(AssertionError, match="did not load"):
        browser.answers_first(browser.dump_dom(tmp_path / "rep" / "report.html", tmp_path / "profile"))


def test_no_path_of_this_machine_in_the_report(setup, tmp_path):
    import re

    import sc3_jax
    root, cfg = setup
    report.render(cfg.out, tmp_path / "rep", videos=0, draws=20)
    for name in ("report.md", "report.html"):
        text = (tmp_path / "rep" / name).read_text()
        for path in (str(root), str(tmp_path), str(Path.home()), str(Path(sc3_jax.__file__).parent), os.getcwd()):
            assert path not in text, (name, path)
        assert not re.search(r"(?<![\w.])/(tmp|root|home|work|usr)/", text), name


def test_sweep_refuses_a_different_config_in_the_same_store(setup):
    _, cfg = setup
    with pytest.raises(ValueError, match="different sweep"):
        sweep.run_sweep(dataclasses.replace(cfg, episodes=3))


def test_store_written_before_a_field_existed_resumes_at_its_default(tmp_path):
    """A store written before a SweepConfig field was added (absent from its sweep.json) resumes when the field is
    at its neutral None, and refuses any other value."""
    for name, new, ok in (("a", None, True), ("b", 2, False)):
        cfg = sweep.SweepConfig(out=str(tmp_path / name))
        old = cfg.to_json()
        del old["inverse_steps"]
        ResultsStore(cfg.out, old).append([{"id": "p/0_real", "mode": "real"}])  # a store holding results
        if ok:
            ResultsStore(cfg.out, dataclasses.replace(cfg, inverse_steps=new).to_json())  # resumes
        else:
            with pytest.raises(ValueError, match="inverse_steps"):
                ResultsStore(cfg.out, dataclasses.replace(cfg, inverse_steps=new).to_json())


def test_rescore_reproduces_the_sweep_and_guards_the_store(setup, tmp_path):
    """sc3 rescore with the sweep's own weights reproduces every record; with other weights the store changes, its
    sweep.json names them, and resuming it with the old weights is refused until it is re-scored back."""
    import shutil

    from sc3_jax.benchmarks.bussing import rescore
    root, cfg = setup
    out = tmp_path / "store"
    shutil.copytree(cfg.out, out)
    before = ResultsStore(out).records()
    assert all("score_stride" in r for r in before if r["mode"] == "real")
    assert rescore.rescore(out, cfg.perception, progress=False) == {"real": 0, "offline": 0, "online": 0}
    assert ResultsStore(out).records() == before
    other = tmp_path / "other.npz"
    perception.save(other, perception.init(jax.random.key(2)))
    # its imagined rollouts read the gripper with the old weights: the store must be told which, and checks them
    with pytest.raises(ValueError, match="--state-reader"):
        rescore.rescore(out, other, progress=False)
    with pytest.raises(ValueError, match="not the weights"):
        rescore.rescore(out, other, state_reader=other, progress=False)
    assert ResultsStore(out).records() == before  # refused before anything was written
    changed = rescore.rescore(out, other, state_reader=cfg.perception, progress=False)
    assert sum(changed.values()) > 0 and ResultsStore(out).records() != before
    stored = ResultsStore(out).config()
    assert stored["perception"] == str(other) and stored["perception_sha256"] == rescore.weights_digest(other)
    assert stored["state_reader"] == cfg.perception
    with pytest.raises(ValueError, match="rescore"):
        sweep.run_sweep(dataclasses.replace(cfg, out=str(out)))
    # physics, U and PSNR are untouched
    for a, b in zip(before, ResultsStore(out).records()):
        assert a["objects"] == b["objects"] or a["mode"] != "real"
        assert a.get("u") == b.get("u") and a.get("psnr_view") == b.get("psnr_view")


def test_report_numbers_come_from_compute(setup, tmp_path):
    _, cfg = setup
    md = report.render(cfg.out, tmp_path / "rep", videos=1)
    t = report.compute(cfg.out)
    assert json.loads((tmp_path / "rep" / "report.json").read_text()) == json.loads(json.dumps(t))
    # recompute the main table independently from the raw records
    evaluation = set(seed_blocks(cfg)["evaluation"])
    recs = [r for r in ResultsStore(cfg.out).records() if r["seed"] in evaluation]
    rows = lambda mode: [{"policy": r["policy"], "split": r["split"], "episode": r["seed"], "object": o["object"],  # noqa: E731
                          **{c: o[c] for c in CRITERIA}} for r in recs if r["mode"] == mode
                         for o in r["objects"]]
    real = metrics.success_rates_by_split(rows("real"))
    for mode in ("offline", "online"):
        ev = metrics.success_rates_by_split(rows(mode))
        f = metrics.faithfulness(ev, real, ["in_distribution", "out_of_distribution"])
        for split in ("in_distribution", "out_of_distribution", "overall"):
            for k in ("pearson", "mmrv"):
                a, b = f[split][k], t["main"][mode][split][k]
                assert (math.isnan(a) and math.isnan(b)) or a == pytest.approx(b)
                c = t["faithfulness"]["physics"][mode]["splits"][split][k]["value"]  # the bootstrap's point
                assert (math.isnan(a) and math.isnan(c)) or a == pytest.approx(c)
    text = md.read_text()
    row = next(line for line in text.splitlines() if line.startswith("| offline |"))
    assert ci(t["faithfulness"]["physics"]["offline"]["splits"]["overall"]["mmrv"]) in row
    assert t["tau"]["chosen"] in ("inf", "1.0", "0.5") and t["protocol"]["calibration"]["n"] == 1
    assert t["psnr"]["views"] == ["left", "right", "wrist"] and "| split | rollouts | left | right | wrist | mean |" in text
    for split, q in t["psnr"]["by_split"].items():  # per split: the offline records of that split only
        pv = np.array([r["psnr_view"] for r in recs if r["mode"] == "offline" and r["split"] == split])
        assert q["rollouts"] == len(pv) and q["per_view"] == pytest.approx(np.nanmean(pv, 0).tolist())
    assert sum(q["rollouts"] for q in t["psnr"]["by_split"].values()) == t["psnr"]["rollouts"]
    assert len(t["psnr"]["by_split"]) == 2
    assert "Incomplete sweep" not in text
    assert (tmp_path / "rep" / "correlation.png").stat().st_size > 1000
    assert (tmp_path / "rep" / "u_chunk.png").exists() and (tmp_path / "rep" / "report.html").exists()
    assert len(list((tmp_path / "rep").glob("*.mp4"))) == 1
    # the tau = inf row equals the untruncated online table
    inf_row = next(e for e in t["termination"] if e["tau"] == "inf")
    assert inf_row["faithfulness"] == t["main"]["online"]
    assert all(v == 0.0 for v in inf_row["termination_rate"].values())


def test_report_from_an_archived_store_needs_only_its_two_json_files(setup, tmp_path):
    """sweep.json + results.jsonl.gz (the repository's form, docs/stores/: a 20th of the records' size) regenerate
    every table of a store whose rollouts/ (frames, gigabytes) are gone; only the videos need the frames. An
    archived store refuses to be written to, with one line, and stays as it was."""
    import gzip
    _, cfg = setup
    archive = tmp_path / "archive"
    archive.mkdir()
    shutil.copy(Path(cfg.out) / "sweep.json", archive / "sweep.json")
    (archive / "results.jsonl.gz").write_bytes(gzip.compress((Path(cfg.out) / "results.jsonl").read_bytes()))
    assert ResultsStore(archive).archived and ResultsStore(archive).records() == ResultsStore(cfg.out).records()
    with pytest.raises(UserError, match="archived store .* read-only"):
        ResultsStore(archive, json.loads((archive / "sweep.json").read_text()))
    assert sorted(f.name for f in archive.iterdir()) == ["results.jsonl.gz", "sweep.json"]
    # NaN-safe equality; read_from names the directory each report read
    same = lambda t: json.dumps({k: v for k, v in t.items() if k != "read_from"}, sort_keys=True, default=str)  # noqa: E731
    assert same(report.compute(archive)) == same(report.compute(cfg.out))
    report.render(archive, tmp_path / "rep", videos=1)
    assert not list((tmp_path / "rep").glob("*.mp4")) and (tmp_path / "rep" / "report.json").exists()


def test_report_warns_while_a_mode_is_incomplete():
    t = {"protocol": {"evaluation": {"n": 4}}, "policies": [("a", "in_distribution"), ("b", "out_of_distribution")]}
    warn = report_bench_render.incomplete(dict(t, counts={"real": 8, "offline": 3, "online": 8}))
    assert "offline 3 of 8" in warn and "online" not in warn and "real" not in warn
    assert report_bench_render.incomplete(dict(t, counts={"real": 8, "offline": 0, "online": 8})) == ""  # not swept
    assert "real 7 of 8" in report_bench_render.incomplete(dict(t, counts={"real": 7, "offline": 0, "online": 7}))


def test_real_from_links_the_real_rollouts_and_refuses_another_protocol(setup, tmp_path):
    """--real-from starts a store from another store's real rollouts (hard links, nothing re-simulated) for this
    sweep's policies and seeds only, simulates the seeds the source lacks, and refuses a source run with another
    protocol before creating anything."""
    import shutil
    _, cfg = setup
    src = ResultsStore(cfg.out)
    one = dataclasses.replace(cfg, out=str(tmp_path / "one"), policies=POLICIES[:1], modes=("real",), episodes=3,
                              calibration_episodes=0, real_from=cfg.out)
    sweep.run_sweep(one)
    got = {r["id"]: r for r in ResultsStore(one.out).records()}
    want = {r["id"]: r for r in src.records() if r["mode"] == "real" and r["policy"] == POLICIES[0]
            and r["seed"] not in seed_blocks(cfg)["calibration"]}
    new = rollout_id(POLICIES[0], cfg.seed0 + 2, "real")  # the third evaluation seed: not in the source
    assert set(got) == set(want) | {new} and all(got[i] == want[i] for i in want)
    assert all(os.path.samefile(ResultsStore(one.out).array_path(i), src.array_path(i)) for i in want)
    assert os.stat(ResultsStore(one.out).array_path(new)).st_nlink == 1  # simulated here, not linked
    # resumes without the source (it may have moved): nothing is copied twice, and real_from may differ
    sweep.run_sweep(dataclasses.replace(one, real_from=str(tmp_path / "gone")))
    assert len(ResultsStore(one.out).records()) == 4
    # a source whose real rollouts the sweep would not have run: refused before the store exists
    retasked = tmp_path / "retasked"
    shutil.copytree(cfg.out, retasked)
    lines = [json.loads(line) for line in (retasked / "results.jsonl").read_text().splitlines()]
    for r in lines:
        r["task"] = "reverse" if r["policy"] == POLICIES[0] else r["task"]
    (retasked / "results.jsonl").write_text("".join(json.dumps(r) + "\n" for r in lines))
    other = tmp_path / "other.npz"
    perception.save(other, perception.init(jax.random.key(2)))
    for k, (change, match) in enumerate(((dict(episode_seconds=1.2), "episode_seconds"),
                                         (dict(degradations="none"), "degradations"),
                                         (dict(perception=str(other)), "perception_sha256"),
                                         (dict(real_from=str(retasked)), "task"),
                                         (dict(modes=("online",)), "modes"))):
        bad = dataclasses.replace(one, out=str(tmp_path / f"bad_{k}"), **change)
        with pytest.raises(ValueError, match=match):
            sweep.run_sweep(bad)
        assert not Path(bad.out).exists()


def test_real_from_a_store_of_records_only_copies_the_records(setup, tmp_path):
    """An archived store keeps results.jsonl and sweep.json only (docs/stores/): its real records start a sweep
    whose world-model modes need no frames; offline replay, which needs the real actions, is refused."""
    import shutil
    _, cfg = setup
    import gzip
    archived = tmp_path / "archived"
    archived.mkdir()
    shutil.copy(Path(cfg.out) / "sweep.json", archived / "sweep.json")
    (archived / "results.jsonl.gz").write_bytes(gzip.compress((Path(cfg.out) / "results.jsonl").read_bytes()))
    one = dataclasses.replace(cfg, out=str(tmp_path / "one"), policies=POLICIES[:1], modes=("real",), episodes=2,
                              calibration_episodes=0, ceiling_episodes=0, real_from=str(archived))
    sweep.run_sweep(one)
    got = ResultsStore(one.out).records()
    want = {r["id"]: r for r in ResultsStore(cfg.out).records() if r["id"] in {g["id"] for g in got}}
    assert len(got) == 2 and all(g == want[g["id"]] for g in got)
    assert not any(ResultsStore(one.out).array_path(g["id"]).exists() for g in got)
    bad = dataclasses.replace(one, out=str(tmp_path / "bad"), modes=("real", "offline"))
    with pytest.raises(ValueError, match="offline"):
        sweep.run_sweep(bad)
    assert not Path(bad.out).exists()


def test_reading_a_store_never_writes_and_its_sweep_repairs_a_cut_line(tmp_path):
    """A report or a --real-from reading a store while its sweep appends must not cut the line being written; the
    store's own sweep, resuming after a kill, truncates the cut line before appending."""
    cfg = sweep.SweepConfig(out=str(tmp_path / "s"))
    store = ResultsStore(cfg.out, cfg.to_json(), lock=True)  # a running sweep holds its store's lock
    store.append([{"id": "a", "mode": "real"}])
    with open(store.path, "a") as fh:
        fh.write('{"id": "b", "mo')
    raw = store.path.read_bytes()
    assert [r["id"] for r in ResultsStore(cfg.out).records()] == ["a"] and store.path.read_bytes() == raw
    store.close()  # the sweep was killed mid-line: a report would leave rollout b out without a word
    with pytest.raises(UserError, match="its last line is cut .* no sweep is writing it: resume the sweep"):
        ResultsStore(cfg.out).records()
    assert store.path.read_bytes() == raw and ResultsStore(cfg.out).done() == {"a"}  # what a resume runs again
    ResultsStore(cfg.out, cfg.to_json())
    assert store.path.read_bytes() == raw[:raw.rfind(b"\n") + 1]
    assert [r["id"] for r in ResultsStore(cfg.out).records()] == ["a"]


def test_a_stores_records_and_sweep_json_linked_out_of_it_are_refused(tmp_path):
    cfg = sweep.SweepConfig(out=str(tmp_path / "s"))
    store = ResultsStore(cfg.out, cfg.to_json())
    store.append([{"id": "a", "mode": "real"}])
    for name in ("results.jsonl", "sweep.json"):
        elsewhere = tmp_path / f"other_{name}"
        elsewhere.write_bytes((store.root / name).read_bytes())
        (store.root / name).rename(tmp_path / f"kept_{name}")
        (store.root / name).symlink_to(elsewhere)
        with pytest.raises(UserError, match="a link to a file outside"):
            ResultsStore(cfg.out).records() if name == "results.jsonl" else ResultsStore(cfg.out).config()
        (store.root / name).unlink()
        (tmp_path / f"kept_{name}").rename(store.root / name)
    assert [r["id"] for r in ResultsStore(cfg.out).records()] == ["a"]


def _flip_first_object(store: Path, mode: str, split: str):
    """Flip every criterion of the first object of the first ``mode`` record of ``split`` in a store."""
    lines = (store / "results.jsonl").read_text().splitlines()
    i = next(k for k, line in enumerate(lines) if json.loads(line)["mode"] == mode
             and json.loads(line)["split"] == split)
    r = json.loads(lines[i])
    r["objects"][0].update({c: not r["objects"][0][c] for c in CRITERIA})
    lines[i] = json.dumps(r)
    (store / "results.jsonl").write_text("\n".join(lines) + "\n")


def test_compute_curve_over_sweeps_sharing_one_real_set(setup, tmp_path):
    """sc3 curve: each point's numbers are its store's report numbers, the floor is the shared real set's, and
    points whose real rollouts differ are refused."""
    import shutil

    from sc3_jax.evaluation import curve
    _, cfg = setup
    second = dataclasses.replace(cfg, out=str(tmp_path / "second"), modes=("real", "online"), real_from=cfg.out)
    sweep.run_sweep(second)
    _flip_first_object(Path(second.out), "online", "in_distribution")  # so the two points differ
    points = [{"label": "a", "store": cfg.out, "steps": 10, "batch": 2, "device": "2-core CPU", "hours": 0.1},
              {"label": "b", "store": second.out, "steps": 40, "batch": 2, "device": "GPU", "hours": 0.05}]
    spec = tmp_path / "curve.json"
    spec.write_text(json.dumps({"title": "t", "points": points}))
    md = curve.render(spec, tmp_path / "out", draws=200)
    c = json.loads((tmp_path / "out" / "curve.json").read_text())
    for p, store in zip(c["points"], (cfg.out, second.out)):
        t = report.compute(store, draws=200)
        assert p["online"]["in_distribution"] == t["faithfulness"]["physics"]["online"]["splits"]["in_distribution"]
        assert p["windows"] == p["steps"] * p["batch"] and p["cases"] == t["cases"]["online"]
    assert c["floor"]["in_distribution"] == t["faithfulness"]["physics"]["policy_blind"]["splits"]["in_distribution"]
    assert c["points"][0]["online"] != c["points"][1]["online"]
    text = md.read_text()
    assert "| a | 2-core CPU, 0.1 h | 20 |" in text and "policy-blind (floor)" in text
    vs = t["faithfulness"]["physics"]["online"]["vs_floor"]["in_distribution"]["pearson"]
    assert c["points"][1]["vs_floor"]["in_distribution"]["pearson"] == vs and f"| b | {ci(vs)} |" in text
    assert (tmp_path / "out" / "curve.png").stat().st_size > 1000
    # a baseline: each point's paired difference to it (its own is 0), printed for the others
    spec.write_text(json.dumps({"title": "t", "points": points, "baseline": "a"}))
    text = curve.render(spec, tmp_path / "out_b", draws=200).read_text()
    c = json.loads((tmp_path / "out_b" / "curve.json").read_text())
    own, other = (p["vs_baseline"]["overall"]["mmrv"] for p in c["points"])
    assert (own["value"], own["lo"], own["hi"]) == (0.0, 0.0, 0.0)
    a_b = [report.compute(st, draws=200)["faithfulness"]["physics"]["online"]["splits"]["overall"]["mmrv"]["value"]
           for st in (cfg.out, second.out)]
    assert other["value"] == pytest.approx(a_b[1] - a_b[0])
    assert f"| b | {ci(c['points'][1]['vs_baseline']['in_distribution']['pearson'])} |" in text
    spec.write_text(json.dumps({"points": points, "baseline": "nope"}))
    with pytest.raises(ValueError, match="baseline 'nope'"):
        curve.read_spec(spec)
    # a point swept against other real rollouts
    third = tmp_path / "third"
    shutil.copytree(second.out, third)
    _flip_first_object(third, "real", "in_distribution")
    spec.write_text(json.dumps({"points": points + [dict(points[1], label="c", store=str(third))]}))
    with pytest.raises(ValueError, match="real rollouts differ"):
        curve.render(spec, tmp_path / "out2", draws=200)
    fourth = tmp_path / "fourth"  # the same evaluation rollouts, another ceiling rollout
    shutil.copytree(second.out, fourth)
    lines = [json.loads(line) for line in (fourth / "results.jsonl").read_text().splitlines()]
    rec = next(r for r in lines if r["mode"] == "real" and r["seed"] in seed_blocks(cfg)["ceiling"])
    rec["objects"][0]["language"] = not rec["objects"][0]["language"]
    (fourth / "results.jsonl").write_text("".join(json.dumps(r) + "\n" for r in lines))
    spec.write_text(json.dumps({"points": points + [dict(points[1], label="d", store=str(fourth))]}))
    with pytest.raises(ValueError, match=rec["id"]):
        curve.render(spec, tmp_path / "out3", draws=200)
    for bad, match in (({"label": "x", "store": cfg.out}, "lacks"), (dict(points[0], steps="2880"), "steps")):
        spec.write_text(json.dumps({"points": [bad]}))
        with pytest.raises(ValueError, match=match):
            curve.read_spec(spec)


def test_sweep_resumes_after_sigkill_with_identical_results(setup):
    root, cfg = setup
    out = root / "killed"
    code = ("import math, sys; import sc3_jax.benchmarks.bussing; from sc3_jax.benchmarks.bussing import sweep; "
            f"sweep.run_sweep(sweep.SweepConfig(out={str(out)!r}, world_model={cfg.world_model!r}, "
            f"perception={cfg.perception!r}, policies={POLICIES!r}, episodes=2, episode_seconds=1.6, batch=2, "
            "progress=False, taus=(math.inf, 1.0, 0.5), calibration_episodes=1, ceiling_episodes=1, "
            "modes=('real', 'offline', 'online'), workers=1))")
    env = dict(os.environ)
    p = subprocess.Popen([sys.executable, "-c", code], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    results = out / "results.jsonl"
    t0 = time.time()
    while time.time() - t0 < 300 and p.poll() is None:
        if results.exists() and results.read_text().count("\n") >= 11:  # mid-way: inside the second policy
            break
        time.sleep(0.05)
    assert p.poll() is None, f"the sweep finished or died before it could be killed: {p.communicate()[1][-2000:]}"
    os.kill(p.pid, signal.SIGKILL)
    p.wait()
    n_before = results.read_text().count("\n")
    assert 11 <= n_before < 18
    sweep.run_sweep(dataclasses.replace(cfg, out=str(out)))
    by_id = lambda path: {r["id"]: r for r in ResultsStore(path).records()}  # noqa: E731
    assert by_id(out) == by_id(cfg.out)


def test_annotation_round_trip_reproduces_ground_truth(setup, tmp_path):
    _, cfg = setup
    csv_path, key_path = annotation.export_blinded(cfg.out, tmp_path / "annotate")
    assert key_path.parent != csv_path.parent  # the key is not shipped with the clips
    recs = {r["id"]: r for r in ResultsStore(cfg.out).records()}
    key = json.loads(key_path.read_text())
    clips = sorted((tmp_path / "annotate" / "clips").glob("*.mp4"))
    assert len(clips) == len(recs) and all(len(c.stem) == 8 for c in clips)
    listing = " ".join(c.name for c in clips) + csv_path.read_text()
    assert not any(w in listing for w in ("real", "offline", "online") + POLICIES)
    # fill the template from the scores in the store (ground truth for real rollouts)
    with open(csv_path) as fh:
        rows = list(csv.DictReader(fh))
    for row in rows:
        o = next(o for o in recs[key[row["clip_id"]]["rollout"]]["objects"] if o["object"] == row["object"])
        row.update({c: str(int(o[c])) for c in CRITERIA})
    write = lambda rs, path=csv_path: _write_csv(path, rs)  # noqa: E731
    write(rows)
    labels = annotation.import_annotations(csv_path, key_path)
    human = HumanScorer(labels)
    for rid, r in recs.items():
        view = RolloutView(rid, None, tuple(o["object"] for o in r["objects"]),
                           {o["object"]: o["destination"] for o in r["objects"]})
        assert human.score(view) == r["objects"]
    # malformed CSVs: each gives a clear error
    bad = tmp_path / "bad.csv"
    cases = [
        (rows[:-1], "missing rows"),
        (rows + [dict(rows[0])], "duplicate row"),
        ([dict(rows[0], clip_id="deadbeef")] + rows[1:], "unknown clip id 'deadbeef'"),
        ([dict(rows[0], lifting="yes")] + rows[1:], r"lifting='yes' \(expected 0 or 1\)"),
        ([dict(rows[0], placing="")] + rows[1:], "placing=''"),
        ([dict(rows[0], object="unicorn")] + rows[1:], "no object 'unicorn'"),
    ]
    for rs, msg in cases:
        write(rs, bad)
        with pytest.raises(annotation.AnnotationError, match=msg):
            annotation.import_annotations(bad, key_path)
    with open(bad, "w") as fh:
        fh.write("clip_id,object,language\n")
    with pytest.raises(annotation.AnnotationError, match="missing columns"):
        annotation.import_annotations(bad, key_path)


def _write_csv(path, rows):
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, annotation.COLUMNS)
        w.writeheader()
        w.writerows(rows)


def test_chunk_actions_compose_pairs_and_hold_still_after_the_end():
    spec = sweep_spec()
    raw = np.zeros((5, 7), np.float32)
    raw[:, 0] = 0.01
    raw[:, 6] = 0.05
    a = rollout.chunk_actions(raw, spec)
    assert a.shape == (spec.num_chunks, spec.predict, 7)
    assert a[0, 0, 0] == pytest.approx(0.02) and a[0, 2, 0] == pytest.approx(0.01)  # 5 raw -> 2.5 model steps
    assert np.all(a[0, 3:, :6] == 0) and np.all(a[..., 6] == pytest.approx(0.05))
    frames = np.arange(7)[None, :, None, None, None] * np.ones((3, 7, 2, 2, 3), np.uint8)
    tgt, valid = rollout.recorded_targets(frames, spec)
    assert tgt[0, :4, 0, 0, 0].tolist() == [2, 4, 6, 6] and valid[:4].tolist() == [True, True, True, False]


def sweep_spec():
    from sc3_jax.rollout import rollout
    from sc3_jax.data.action_space import DELTA_EE
    return rollout.make_spec(load_config("bussing_sim"), 20.0, num_chunks=2, action_space=DELTA_EE)  # its data: 20 fps


def test_remote_policy_over_the_openpi_protocol(setup, tmp_path):
    """A policy behind an openpi-protocol server is evaluated like a zoo policy (real + online via the host loop)."""
    from sc3_jax.policies.openpi_server import PolicyServer
    from sc3_jax.benchmarks.bussing.zoo import load_policy
    root, cfg = setup
    server = PolicyServer(load_policy(POLICIES[0]), host="127.0.0.1", port=0).start()
    try:
        remote = dataclasses.replace(cfg, out=str(tmp_path / "remote"), episodes=1, modes=("real", "online"),
                                     calibration_episodes=0, ceiling_episodes=0,
                                     policies=(f"served=ws://127.0.0.1:{server.port}@bussing",))
        sweep.run_sweep(remote)
    finally:
        server.shutdown()
    recs = {r["mode"]: r for r in ResultsStore(remote.out).records()}
    local = {r["mode"]: r for r in ResultsStore(cfg.out).records()
             if r["policy"] == POLICIES[0] and r["seed"] == cfg.seed0}
    assert set(recs) == {"real", "online"} and recs["real"]["policy"] == "served"
    assert recs["real"]["objects"] == local["real"]["objects"]  # same policy, same simulator: same outcomes
    assert len(recs["online"]["u"]) == 2
    with pytest.raises(ValueError, match="NAME=ws://HOST:PORT@TASK"):  # not a task of the benchmark's: refused
        engine.resolve_policies(["x=ws://127.0.0.1:1@nowhere"], need_task=True, tasks=TASKS)  # before connecting


def test_degradations_choice_reads_legacy_booleans_and_refuses_others():
    from sc3_jax.core.errors import UserError
    assert [sweep.degradations_choice(v) for v in (True, False, "calibration", "all", "none")] == \
        ["all", "none", "calibration", "all", "none"]
    with pytest.raises(UserError, match="choose from"):
        sweep.degradations_choice("some")
    assert [sweep.degraded_block("calibration", b) for b in ("evaluation", "calibration", "ceiling")] == \
        [False, True, False]
    assert all(sweep.degraded_block("all", b) for b in ("evaluation", "ceiling"))
    assert not any(sweep.degraded_block("none", b) for b in ("evaluation", "calibration"))

"""sc3 diagnose (sc3_jax/evaluation/diagnose*.py): the metric pieces on hand-built frames, and the whole table on a tiny
"copy the last frame" world model (residual prediction with zero output weights, i.e. an untrained one) over two
short simulated episodes, where every model figure must equal its copy-last baseline exactly."""
import contextlib
import copy
import io
import json
import math
from pathlib import Path

import jax
import numpy as np
import pytest

import sc3_jax.benchmarks.bussing  # noqa: F401  (picks the GL backend before mujoco is imported)
from sc3_jax.model import checkpoint
from sc3_jax.train import train
from sc3_jax.core.config import load_config, replace
from sc3_jax.data.episodes import Episode, EpisodeStore
from sc3_jax.data.norm_stats import NormStats
from sc3_jax.cli import main as cli
from sc3_jax.evaluation import diagnose as dg
from sc3_jax.evaluation import diagnose_outcomes


def test_moving_mask_and_pooled_psnr_on_a_constructed_pair():
    ref = np.full((8, 8, 3), 100, np.uint8)
    tgt = ref.copy()
    tgt[2:4, 3:6, 1] += 10  # 10 / 127.5 = 0.078 > 0.06: moving
    tgt[6, 6, 0] += 7  # 7 / 127.5 = 0.055 <= 0.06: flicker, not moving
    mask = dg.moving_mask(tgt, ref, 0.06)
    want = np.zeros((8, 8), bool)
    want[2:4, 3:6] = True
    np.testing.assert_array_equal(mask, want)
    s = dg.squared_errors(ref, tgt, mask)  # "copy last" against the target
    np.testing.assert_allclose(s, [6 * 100 + 49, 8 * 8 * 3, 6 * 100, 6 * 3])
    assert dg.psnr_from_sums(s[2], s[3]) == pytest.approx(10 * math.log10(255 ** 2 * 18 / 600))
    assert dg.psnr_from_sums(0.0, 5) == math.inf and math.isnan(dg.psnr_from_sums(0.0, 0))
    # the threshold is a parameter: at 0.05 the flickering pixel moves too
    assert dg.moving_mask(tgt, ref, 0.05).sum() == 7


def test_temporal_median_erases_a_moving_arm_and_the_centroid_finds_it():
    bg = np.random.default_rng(0).integers(0, 200, (16, 16, 3), dtype=np.uint8)
    frames = np.repeat(bg[None], 9, 0)
    for t in range(9):  # a bright 3x3 "arm" crossing the image: on any pixel in at most 3 of the 9 frames
        frames[t, 5:8, t:t + 3] = 250
    med = dg.temporal_median(frames)
    np.testing.assert_array_equal(med, bg)
    c = dg.arm_centroid(frames[4], med, 0.12, 4)
    np.testing.assert_allclose(c, [6.0, 5.0])  # rows 5..7, cols 4..6
    assert np.all(np.isnan(dg.arm_centroid(bg, med, 0.12, 4)))


def _tiny_store(root, n=2, steps=40):
    from sc3_jax.benchmarks.bussing.env import BussingEnv
    from sc3_jax.benchmarks.bussing.expert import run_expert_episode
    env = BussingEnv(image_size=(64, 64))
    store = EpisodeStore(root, views=list(env.views), fps=env.control_hz, image_size=(64, 64), create=True)
    for i in range(n):
        r = run_expert_episode(env, 7 + i, "bussing", record=True, max_steps=steps)
        store.write(Episode(f"ep{i:02d}", r.frames, r.actions, r.ee_pose, r.ic.prompt,
                            {"initial_condition": r.ic.to_json(),
                             "labels": {"objects": [o.to_json() for o in r.outcomes]}}))
    env.close()
    return store


def _copy_last_model(root):
    cfg = load_config("bussing_sim")
    assert cfg.model.prediction == "residual"  # zero-initialised output: predicts the last context frame
    # 3 sampler steps of its own: `sc3 diagnose` samples as the sweep does (SweepConfig's 2 steps, 1 to re-read U)
    cfg = replace(cfg, model=dict(dim=32, depth=1, num_heads=2, num_kv_heads=1, head_dim=16, mlp_dim=64,
                                  rope_axes_dim=(4, 2, 2)), sample=dict(steps=3),
                  data=dict(fps=20.0, state_dim=0))  # its data's facts, as `sc3 train` records them (_tiny_store's)
    params = jax.device_get(train.init_state(cfg)["params"])
    stats = NormStats(np.zeros(7, np.float32), np.full(7, 0.02, np.float32))
    return checkpoint.save(root / "wm", cfg, stats, params, np.float32)


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    root = tmp_path_factory.mktemp("diagnose")
    store = _tiny_store(root / "heldout")
    wm = _copy_last_model(root)
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        rc = cli(["diagnose", "--world-model", str(wm), "--data", str(store.root), "--out", str(root / "result.json"),
                  "--benchmark", "bussing", "--no-progress"])
    assert rc == 0
    return store, dg.load_result(root / "result.json"), out.getvalue()


def test_table_prints_every_section(run):
    _, result, text = run
    for heading in ("One chunk ahead from real context", "Drift", "Counterfactual actions",
                    "Inverse dynamics on real frames", "Offline outcome reproduction", "Gates"):
        assert f"### {heading}" in text
    for view in ("left", "right", "wrist"):
        assert f"| {view} | 0.8 s |" in text and f"| {view} | 8 s | 0 |" in text  # 2 s episodes: no 8 s point
    # the CLI prints exactly the rendering of the saved result, then the sampler and the gates' verdicts
    table, tail = text[:len(dg.render_table(result))], text[len(dg.render_table(result)):].splitlines()
    assert table == dg.render_table(result)
    assert len(result["gates"]) == len(dg.GATES)
    failed = [g["gate"] for g in result["gates"] if not g["pass"]]
    assert tail[2] == f"gates: {len(dg.GATES) - len(failed)} of {len(dg.GATES)} pass; failed:"
    assert [line.split(": ")[0] for line in tail[3:-2]] == [f"  FAIL {g}" for g in failed]
    assert tail[-2].startswith("outcome set: 6 objects with physics labels in 2 episodes: too few")
    assert tail[-1].startswith("result: ") and tail[-1].endswith("result.json")


def test_diagnose_samples_as_the_sweep_does(run):
    """The world model's own 3 steps are replaced by the sweep's sampler settings (one set for every command)."""
    from sc3_jax.benchmarks.bussing.sweep import SweepConfig

    _, result, text = run
    st, sweep = result["settings"], SweepConfig()
    assert (st["sample_steps"], st["inverse_steps"]) == (sweep.sample_steps, sweep.inverse_steps)
    assert f"{sweep.sample_steps} sampler steps (U re-read in {sweep.inverse_steps})" in text


def test_copy_last_model_scores_exactly_the_copy_last_baseline(run):
    store, result, _ = run
    tf = result["teacher_forced"]
    assert tf["n_chunks"] == 4  # 40-frame episodes: chunks from frames 0 and 16 (the next would need frame 50)
    for v in ("left", "right", "wrist"):
        p = tf["views"][v]["psnr"]
        assert p["model"] == p["copy_last"] == p["shuffled"]  # actions cannot matter to it either
        assert tf["views"][v]["true_minus_shuffled_moving"] == 0.0
        assert p["copy_last"]["moving"] < p["copy_last"]["whole"]  # the moving pixels are where it is wrong
        for row in result["drift"]["views"][v]:
            if row["n_episodes"]:
                assert row["psnr"]["model"] == row["psnr"]["copy_last"]
    # the copy-last, copy-first and median figures recomputed independently for the first teacher-forced chunk
    # pool (both episodes' chunk from frame 0, target = frame 2 + 2 * 8 = 18, context = frame 2)
    # over both episodes' chunks from frames 0 and 16: context frame s + 2, target at 0.8 s = frame s + 2 + 2 * 8
    sums = {k: np.zeros(4) for k in ("copy_last", "copy_first", "median")}
    for eid in store.episode_ids():
        f = np.asarray(store.load(eid).frames["left"]).astype(np.float64)
        for s in (0, 16):
            ctx, tgt = f[s + 2], f[s + 18]
            mask = np.any(np.abs(tgt - ctx) / 127.5 > 0.06, -1)[..., None]
            for k, pred in (("copy_last", ctx), ("copy_first", f[0]), ("median", np.median(f, 0))):
                e = (pred - tgt) ** 2
                sums[k] += [e.sum(), e.size, (e * mask).sum(), mask.sum() * 3]
    for k, (a, n, am, nm) in sums.items():
        got = tf["views"]["left"]["psnr"][k]
        assert got["whole"] == pytest.approx(10 * np.log10(255 ** 2 * n / a), abs=1e-9)
        assert got["moving"] == pytest.approx(10 * np.log10(255 ** 2 * nm / am), abs=1e-9)
    # inverse dynamics: zero output weights estimate the mean action: exactly the "zero" floor
    idr = result["inverse_dynamics"]
    assert idr["mse"] == pytest.approx(idr["zero"], rel=1e-6) and idr["ratio_to_floor"] >= 1.0 - 1e-6
    # the floor recomputed from the recorded actions: the 8 model-rate actions of each chunk (pairs of 20 Hz
    # actions composed, from the last context frame s + 2), normalised by the model's stats (mean 0, std 0.02)
    from sc3_jax.data.action_space import DELTA_EE
    from sc3_jax.data.pipeline import compose_actions
    a = np.stack([compose_actions(store.load(eid).actions, s + 2 + 2 * i, 2, DELTA_EE) for eid in store.episode_ids()
                  for s in (0, 16) for i in range(8)]) / 0.02
    assert idr["n_steps"] == len(a) == 32
    assert idr["zero"] == pytest.approx(np.mean(a ** 2), rel=1e-5)
    assert idr["mean_floor"] == pytest.approx(np.mean(a.var(0)), rel=1e-4)


def test_gates_evaluate(run):
    _, result, _ = run
    g = {x["gate"]: x for x in result["gates"]}
    assert g[dg.GATES[0]]["value"] == 0.0 and not g[dg.GATES[0]]["pass"]  # copy-last is not 3 dB above itself
    assert g[dg.GATES[2]]["value"] == 0.0 and not g[dg.GATES[2]]["pass"]
    assert g[dg.GATES[4]]["pass"]
    oc = result["outcomes"]
    assert oc["available"] and oc["reference"] == "physics" and oc["imagined_vs_physics"]["n_objects"] == 6
    assert g[dg.GATES[3]]["value"] == oc["imagined_vs_physics"]["outcome"]
    # a result whose model beats both baselines by 4 dB and its shuffled actions by 3 dB passes those gates
    better = copy.deepcopy(result)
    for v in better["views"]:
        r = better["teacher_forced"]["views"][v]
        r["psnr"]["model"]["moving"] = max(r["psnr"]["copy_last"]["moving"], r["psnr"]["median"]["moving"]) + 4
        r["true_minus_shuffled_moving"] = 3.0
    better["outcomes"]["imagined_vs_physics"]["outcome"] = 0.8
    passed = {x["gate"]: x["pass"] for x in dg.gates(better, dg.DiagnoseConfig())}
    assert all(passed.values()), passed
    better["outcomes"]["imagined_vs_physics"]["outcome"] = 0.7
    assert not {x["gate"]: x["pass"] for x in dg.gates(better, dg.DiagnoseConfig())}[dg.GATES[3]]


def test_outcome_agreement_compares_criteria_not_category_spellings():
    """The simulator's labels spell the category "no failure", the scorers' metrics "no_failure": agreement is
    decided on the criteria (and the category recomputed from them)."""
    obj = lambda name, lifting, placing, outcome: {"name": name, "destination": "bin", "language": True,  # noqa: E731
                                                   "lifting": lifting, "placing": placing, "outcome": outcome}
    physics = [obj("cup", True, True, "no failure"), obj("bowl", False, False, "lifting")]
    imagined = [obj("cup", True, True, "no_failure"), obj("bowl", True, False, "placing")]
    sec = diagnose_outcomes.outcome_section([{"episode": "e", "imagined": imagined, "real_perception": physics,
                                "physics": physics, "covered": True}], None)
    r = sec["imagined_vs_physics"]
    assert sec["reference"] == "physics" and r["n_objects"] == 2
    assert (r["lifting"], r["placing"], r["lifting_and_placing"], r["outcome"]) == (0.5, 1.0, 0.5, 0.5)
    assert sec["real_perception_vs_physics"]["outcome"] == 1.0


def test_diagnose_table_compares_models_with_a_baseline(run, tmp_path, capsys):
    from sc3_jax.evaluation import diagnose_table as dt

    _, result, _ = run
    cfg = json.loads(Path(result["world_model"], "config.json").read_text())
    base = dt.summary(result, cfg)
    # the copy-last model: every margin to copy-last is exactly 0; its 2 s episodes have no 4 s drift point
    assert base["tf_copy_last"] == base["wrist"] == base["actions"] == 0.0
    assert math.isnan(base["drift"]) and base["inverse"] == result["inverse_dynamics"]["ratio_to_floor"]
    assert base["gates_failed"] == sum(not g["pass"] for g in result["gates"])
    # a model 2 dB better on the wrist, with a 4 s drift point, trained without inverse dynamics
    other = copy.deepcopy(result)
    wrist = other["teacher_forced"]["views"]["wrist"]["psnr"]["model"]
    wrist["moving"] += 2.0
    for v, gain in (("left", 1.0), ("right", 3.0)):
        row = other["drift"]["views"][v][2]
        assert row["horizon_s"] == dt.DRIFT_HORIZON_S
        row["n_episodes"] = 1
        row["psnr"] = {"model": {"moving": 10.0 + gain}, "copy_last": {"moving": 10.0}}
    no_id = copy.deepcopy(cfg)
    no_id["modes"]["probs"] = [0.9, 0.1, 0.0]
    s = dt.summary(other, no_id)
    assert s["wrist"] == pytest.approx(2.0) and s["drift"] == pytest.approx(2.0) and s["inverse"] is None
    # the CLI: labels from the directory (its parent's name for `export`), differences to the baseline
    for name, res, c in (("full/export", result, cfg), ("no_id", other, no_id)):
        (tmp_path / name).mkdir(parents=True)
        (tmp_path / name / "diagnose.json").write_text(json.dumps(res))
        (tmp_path / name / "config.json").write_text(json.dumps(c))
    out = tmp_path / "table.md"
    assert cli(["diagnose-table", "--world-model", str(tmp_path / "full/export"), str(tmp_path / "no_id"),
                "--baseline", "full", "--out", str(out)]) == 0
    lines = out.read_text().splitlines()
    assert lines[2].startswith("| **full** | 0.00 | ") and lines[3].startswith("| no_id | 0.00 (+0.00) | ")
    cells = lines[3].split(" | ")
    assert "2.00 (+2.00)" in cells and "2.00" in cells and "not trained" in cells  # wrist; drift (no base); ID
    # bad input: an unknown baseline, a directory without diagnose.json; nothing written
    assert cli(["diagnose-table", "--world-model", str(tmp_path / "no_id"), "--baseline", "full"]) == 2
    assert "baseline 'full' is not one of ['no_id']" in capsys.readouterr().err
    assert cli(["diagnose-table", "--world-model", str(tmp_path)]) == 2
    assert "no diagnose.json or config.json" in capsys.readouterr().err


def test_objects_kept_are_split_into_stages_with_a_filmstrip_each(run):
    """Every stage of the objects-kept table is there, at 1 s and 2 s (2 s episodes), and the pixel tokenizer's
    exact round trip keeps every object pixel: 1 exactly. A filmstrip per stage lies beside --out."""
    _, result, text = run
    sec = result["permanence"]
    assert [(r["stage"], r["measure"]) for r in sec["rows"]] == [
        ("round trip", "objects"), ("one chunk", "objects"), ("open loop", "objects")]
    for r in sec["rows"]:
        assert set(r["times"]) == {"1 s"} or set(r["times"]) == {"1 s", "2 s"}, r
    trip = sec["rows"][0]["times"]["1 s"]["kept"]["all views"]
    assert trip["value"] == 1.0 and trip["lo"] == trip["hi"] == 1.0
    assert "### Objects kept, stage by stage" in text and "| objects | round trip | 1.00 [1.00, 1.00] |" in text
    strips = [Path(p) for p in sec["filmstrips"]]
    assert sorted(p.name for p in strips) == ["one_chunk.png", "open_loop.png", "round_trip.png"]
    assert all(p.is_file() and p.parent.name == "result_filmstrips" for p in strips)


def test_a_stage_that_loses_what_the_measure_counts_reads_0(run):
    """A measure of what moved since the last context frame: the copy-last model draws the context frame again, so
    open loop keeps none of it (0 exactly) while the round trip keeps all of it (1): the table reads both ends."""
    store, _, _ = run
    wm = Path(store.root).parent / "wm"
    # each episode's last context frame (frame 2), every view: [E, V, 1, H, W, 3]
    ref = np.stack([np.stack([np.asarray(store.load(eid).frames[v][2]) for v in store.views])[:, None]
                    for eid in store.episode_ids()]).astype(int)

    def moved(frames):  # [V, T, H, W, 3] -> [V, T]: pixels away from both episodes' context frame, view by view
        far = (np.abs(frames.astype(int)[None] - ref).max(-1) > 8).all(0)
        return far.mean((-2, -1))
    result = dg.diagnose(wm, store.root, dg.DiagnoseConfig(stages=("open_loop",), progress=False),
                         scene={"moved": moved})
    rows = {r["stage"]: r for r in result["permanence"]["rows"]}
    assert rows["round trip"]["times"]["1 s"]["kept"]["all views"]["value"] == 1.0
    assert rows["open loop"]["times"]["1 s"]["kept"]["all views"]["value"] == 0.0
    assert rows["one chunk"]["times"] == {}  # its pass did not run

"""Evaluation without a simulator: `sc3 sweep episodes --data` ranks
policies inside a world model from held-out episodes of the tiny bimanual 14-D robot of test_any_robot.py -- two
`module:attr` host policies and one served over a real websocket by an openpi-style ALOHA server (`--family aloha`:
4 CHW cameras, 14-D state) -- scored by a `module:attr` scorer, resumably, and compares the ranking with real
outcomes (r / MMRV with intervals, next to the policy-blind floor); `sc3 rollout` runs a `module:attr` policy on the
same model. Policies, scorers and their faulty twins are defined here and named as `test_ic_sweep:ATTR`."""
import csv
import json
import shutil

import numpy as np
import pytest

from sc3_jax.cli import main
from sc3_jax.data.action_space import ActionSpace
from sc3_jax.data.episodes import Episode, EpisodeStore
from sc3_jax.core.errors import UserError
from sc3_jax.evaluation import labels
from sc3_jax.evaluation.diagnose_outcomes import no_scorer
from sc3_jax.policies.openpi_mappings import ALOHA_CAMERAS, for_world_model, resize_with_pad
from test_any_robot import CAMS, A, H, W, bimanual  # noqa: F401  (the fixture: imported store + trained tiny model)

CHUNK = 8  # the fixture model's rollout.policy_chunk


# -- policies: absolute joint targets, a fixed offset from the state they observe each chunk ---------------------
class Offset:
    chunk, action_dim = CHUNK, A

    def __init__(self, d: float, dim: int = A):
        self.d, self.action_dim = d, dim

    def infer(self, obs):
        return np.repeat(np.asarray(obs["state"])[None, :self.action_dim] + self.d, CHUNK, 0).astype(np.float32)


def hold():
    return Offset(0.0)


def half():
    return Offset(0.1)


def reach():
    return Offset(0.3)


def seven():
    return Offset(0.0, dim=7)  # the benchmark's 7-D actions: not this robot's


# -- a policy served over openpi's protocol, as an openpi ALOHA server sees the world ------------------------------
class AlohaServed:
    """openpi's ALOHA observation in (aloha_policy.AlohaInputs: images {cam_high, cam_low, cam_left_wrist,
    cam_right_wrist} CHW uint8, state [14], prompt), {"actions": [H, 14]} out; `half`'s offset, H = 10 rows (fewer
    than the client's chunk: it holds the last). Every request is kept, to check what crossed the wire."""

    def __init__(self, d: float):
        self.d, self.requests = d, []

    def infer(self, obs):
        self.requests.append(obs)
        return {"actions": np.repeat(np.asarray(obs["state"], np.float32)[None] + np.float32(self.d), 10, 0)}


# -- scorers ---------------------------------------------------------------------------------------------------------
SEEN = []  # what the scorer was shown


def score(view):
    """Outcomes from the imagined state: moved at all, and moved far (> 0.4 rad on average) = success."""
    SEEN.append(view)
    moved = float(np.mean(view.state[-1] - view.state[0]))
    return {"success": moved > 0.4, "moved": bool(moved > 0.05)}


def not_a_dict(view):
    return 0.5


# -- stores ----------------------------------------------------------------------------------------------------------
def _conditions(store, root):
    """The imported store's 2 episodes twice over (4 held-out conditions, as 4 episodes)."""
    shutil.copytree(store.root, root)
    for i, eid in enumerate(store.episode_ids()):
        shutil.copytree(store.root / eid, root / f"lerobot{i + 2:06d}")
    return root


REAL = {"hold": ([0, 0, 0, 1], [0, 1, 0, 0]), "half": ([0, 0, 1, 0], [1, 1, 1, 0]),
        "reach": ([1, 1, 1, 0], [1, 1, 1, 1])}  # policy -> (success, moved) of 4 real episodes each


def _real_store(root):
    st = EpisodeStore(root, views=["cam"], fps=20, image_size=(4, 4), create=True,
                      action_space=ActionSpace("absolute", 1), has_pose=False)
    for policy, (success, moved) in REAL.items():
        for i, (s, m) in enumerate(zip(success, moved)):
            st.write(Episode(f"{policy}{i}", {"cam": np.zeros((1, 4, 4, 3), np.uint8)}, np.zeros((1, 1), np.float32),
                             None, "fold the towel", {"policy": policy, "labels": {"success": bool(s), "moved": bool(m),
                                                                                   "objects": []}}))
    return root


def _sweep(ic, run, out, *extra, policies=("hold", "half", "reach"), scorer="test_ic_sweep:score"):
    """`sc3 sweep episodes --data`; a policy NAME is test_ic_sweep:NAME, a NAME=SPEC is given as is."""
    return main(["sweep", "episodes", "--data", str(ic), "--world-model", str(run), "--policies",
                 *[p if "=" in p else f"{p}=test_ic_sweep:{p}" for p in policies], "--scorer", scorer,
                 "--episodes", "2", "--calibration-episodes", "2", "--batch", "2", "--episode-seconds", "0.6", "--taus", "inf", "0.5",
                 "--out", str(out), "--no-progress", *extra])


def _error(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert err.startswith("sc3 sweep: error: ") and "\n" not in err, err
    return err


@pytest.fixture(scope="module")
def aloha():
    """The openpi-style ALOHA server, on a free port for the module; `half=ws://...` in the sweep."""
    from sc3_jax.policies.openpi_server import PolicyServer

    server = PolicyServer(AlohaServed(0.1), host="127.0.0.1", port=0).start()  # no mapping: openpi's dict as is
    yield server
    server.shutdown()


def _served(server) -> tuple[str, ...]:
    """hold and reach by module:attr, half over the websocket through the ALOHA mapping."""
    return ("hold", f"half={server.url}", "reach")


@pytest.fixture(scope="module")
def swept(bimanual, aloha, tmp_path_factory):  # noqa: F811
    tmp = bimanual[0]
    ic = _conditions(bimanual[4], tmp_path_factory.mktemp("ic") / "heldout")
    real = _real_store(tmp_path_factory.mktemp("real") / "store")
    out = tmp_path_factory.mktemp("sweep") / "out"
    SEEN.clear()
    assert _sweep(ic, tmp / "run", out, "--real", str(real), "--family", "aloha", policies=_served(aloha)) == 0
    return ic, tmp / "run", real, out, list(SEEN)


def test_records_and_what_the_scorer_sees(swept):
    ic, _, _, out, seen = swept
    recs = [json.loads(x) for x in (out / "results.jsonl").read_text().splitlines()]
    assert len(recs) == 3 * 4 and {r["mode"] for r in recs} == {"online"}
    ids = EpisodeStore(ic).episode_ids()
    assert sorted((r["policy"], r["seed"]) for r in recs) == sorted((p, i) for p in REAL for i in range(4))
    for r in recs:
        assert r["episode"] == ids[r["seed"]] and r["block"] == ("evaluation" if r["seed"] < 2 else "calibration")
        assert r["num_chunks"] == 2 and len(r["u_raw"]) == 2 and r["outcomes"] == r["outcomes_by_cut"]["2"]
        want = {"hold": (False, False), "half": (False, True), "reach": (True, True)}[r["policy"]]
        assert (r["outcomes"]["success"], r["outcomes"]["moved"]) == want, r
    v = seen[0]  # whole rollouts: the last context frame + 2 chunks of 3 frames, every view; the imagined joints
    assert v.frames.dtype == np.uint8 and v.frames.shape[0] == 4 and v.frames.shape[2:] == (H, W, 3)
    assert max(x.frames.shape[1] for x in seen) == 7 and v.state.shape == (v.frames.shape[1], A)
    assert v.instruction == "fold the towel" and v.id in ids and not hasattr(v, "policy")
    with np.load(out / "rollouts" / "reach" / "0_online.npz") as z:
        assert z["frames"].shape == (4, 7, H, W, 3) and z["states"].shape == (6, A)
    assert json.loads((out / "sweep.json").read_text())["kind"] == "initial_conditions"


def test_the_time_inside_the_world_models_compiled_calls_is_a_share_of_the_sweep(swept):
    """timing.json: the seconds spent inside the jitted rollout programs (here served policies act between chunk
    steps, in this process), a part of the sweep's wall time and not all of it; and the library versions and CPU
    the run's numerics depend on."""
    timing = json.loads((swept[3] / "timing.json").read_text())
    assert timing["model_workers"] == 1
    assert 0 < timing["seconds_in_world_model_calls"] < timing["seconds_last_run"]
    assert timing["share_in_world_model_calls"] == pytest.approx(
        timing["seconds_in_world_model_calls"] / timing["seconds_last_run"])
    import jax
    assert timing["environment"]["jax"] == jax.__version__ and timing["environment"]["cpu"]  # what numerics move with

def test_the_sweep_writes_each_policys_rates_in_lerobot_evals_shape_beside_its_report(swept):
    """OUT/report/eval_info/online/<policy>/eval_info.json: the evaluation block's success with its Wilson interval,
    as lerobot-eval's eval_info.json (the sweep writes them as `sc3 report` does)."""
    out = swept[3]
    files = sorted((out / "report" / "eval_info" / "online").glob("*/eval_info.json"))
    assert [f.parent.name for f in files] == sorted(REAL)
    info = json.loads((out / "report" / "eval_info" / "online" / "reach" / "eval_info.json").read_text())
    assert info["overall"]["n_episodes"] == 2 and info["overall"]["pc_success"] == 100.0  # reach succeeds twice
    assert info["overall"]["pc_success_ci95"][1] == 100.0 and info["overall"]["pc_success_ci95"][0] < 100.0


def test_the_served_policy_gets_openpi_aloha_observations(swept, aloha):
    """What crossed the wire: per condition and chunk one request of openpi's ALOHA layout -- the 4 cameras by
    name, each the model's view of that name letterboxed to 224x224 CHW uint8, the 14-D state, the episode's own
    prompt -- and its actions came back into the world model unchanged."""
    ic, _, _, out, _ = swept
    got = aloha.policy.requests
    assert len(got) == 4 * 2  # 4 conditions x 2 chunks
    for req in got:
        assert set(req) == {"images", "state", "prompt"} and req["prompt"] == "fold the towel"
        assert tuple(req["images"]) == ALOHA_CAMERAS and req["state"].dtype == np.float32
        assert req["state"].shape == (A,)
        for img in req["images"].values():
            assert img.dtype == np.uint8 and img.shape == (3, 224, 224)
    with np.load(out / "rollouts" / "half" / "0_online.npz") as z:  # the first request: condition 0, chunk 0
        first, actions = z["frames"][:, 0], z["actions"]
    for v, cam in enumerate(CAMS):  # the view of that name, not just some view
        sent = got[0]["images"][cam].transpose(1, 2, 0).astype(int)
        err = [np.abs(sent - resize_with_pad(first[w], 224, 224).astype(int)).mean() for w in range(len(CAMS))]
        assert int(np.argmin(err)) == v and err[v] < 2, (cam, err)
    np.testing.assert_allclose(actions[0], got[0]["state"] + np.float32(0.1), atol=1e-6)  # state + 0.1, back


def test_the_report_ranks_the_served_policy_with_the_others(swept, aloha):
    out = swept[3]
    t = json.loads((out / "report" / "report.json").read_text())
    # by success: half (moves, never far enough) ties hold; ties share a rank, listed by name
    assert [(p["policy"], p["rank"]) for p in t["policies"]] == [("reach", 1), ("half", 2), ("hold", 2)]
    assert json.loads((out / "sweep.json").read_text())["policies"][1] == f"half={aloha.url}"
    f = t["real"]["faithfulness"]["online"]  # half's real labels match its name, wherever it runs
    assert t["real"]["policies"]["half"]["rates"]["moved"]["value"] == 0.75
    for k in ("pearson", "mmrv"):
        assert f[k]["lo"] <= f[k]["value"] <= f[k]["hi"]


def test_rerun_adds_nothing(swept, aloha, capsys):
    ic, run, real, out, _ = swept
    before, asked = (out / "results.jsonl").read_text(), len(aloha.policy.requests)
    SEEN.clear()
    assert _sweep(ic, run, out, "--real", str(real), "--family", "aloha", policies=_served(aloha)) == 0
    assert (out / "results.jsonl").read_text() == before and not SEEN and len(aloha.policy.requests) == asked
    said = capsys.readouterr().out
    assert "ranking by success" in said and "report:" in said and "r " in said and "half (aloha)" in said
    # these conditions are copies of the training store's episodes (same dataset, same episode_index): said so
    assert "warning: 4 of the 4 initial conditions are episodes the world model trained on" in said
    assert _sweep(ic, run, out, "--real", str(real), policies=("hold", "reach")) == 2  # another sweep: refused
    assert "different sweep" in _error(capsys)


def test_ranking_and_faithfulness_in_report(swept):
    out = swept[3]
    t = json.loads((out / "report" / "report.json").read_text())
    assert (out / "report" / "report.md").read_text().startswith("# Sweep report: held-out episodes")
    ranked = [p["policy"] for p in t["policies"]]
    assert ranked[0] == "reach" and t["policies"][0]["rank"] == 1 and t["policies"][0]["p_best"] == 1.0
    rates = {p["policy"]: {c: v["value"] for c, v in p["rates"].items()} for p in t["policies"]}
    assert rates["half"] == {"moved": 1.0, "success": 0.0} and rates["hold"] == {"moved": 0.0, "success": 0.0}
    assert t["ranked_by"] == "success" and t["rollouts"] == {"evaluation": 6, "calibration": 6}
    r = t["real"]
    assert r["criteria"] == ["moved", "success"] and r["policies"]["half"]["rates"]["moved"]["value"] == 0.75
    f = r["faithfulness"]
    names = ("hold", "half", "reach")  # the sweep's order; criteria sorted: moved, success
    im = np.array([[rates[p]["moved"], rates[p]["success"]] for p in names])
    re = np.array([[np.mean(REAL[p][1]), np.mean(REAL[p][0])] for p in names])
    online = f["online"]
    assert online["points"] == 6 and abs(online["pearson"]["value"] - np.corrcoef(im.ravel(), re.ravel())[0, 1]) < 1e-9
    assert r["tau"]["chosen"] in ("inf", "0.5") and ("online_tau" in f) == (r["tau"]["chosen"] != "inf")
    assert {"online", "policy_blind", "ceiling"} <= set(f)
    for row in f:
        for k in ("pearson", "mmrv"):
            cell = f[row][k]
            assert {"value", "lo", "hi"} <= set(cell) and (np.isnan(cell["lo"]) or cell["lo"] <= cell["hi"])
    assert online["pearson"]["lo"] <= online["pearson"]["value"] <= online["pearson"]["hi"]
    assert online["vs_floor"]["pearson"]["value"] > 0  # the model knows which policy moves: better than a guess


def test_sc3_report_reads_the_store_and_takes_other_real_outcomes(swept, tmp_path, capsys):
    out, real = swept[3], swept[2]
    assert main(["report", str(out), "--out", str(tmp_path / "a")]) == 0  # the sweep's own --real, as written
    same = json.loads((tmp_path / "a" / "report.json").read_text())
    assert same == json.loads((out / "report" / "report.json").read_text())
    assert main(["report", str(out), "--out", str(tmp_path / "b"), "--real", str(real)]) == 0
    typed = json.loads((tmp_path / "b" / "report.json").read_text())["real"]
    assert {**typed, "kept": True} == same["real"] and not typed["kept"]  # the same outcomes, typed or kept
    capsys.readouterr()
    assert main(["report", str(out), "--out", str(tmp_path / "c"), "--real", str(tmp_path / "none")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("sc3 report: error: ") and "\n" not in err and "none" in err, err
    assert not (tmp_path / "c").exists()


def test_the_store_keeps_its_real_outcomes_and_reports_them_without_their_source(swept, tmp_path, monkeypatch):
    """--real is kept in the store as read (real.json, issue 76): a copy of the store, where the source is not (on
    another machine, its path would name whatever is there), reports the same real numbers from any directory."""
    from sc3_jax.evaluation import report

    out, real = swept[3], swept[2]
    kept = json.loads((out / "real.json").read_text())
    assert kept["format"] == 2 and kept["given"] == [str(real)] and len(kept["episodes"]) == 12
    copy = tmp_path / "copy"
    shutil.copytree(out, copy, ignore=shutil.ignore_patterns("rollouts", "report"))
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(labels, "read", lambda sources: pytest.fail(f"read {sources}, not the store"))
    t = report.compute(copy)
    assert json.dumps(t["real"]) == json.dumps(json.loads((out / "report" / "report.json").read_text())["real"])


def test_the_simulator_free_report_is_the_same_page_answering_first_with_no_machine_path(swept, tmp_path):
    import browser
    ic, run, real, out, _ = swept
    page = out / "report" / "report.html"
    dom = browser.dump_dom(page, tmp_path / "profile")
    browser.answers_first(dom)
    assert "better than a policy-blind guess" in dom.split('id="ranking"')[0] or "not distinguishable" in dom
    for name in ("report.md", "report.html"):
        text = (out / "report" / name).read_text()
        for path in (str(ic), str(run), str(real), str(out), str(tmp_path)):
            assert path not in text, (name, path)


def test_a_bad_scorer_spec_is_one_line(swept, capsys):
    ic, run, _, out, _ = swept
    for spec, words in (("test_ic_sweep:nope", "no attribute 'nope'"), ("no_such_module_x:f", "cannot import"),
                        ("score", "package.module:attr")):
        assert _sweep(ic, run, out.parent / "bad", scorer=spec) == 2
        err = _error(capsys)
        assert spec in err and words in err, err
    assert not (out.parent / "bad").exists()  # refused before anything was written


def test_a_scorer_answering_otherwise_is_one_line(swept, capsys):
    ic, run, _, out, _ = swept
    assert _sweep(ic, run, out.parent / "wrong", policies=("hold",), scorer="test_ic_sweep:not_a_dict") == 2
    err = _error(capsys)
    assert "test_ic_sweep:not_a_dict" in err and "float" in err and "{criterion: bool}" in err, err


def test_family_mistakes_are_one_line(swept, aloha, capsys):
    ic, run, _, out, _ = swept
    for policies, family, words in (
            (_served(aloha), ["pi0"], ("--family pi0", "native, droid, libero, aloha")),
            (_served(aloha), ["hold=aloha"], ("--family hold=aloha", "'hold' is not a ws:// policy")),
            (("hold", "reach"), ["aloha"], ("--family aloha", "--policies has none")),
            (_served(aloha), ["aloha", "half=droid", "half=aloha"], ("--family half=aloha", "already has"))):
        assert _sweep(ic, run, out.parent / "fam", "--family", *family, policies=policies) == 2
        err = _error(capsys)
        assert all(w in err for w in words), err
    assert not (out.parent / "fam").exists()
    with pytest.raises(UserError, match=r"--family aloha: openpi's aloha layout sends 4 cameras .* has 3 views"):
        for_world_model("aloha", ("a", "b", "c"), ["x"], "--family aloha")
    # the cameras go by the model's view names whatever their order; others by the preset's order
    imgs = np.stack([np.full((4, 4, 3), v, np.uint8) for v in range(4)])
    for views, want in ((("cam_low", "cam_right_wrist", "cam_high", "cam_left_wrist"), [2, 0, 3, 1]),
                        (("a", "b", "c", "d"), [0, 1, 2, 3])):
        sent = for_world_model("aloha", views, ["fold"], "--family aloha").to_family(
            {"images": imgs, "state": np.zeros(A), "task": 0})
        assert [int(sent["images"][c].max()) for c in ALOHA_CAMERAS] == want and sent["prompt"] == "fold"
    quiet = for_world_model("aloha", CAMS, [""], "--family aloha").to_family(
        {"images": imgs, "state": np.zeros(A), "task": 0})
    assert "prompt" not in quiet  # an episode without a prompt: the server's default prompt applies


def test_sc3_rollout_of_a_module_attr_policy(swept, tmp_path, capsys):
    """`sc3 rollout` (the command) on the bimanual model from the held-out store: a 14-D policy, 4 views, 2
    chunks of 3 frames; the policy drove it (each chunk's target = the observed state + 0.3). tau is left at its
    default, which for joint targets is no early stop (0.02 rad would stop every rollout at its first chunk)."""
    ic, run, _, _, _ = swept
    assert main(["rollout", "--world-model", str(run), "--policy", "test_ic_sweep:reach", "--data",
                 str(ic), "--out", str(tmp_path / "ro"), "--episodes", "2", "--batch", "2",
                 "--rollout.episode-seconds", "0.6", "--no-progress"]) == 0
    with np.load(tmp_path / "ro" / "rollout.npz") as z:
        assert z["frames"].shape == (2, 4, 6, H, W, 3) and z["actions"].shape == z["states"].shape == (2, 6, A)
        assert list(z["episode_ids"]) == EpisodeStore(ic).episode_ids()[:2]
        np.testing.assert_allclose(z["actions"][:, 3], z["actions"][:, 0] + 0.3, atol=1e-5)
    summary = json.loads((tmp_path / "ro" / "summary.json").read_text())
    assert summary["num_chunks"] == 2 and summary["keep_frames"] == 3 and summary["stopped"] == 0
    assert summary["success"] == {"available": False, "note": no_scorer(None, None)[1]}  # no --benchmark: no scorer
    assert sorted(p.name for p in (tmp_path / "ro").glob("*.mp4")) == sorted(
        f"{e}_{v}.mp4" for e in summary["episodes"] for v in CAMS)
    assert capsys.readouterr().out.strip().splitlines()[-1].startswith(f"wrote {tmp_path / 'ro'}/: rollout.npz")


def test_sc3_rollout_of_a_served_aloha_policy(swept, aloha, tmp_path):
    """`sc3 rollout --family aloha` sends what the sweep sends: each episode's own prompt, the cameras by name."""
    ic, run, _, _, _ = swept
    before = len(aloha.policy.requests)
    assert main(["rollout", "--world-model", str(run), "--policy", aloha.url, "--family", "aloha",
                 "--data", str(ic), "--out", str(tmp_path / "ro"), "--episodes", "1",
                 "--rollout.episode-seconds", "0.3", "--no-progress"]) == 0
    got = aloha.policy.requests[before:]
    assert len(got) == 1 and got[0]["prompt"] == "fold the towel" and tuple(got[0]["images"]) == ALOHA_CAMERAS
    with np.load(tmp_path / "ro" / "rollout.npz") as z:
        first = z["frames"][0][:, 0]
        np.testing.assert_allclose(z["actions"][0, 0], got[0]["state"] + np.float32(0.1), atol=1e-6)
    sent = got[0]["images"]["cam_low"].transpose(1, 2, 0).astype(int)
    assert np.abs(sent - resize_with_pad(first[CAMS.index("cam_low")], 224, 224).astype(int)).mean() < 2


def test_policy_action_dim_mismatch_is_one_line(swept, capsys):
    ic, run, _, out, _ = swept
    assert _sweep(ic, run, out.parent / "seven", policies=("hold", "seven")) == 2
    err = _error(capsys)
    assert "seven=test_ic_sweep:seven" in err and "7-D" in err and "14-D" in err, err


def test_real_outcome_sources(tmp_path):
    pytest.importorskip("pyarrow")
    st = _real_store(tmp_path / "st")
    got = labels.read([str(st)])
    assert len(got) == 12 and {e.policy for e in got} == set(REAL)
    assert got[0].outcomes == {"success": False, "moved": True}  # half0 (sorted ids); "objects" is not a criterion
    assert {e.policy for e in labels.read([f"other={st}"])} == {"other"}
    path = tmp_path / "real.csv"
    with open(path, "w", newline="") as fh:
        csv.writer(fh).writerows([["policy", "episode", "success"], ["a", "e1", "true"], ["b", "e2", "0"]])
    assert [(e.policy, e.outcomes) for e in labels.read([str(path)])] == [("a", {"success": True}),
                                                                           ("b", {"success": False})]
    path.write_text("policy,success\na,maybe\n")
    with pytest.raises(UserError, match=r"real.csv:2: column 'success' is 'maybe'"):
        labels.read([str(path)])
    # a LeRobot dataset's next.success (any frame true = success), named by NAME=
    pytest.importorskip("av")
    from sc3_jax.data.lerobot_write import RawEpisode, write_lerobot

    import pyarrow as pa
    import pyarrow.parquet as pq

    flags = {0: [False, False, True], 1: [False, False, False]}
    eps = [RawEpisode({"observation.images.cam": np.zeros((3, 8, 8, 3), np.uint8)}, np.zeros((3, 2), np.float32),
                      "t") for _ in flags]
    write_lerobot(tmp_path / "lr", eps, 20, image_dtype="image")
    for f in (tmp_path / "lr" / "data").glob("**/*.parquet"):  # LeRobot's column: a plain bool per frame
        t = pq.read_table(f)
        col = [flags[int(e)][int(i)] for e, i in zip(t["episode_index"].to_pylist(), t["frame_index"].to_pylist())]
        pq.write_table(t.append_column("next.success", pa.array(col, pa.bool_())), f)
    got = labels.read([f"pi0={tmp_path / 'lr'}"])
    assert [(e.policy, e.outcomes["success"]) for e in got] == [("pi0", True), ("pi0", False)]
    with pytest.raises(UserError, match="NAME="):
        labels.read([str(tmp_path / "lr")])
    # a store without the policy's name
    bare = EpisodeStore(tmp_path / "bare", views=["cam"], fps=20, image_size=(4, 4), create=True,
                        action_space=ActionSpace("absolute", 1), has_pose=False)
    bare.write(Episode("e0", {"cam": np.zeros((1, 4, 4, 3), np.uint8)}, np.zeros((1, 1), np.float32), None, "",
                       {"labels": {"success": True}}))
    with pytest.raises(UserError) as e:
        labels.read([str(tmp_path / "bare")])
    assert "'policy'" in str(e.value) and "e0" in str(e.value) and "\n" not in str(e.value)

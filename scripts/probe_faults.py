#!/usr/bin/env python
"""A fault probe of the `sc3` command line (issue 66): numeric options at their edges, damaged input files of every
kind, output paths that are files or links, interrupts at several phases, resumes with changed flags, bad clients of
the policy server, and the issue's own cases re-run as written.

It makes its own tiny fixtures in a temporary directory (a 2-step `sc3 demo` model and its stores, an exported copy,
a finished tiny sweep, a results store, a LeRobot dataset), runs each case as a subprocess with a timeout on a fresh
copy of them, and classifies it:

  handled   one clear line (non-zero exit, no traceback, a last stderr line that says what is wrong), the correct
            result (exit 0 and the case's check passes), or exit 130 and its one line for an interrupt
  traceback a Python traceback, a signal (segfault) or an exit 130 missing its line
  hang      the case ran past its timeout (or an interrupt did not end the command)
  silent    exit 0 where a refusal was due, or a check of the result that fails
  outside   a file outside the case's named output changed (its inputs, the current directory, a link's target)

    python scripts/probe_faults.py                 # every case (13.5 min on 2 shared cores, 2026-12-02)
    python scripts/probe_faults.py --quick         # a subset, a few minutes
    python scripts/probe_faults.py --set issue     # only issue 66's cases as written
    python scripts/probe_faults.py --only rollout  # cases whose name holds a word
    python scripts/probe_faults.py --keep DIR      # keep the fixtures and the cases' directories in DIR

Exit 0 when every case is handled, 1 otherwise. Runs nice'd; ``--jobs`` cases at once (default 2).
"""
from __future__ import annotations

import argparse
import concurrent.futures
import contextlib
import dataclasses
import gzip
import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path
from typing import Callable

ROOT = Path(__file__).resolve().parents[1]
SC3 = [sys.executable, "-m", "sc3_jax.cli"]
INTERRUPTED = "interrupted"
CLASSES = ["handled", "traceback", "hang", "silent", "outside"]


# -- one case -------------------------------------------------------------------------------------------------------
@dataclasses.dataclass
class Case:
    name: str
    argv: list[str]  # placeholders: {in} the case's inputs, {out} its output (absent), {cwd}, {victim}
    group: str = "new"  # "issue": issue 66's case as written; "new": the new probe's
    expect: str = "error"  # error | ok | either | interrupt
    damage: Callable[[Path], None] | None = None  # applied to the case's directory before the command
    check: Callable[[Path, "Result"], str | None] | None = None  # what is wrong with the result (None: right)
    writes: tuple[str, ...] = ()  # paths (of the case dir) the command may change besides out/
    timeout: float = 90.0
    interrupt_after: str | float | None = None  # a stdout/stderr text (or seconds) after which SIGINT goes out
    interrupt_delay: float = 0.0
    pre: list[list[str]] = dataclasses.field(default_factory=list)  # commands run first (must exit 0)
    quick: bool = False
    fn: Callable[[Path], tuple[str, str]] | None = None  # an in-probe case (the server's): (class, what it saw)
    env: dict = dataclasses.field(default_factory=dict)  # the command's environment beyond env_for's


@dataclasses.dataclass
class Result:
    rc: int | None
    stdout: str
    stderr: str
    seconds: float


def last_line(text: str) -> str:
    lines = [x for x in text.replace("\r", "\n").splitlines() if x.strip()]
    return lines[-1].strip() if lines else ""


def snapshot(root: Path, skip: tuple[str, ...] = ()) -> dict[str, tuple]:
    """Every path under ``root`` (links not followed) with its kind, size and content digest."""
    out = {}
    for dirpath, dirnames, filenames in os.walk(root, followlinks=False):
        rel_dir = os.path.relpath(dirpath, root)
        if rel_dir != "." and any(rel_dir == s or rel_dir.startswith(s + "/") for s in skip):
            dirnames[:] = []
            continue
        for name in dirnames + filenames:
            p = Path(dirpath) / name
            rel = os.path.relpath(p, root)
            if any(rel == s or rel.startswith(s + "/") for s in skip):
                continue
            st = os.lstat(p)
            if os.path.islink(p):
                out[rel] = ("link", os.readlink(p))
            elif os.path.isdir(p) and not os.path.islink(p):
                out[rel] = ("dir",)
            elif Path(p).is_fifo():
                out[rel] = ("fifo",)
            else:
                h = hashlib.sha1()
                with open(p, "rb") as f:
                    for block in iter(lambda: f.read(1 << 20), b""):
                        h.update(block)
                out[rel] = ("file", st.st_size, h.hexdigest())
    return out


def _ours_in_temp() -> set[str]:
    return {p.name for p in Path(tempfile.gettempdir()).glob("sc3*")}


def fill(argv: list[str], case_dir: Path) -> list[str]:
    subs = {"{in}": str(case_dir / "in"), "{out}": str(case_dir / "out"), "{cwd}": str(case_dir / "cwd"),
            "{victim}": str(case_dir / "victim"), "{fix}": FIXTURES[0] if FIXTURES else "{fix}"}
    res = []
    for a in argv:
        for k, v in subs.items():
            a = a.replace(k, v)
        res.append(a)
    return res


FIXTURES: list[str] = []  # the fixtures' own directory: a copied workdir records its training store's path there
CODE: list[str] = []  # --code DIR: that checkout's sc3_jax in front of the installed one (a probe of an old tree)


def env_for(case_dir: Path) -> dict:
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "JAX_PLATFORMS": "cpu", "COLUMNS": "200",
           "PYTHONPATH": os.pathsep.join([*CODE, str(case_dir / "in"), os.environ.get("PYTHONPATH", "")]),
           "XLA_FLAGS": "--xla_backend_optimization_level=0", "TQDM_DISABLE": "1"}
    return env


def run_cmd(argv: list[str], cwd: Path, env: dict, timeout: float, interrupt_after=None,
            interrupt_delay: float = 0.0) -> Result:
    """Run in a session of its own (SIGINT to its group is Ctrl-C in a terminal); rc None: past its timeout."""
    t0 = start = time.monotonic()
    with tempfile.TemporaryFile("w+") as out, tempfile.TemporaryFile("w+") as err:
        proc = subprocess.Popen(["nice", "-n", "5", *argv], cwd=cwd, env=env, stdout=out, stderr=err,
                                stdin=subprocess.DEVNULL, start_new_session=True,
                                preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
        sent = interrupt_after is None
        rc, t_up = None, None
        while time.monotonic() - t0 < timeout:
            rc = proc.poll()
            if rc is not None:
                break
            if not sent:
                if isinstance(interrupt_after, (int, float)):
                    # seconds from when the interpreter answers SIGINT: a Ctrl-C before that ends any Python
                    # program (its default action; rc -2, nothing printed), so on a loaded machine a fixed delay
                    # from the start measured the interpreter's start-up, not the command
                    t_up = t_up or (time.monotonic() if _catches_sigint(proc.pid) else None)
                    ready = t_up is not None and time.monotonic() - t_up >= interrupt_after
                else:
                    ready = _seen(out, err, interrupt_after)
                if ready:
                    time.sleep(interrupt_delay)
                    with contextlib.suppress(ProcessLookupError):
                        os.killpg(proc.pid, signal.SIGINT)
                    sent = True
                    t0 = min(t0, time.monotonic() - timeout + 60)  # an interrupted command has a minute to end
            time.sleep(0.1)
        if rc is None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        else:
            time.sleep(0.2)  # a worker writing after the command's last line would show now
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        out.seek(0)
        err.seek(0)
        return Result(rc, out.read(), err.read(), time.monotonic() - start)


def _catches_sigint(pid: int) -> bool:
    """Whether process ``pid`` has a handler for SIGINT (its /proc status's caught-signals mask; no /proc: yes)."""
    if not Path("/proc/self/status").exists():
        return True
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("SigCgt:"):
                return bool(int(line.split()[1], 16) & (1 << (signal.SIGINT - 1)))
    except (OSError, ValueError):
        pass
    return False


def _seen(out, err, text: str) -> bool:
    for f in (out, err):
        f.flush()
        pos = f.tell()
        f.seek(0)
        found = text in f.read()
        f.seek(pos)
        if found:
            return True
    return False


def classify(case: Case, res: Result, changed: list[str]) -> tuple[str, str]:
    err = res.stderr
    line = last_line(err)
    if res.rc is None:
        return "hang", f"past {case.timeout:.0f} s; {line[:160]}"
    if changed:
        return "outside", f"changed {changed[:3]}"
    if "Traceback (most recent call last)" in err or res.rc < 0 or res.rc in (134, 139):
        tb = [x for x in err.splitlines() if x and not x.startswith(" ")]
        return "traceback", f"rc {res.rc}: {(tb[-1] if tb else line)[:200]}"
    if case.expect == "interrupt":
        if res.rc == 130 and INTERRUPTED in line:
            return "handled", f"130: {line[:160]}"
        if res.rc == 0:
            return "silent", "exit 0: the interrupt came too late or was swallowed"
        return "traceback", f"rc {res.rc} for an interrupt: {line[:160]}"
    if res.rc == 0:
        if case.expect == "error":
            return "silent", f"exit 0 where a refusal was due: {last_line(res.stdout)[:160]}"
        wrong = case.check(Path(case._dir), res) if case.check else None  # type: ignore[attr-defined]
        return ("silent", f"exit 0 but {wrong}") if wrong else ("handled", f"ok: {last_line(res.stdout)[:120]}")
    if case.expect == "ok":
        return ("handled" if line else "silent"), f"refused where it should run: rc {res.rc}: {line[:160]}"
    if not line or len(line) > 600:
        return "silent", f"rc {res.rc} with no clear last line"
    if case.check and case.expect == "either":
        wrong = case.check(Path(case._dir), res)  # type: ignore[attr-defined]
        if wrong:
            return "silent", f"rc {res.rc} but {wrong}"
    return "handled", f"rc {res.rc}: {line[:160]}"


def run_case(case: Case, fixtures: Path, work: Path, index: int) -> dict:
    case_dir = work / f"{index:03d}"
    if case_dir.exists():
        shutil.rmtree(case_dir)
    case_dir.mkdir(parents=True)
    case._dir = str(case_dir)  # type: ignore[attr-defined]
    shutil.copytree(fixtures, case_dir / "in", symlinks=True)
    (case_dir / "cwd").mkdir()
    (case_dir / "victim").mkdir()
    (case_dir / "victim" / "keep.txt").write_text("not yours to overwrite\n")
    env = {**env_for(case_dir), **case.env}
    t0 = time.monotonic()
    try:
        for pre in case.pre:
            r = run_cmd([*SC3, *fill(pre, case_dir)], case_dir / "cwd", env, 300)
            if r.rc != 0:
                return dict(name=case.name, group=case.group, cls="traceback" if "Traceback" in r.stderr else
                            "silent", said=f"setup {pre[:2]} rc {r.rc}: {last_line(r.stderr)[:160]}",
                            seconds=time.monotonic() - t0, argv=" ".join(pre), rc=r.rc)
        if case.damage:  # after the commands run first: it may damage what they wrote
            case.damage(case_dir)
        if case.fn is not None:
            cls, said = case.fn(case_dir)
            return dict(name=case.name, group=case.group, cls=cls, said=said, seconds=time.monotonic() - t0,
                        argv="(in-probe client)", rc=None, stderr_last=said)
        skip = ("out", *case.writes)
        before = snapshot(case_dir, skip)
        temp_before = _ours_in_temp()
        argv = fill(case.argv, case_dir)
        res = run_cmd([*SC3, *argv], case_dir / "cwd", env, case.timeout, case.interrupt_after, case.interrupt_delay)
        after = snapshot(case_dir, skip)
        changed = sorted(k for k in set(before) | set(after) if before.get(k) != after.get(k))
        changed += [f"$TMPDIR/{n}" for n in sorted(_ours_in_temp() - temp_before)]
        cls, said = classify(case, res, changed)
        return dict(name=case.name, group=case.group, cls=cls, said=said, seconds=round(res.seconds, 1),
                    argv="sc3 " + " ".join(argv).replace(str(case_dir), "CASE"), rc=res.rc,
                    stderr_last=last_line(res.stderr)[:300])
    except Exception as e:  # noqa: BLE001  (the probe's own fault: reported, never hidden)
        return dict(name=case.name, group=case.group, cls="traceback", said=f"probe error {type(e).__name__}: {e}",
                    seconds=time.monotonic() - t0, argv=" ".join(case.argv), rc=None)


# -- fixtures -------------------------------------------------------------------------------------------------------
SCORER = '''
def score(view):
    """A scorer of imagined rollouts: success when the last frame is brighter than the first."""
    import numpy as np
    f = np.asarray(view.frames, np.float32)
    return {"success": bool(f[:, -1].mean() > f[:, 0].mean())}
'''


def make_fixtures(fix: Path) -> None:
    """The tiny inputs every case copies: ``demo/`` (a 2-step `sc3 demo`: train/ the workdir, episodes/ its store,
    heldout/ 16 held-out episodes), ``export/`` (the same model exported, params.npz), ``sweep1/`` (a finished
    `sc3 sweep episodes` store of it), ``results/`` and ``results_ep/`` (archived sweeps), ``lerobot/``, ``real.csv``,
    ``ic.npz`` (one initial condition), ``probe_scorer.py``."""
    import numpy as np

    fix.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "PYTHONPATH": str(fix), "TQDM_DISABLE": "1",
           "XLA_FLAGS": "--xla_backend_optimization_level=0"}
    (fix / "probe_scorer.py").write_text(SCORER)
    t0 = time.monotonic()
    r = subprocess.run(["nice", "-n", "5", *SC3, "demo", "--out", str(fix / "demo"), "--steps", "2", "--episodes",
                        "4", "--batch", "4"], env=env, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr[-3000:]
    code = textwrap.dedent(f"""
        import numpy as np, json, shutil, gzip
        from pathlib import Path
        from sc3_jax.model import checkpoint
        fix = Path({str(fix)!r})
        cfg, stats, params = checkpoint.load(fix / "demo" / "train")
        checkpoint.save(fix / "export", cfg, stats, params, np.float32)
        from sc3_jax.data.lerobot_write import RawEpisode, write_lerobot
        eps = [RawEpisode({{"observation.images.cam": np.full((3, 8, 8, 3), 40 * i, np.uint8)}},
                          np.zeros((3, 2), np.float32), "t", np.zeros((3, 2), np.float32)) for i in range(2)]
        write_lerobot(fix / "lerobot", eps, 10)
        print(cfg.model.action_dim, cfg.model.num_views, cfg.data.context_frames)
    """)
    r = subprocess.run(["nice", "-n", "5", sys.executable, "-c", code], env=env, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr[-3000:]
    action_dim, views, context = map(int, r.stdout.split()[-3:])
    np.savez(fix / "ic.npz", frames=np.full((1, views, context, 16, 16, 3), 90, np.uint8),
             state=np.zeros((1, action_dim), np.float32))
    for name, src in (("results", "cmd1_s1"), ("results_ep", "so101_sweep36")):
        d = fix / name
        d.mkdir()
        for p in (ROOT / "docs" / "stores" / src).iterdir():
            if p.name == "results.jsonl.gz":
                (d / "results.jsonl").write_bytes(gzip.decompress(p.read_bytes()))
            elif p.is_file():
                shutil.copy(p, d / p.name)
    (fix / "real.csv").write_text("policy,episode,success\nz,seed0,1\n")
    r = subprocess.run(["nice", "-n", "5", *SC3, *SWEEP1(fix)], env=env, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr[-3000:]
    print(f"fixtures in {time.monotonic() - t0:.0f} s", file=sys.stderr)


def SWEEP1(root, out=None) -> list[str]:  # noqa: N802  (the finished sweep of the fixtures, and the resumes of it)
    root = str(root)
    return ["sweep", "episodes", "--data", f"{root}/demo/heldout", "--world-model", f"{root}/demo/train",
            "--policies", "z=zero", "r=random", "--scorer", "probe_scorer:score", "--out", out or f"{root}/sweep1",
            "--episodes", "2", "--calibration-episodes", "0", "--episode-seconds", "0.6", "--no-progress"]


# -- the cases ------------------------------------------------------------------------------------------------------
WM, STORE, TRAIN, EXPORT = "{in}/demo/train", "{in}/demo/heldout", "{in}/demo/episodes", "{in}/export"


def rollout(*extra, wm=WM, data=STORE):
    return ["rollout", "--world-model", wm, "--policy", "zero", "--data", data, "--episodes", "1", "--out",
            "{out}/r", "--no-video", "--no-progress", "--benchmark", "none", "--rollout.episode-seconds", "0.6",
            *extra]


def rollout_ic(*extra):
    return rollout("--data", "{in}/ic.npz", *extra)


def diagnose(*extra):
    return ["diagnose", "--world-model", WM, "--data", STORE, "--episodes", "2", "--benchmark", "none",
            "--no-progress", "--stages", "teacher_forced", "--out", "{out}/d.json", *extra]


def train(*extra, workdir="{out}/wd"):
    return ["train", "--config", "tiny", "--data", TRAIN, "--batch", "4", "--train.workdir", workdir,
            "--train.steps", "1", "--train.no-progress", "--train.no-tensorboard", "--model.dim", "32",
            "--model.depth", "1", "--model.num-heads", "2", "--model.num-kv-heads", "1", "--model.mlp-dim", "64",
            *extra]


def sweep(*extra, out="{out}/s"):
    return ["sweep", "episodes", "--data", STORE, "--world-model", WM, "--policies", "z=zero", "--scorer",
            "probe_scorer:score", "--out", out, "--episodes", "1", "--calibration-episodes", "0",
            "--episode-seconds", "0.6", "--no-progress", *extra]


def report(*extra, store="{in}/results"):
    return ["report", store, "--out", "{out}/rep", "--draws", "10", *extra]


def imp(*extra):
    return ["data", "import-lerobot", "--data", "{in}/lerobot", "--out", "{out}/st", "--action-space", "absolute",
            *extra]


def exp(*extra, data=TRAIN):
    return ["data", "export-lerobot", "--data", data, "--out", "{out}/lr", *extra]


def tokenizer(*extra):
    return ["train-tokenizer", "--data", TRAIN, "--workdir", "{out}/tok", "--steps", "1", "--batch", "2",
            "--no-progress", "--eval-frames", "2", *extra]


def serve(*extra):
    return ["serve-policy", "--policy", "zero", *extra]


def has(*rels):
    def check(case_dir: Path, res: Result):
        missing = [r for r in rels if not (case_dir / r).exists()]
        return f"missing {missing}" if missing else None
    return check


def first_episode(case_dir: Path) -> Path:
    return sorted(p for p in (case_dir / "in" / "demo" / "episodes").iterdir() if p.is_dir())[0]


def damage_file(kind: str, where: Callable[[Path], Path]):
    """``kind`` done to the file ``where(case_dir)``."""
    import numpy as np

    def damage(case_dir: Path):
        p = where(case_dir)
        raw = p.read_bytes() if p.is_file() else b""
        if kind == "truncated":
            p.write_bytes(raw[: max(1, len(raw) // 2)])
        elif kind == "empty":
            p.write_bytes(b"")
        elif kind == "symlink out":
            target = case_dir / "victim" / p.name
            target.write_bytes(raw)
            p.unlink()
            p.symlink_to(target)
        elif kind == "directory":
            p.unlink()
            p.mkdir()
        elif kind == "fifo":
            p.unlink()
            os.mkfifo(p)  # nobody writes it: a reader that opens it blocks (a hang)
        elif kind in ("wrong dtype", "wrong shape"):
            if p.suffix == ".npy":
                x = np.load(p)
                y = x.astype(np.complex64) if kind == "wrong dtype" else x.reshape(-1)[: max(1, x.size // 3)]
                np.save(p, y)
            elif p.suffix == ".json":
                obj = json.loads(raw)
                if kind == "wrong dtype":
                    p.write_text(json.dumps(["not", "an", "object"]) if not isinstance(obj, list) else '{"a": 1}')
                else:
                    p.write_text(json.dumps({"unrelated": obj}))
            elif p.suffix == ".jsonl":
                lines = raw.decode().splitlines()
                rec = json.loads(lines[0])
                if kind == "wrong dtype":
                    rec = {k: (str(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else v)
                           for k, v in rec.items()}
                else:
                    rec = [rec]
                lines[0] = json.dumps(rec)
                p.write_text("\n".join(lines) + "\n")
            elif p.suffix == ".npz":
                with np.load(p) as z:
                    arrays = {k: z[k] for k in z.files}
                k = sorted(arrays)[0]
                arrays[k] = (arrays[k].astype(np.complex64) if kind == "wrong dtype"
                             else arrays[k].reshape(-1)[:1])
                np.savez(p, **arrays)
            else:  # csv
                p.write_text("policy,episode,success\nz,seed0,maybe\n" if kind == "wrong dtype"
                             else "a;b;c\n1;2;3\n")
        else:
            raise ValueError(kind)
    return damage


DAMAGES = ["truncated", "wrong dtype", "wrong shape", "empty", "symlink out", "directory", "fifo"]


def _npz_member(case_dir: Path) -> Path:
    return case_dir / "in" / "export" / "params.npz"


FILE_KINDS = {
    # name: (where, argv, damages): the command that reads it
    "episode frames .npy": (lambda d: sorted((first_episode(d) / "frames").iterdir())[0], exp(), DAMAGES),
    "episode actions.npy": (lambda d: first_episode(d) / "actions.npy", exp(), DAMAGES),
    "episode meta.json": (lambda d: first_episode(d) / "meta.json", exp(), DAMAGES),
    "store dataset.json": (lambda d: d / "in" / "demo" / "episodes" / "dataset.json", exp(), DAMAGES),
    "model config.json": (lambda d: d / "in" / "export" / "config.json", rollout(wm=EXPORT), DAMAGES),
    "model norm_stats.json": (lambda d: d / "in" / "export" / "norm_stats.json", rollout(wm=EXPORT), DAMAGES),
    "model params.npz": (_npz_member, rollout(wm=EXPORT), ["truncated", "wrong dtype", "wrong shape", "fifo"]),
    "workdir config.json": (lambda d: d / "in" / "demo" / "train" / "config.json", rollout(),
                            ["truncated", "symlink out", "directory"]),
    "results.jsonl": (lambda d: d / "in" / "results" / "results.jsonl", report(), DAMAGES),
    "sweep.json": (lambda d: d / "in" / "results" / "sweep.json", report(), DAMAGES),
    "real labels CSV": (lambda d: d / "in" / "real.csv", sweep("--real", "{in}/real.csv"), DAMAGES),
    "kept real.json": (lambda d: d / "in" / "results_ep" / "real.json", report(store="{in}/results_ep"), DAMAGES),
    "initial conditions .npz": (lambda d: d / "in" / "ic.npz", rollout_ic(), DAMAGES),
    "LeRobot info.json": (lambda d: d / "in" / "lerobot" / "meta" / "info.json", imp(), DAMAGES),
    "LeRobot episodes parquet": (lambda d: sorted((d / "in" / "lerobot" / "meta" / "episodes").rglob("*.parquet"))[0],
                                 imp(), ["truncated", "empty", "symlink out", "directory", "fifo"]),
    "sweep1 results.jsonl (resume)": (lambda d: d / "in" / "sweep1" / "results.jsonl",
                                      ["report", "{in}/sweep1", "--out", "{out}/rep", "--draws", "10"],
                                      ["truncated", "wrong dtype", "fifo"]),
}


def numeric_cases() -> list[Case]:
    """Every numeric option of every command at 0, -1, nan, inf, huge and a non-number (an option whose 0 or
    negative is meaningful is `either`: a correct run or one line)."""
    I, F = ["0", "-1", "10000000000"], ["0", "-1", "nan", "inf", "1e308"]  # noqa: E741
    table = [  # (command, builder, option, values, values that may run)
        ("rollout", rollout, "--episodes", I, ()), ("rollout", rollout, "--sample-steps", I, ()),
        ("rollout", rollout, "--inverse-steps", I, ("0",)), 
        ("rollout", rollout, "--start", I, ("0",)), ("rollout", rollout, "--batch", I, ()),
        ("rollout", rollout, "--data-fps", F, ()), ("rollout", rollout, "--seed", ["-1"], ()),
        ("rollout", rollout, "--rollout.tau", F, ("inf", "0", "1e308")),
        ("diagnose", diagnose, "--episodes", I, ()), ("diagnose", diagnose, "--cf-starts", I, ()),
        ("diagnose", diagnose, "--cf-fraction", F, ()), ("diagnose", diagnose, "--max-seconds", F, ()),
        ("diagnose", diagnose, "--batch", I, ()), 
        ("train", train, "--batch", I, ()), ("train", train, "--train.steps", I, ()),
        ("train", train, "--train.lr", F, ()), ("train", train, "--train.warmup-steps", ["-1", "10000000000"], ()),
        ("train", train, "--data.context-frames", I, ()),
        ("sweep", sweep, "--episodes", I, ()), ("sweep", sweep, "--calibration-episodes", ["-1", "10000000000"], ()),
        ("sweep", sweep, "--start", ["-1", "10000000000"], ()), ("sweep", sweep, "--batch", I, ()),
        ("sweep", sweep, "--episode-seconds", F, ()), ("sweep", sweep, "--taus", ["-1", "nan"], ()),
        ("report", report, "--draws", I, ()), ("report", report, "--videos", ["-1"], ()),
        ("report", report, "--taus", ["-1", "nan"], ()),
        ("import-lerobot", imp, "--fps", F, ()), ("export-lerobot", exp, "--crf", ["-1", "10000000000"], ()),
        ("serve-policy", serve, "--port", ["-1", "70000"], ()),
        ("serve-policy", serve, "--max-message-mb", F, ()), 
        ("serve-policy", serve, "--default-task", ["-1"], ()),
        ("train-tokenizer", tokenizer, "--steps", I, ()), ("train-tokenizer", tokenizer, "--batch", I, ()),
        ("train-tokenizer", tokenizer, "--lr", F, ()),
        ("demo", lambda *e: ["demo", "--out", "{out}/demo", "--steps", "1", "--episodes", "2", "--batch", "2", *e],
         "--episodes", I, ()),
        ("plan", lambda *e: ["plan", "--config", "tiny", "--no-compile", *e], "--batch", I, ("10000000000",)),
        ("plan", lambda *e: ["plan", "--config", "tiny", "--no-compile", *e], "--mfu", ["0", "nan", "2"], ()),
        ("curve", lambda *e: ["curve", "1={in}/results", "--out", "{out}/c", *e], "--draws", I, ()),
        ("train-state", lambda *e: ["train-state", "--world-model", WM, "--data", TRAIN, "--steps", "1",
                                    "--no-progress", *e], "--batch", I, ()),
        ("train-state", lambda *e: ["train-state", "--world-model", WM, "--data", TRAIN, "--steps", "1",
                                    "--no-progress", *e], "--lr", ["nan", "-1"], ()),
    ]
    cases, seen = [], set()
    for cmd, build, opt, values, may_run in table:
        if cmd not in seen:  # a non-number, once a command
            seen.add(cmd)
            values = [*values, "abc"]
        for v in values:
            quick = v == "nan" or (v == "-1" and opt in ("--episodes", "--batch"))
            cases.append(Case(f"{cmd} {opt} {v}", build(opt, v), expect="either" if v in may_run else "error",
                              timeout=150, quick=quick))
    for v in (["0", "0"], ["-5", "8"], ["8", "abc"], ["100000", "100000"]):
        cases.append(Case(f"import-lerobot --image-size {' '.join(v)}", imp("--image-size", *v)))
    for v in (["0"], ["-1", "2"], ["abc"]):
        cases.append(Case(f"serve-policy --image-size {' '.join(v)} 8", serve("--image-size", *v, "8")
                          if v != ["-1", "2"] else serve("--image-size", "-1", "2")))
    for v in ("2/2", "3/2", "-1/2", "1/0", "x", "1/2/3"):
        cases.append(Case(f"sweep bench --shard {v}", ["sweep", "bench", "--world-model", WM, "--out", "{out}/b",
                                                        "--shard", v, "--no-progress"]))
    for opt, v in (("--workers", "-1"), ("--episodes", "0"), ("--ceiling-episodes", "-1"),
                   ("--calibration-episodes", "-1"), ("--episode-seconds", "nan"), ("--batch", "0")):
        cases.append(Case(f"sweep bench {opt} {v}", ["sweep", "bench", "--world-model", WM, "--out", "{out}/b",
                                                      opt, v, "--no-progress"]))
    return cases


# damages that are no fault: a file the user names (a labels CSV, an .npz), a model's files or a LeRobot dataset's
# may be links anywhere (the Hugging Face cache is links into its blobs); only a store's own files must be its own.
# A meta.json without a prompt is an episode without one (its keys are optional), and a results.jsonl cut in its
# last line is read without that line while its sweep runs, and refused in one line once none does (documented)
NOT_A_FAULT = {("real labels CSV", "symlink out"), ("initial conditions .npz", "symlink out"),
               ("model config.json", "symlink out"), ("model norm_stats.json", "symlink out"),
               ("model params.npz", "symlink out"), ("workdir config.json", "symlink out"),
               ("LeRobot info.json", "symlink out"), ("LeRobot episodes parquet", "symlink out"),
               ("episode meta.json", "wrong shape"), ("sweep1 results.jsonl (resume)", "truncated")}


def file_cases() -> list[Case]:
    cases = []
    for kind, (where, argv, damages) in FILE_KINDS.items():
        for d in damages:
            cases.append(Case(f"{kind}: {d}", argv, damage=damage_file(d, where), timeout=120,
                              expect="either" if (kind, d) in NOT_A_FAULT else "error",
                              quick=d == "fifo" or (d == "truncated" and "episode" in kind)))
    return cases


def output_cases() -> list[Case]:
    """Every command's output path as an existing file, a path under a file, and a symlink to a directory
    outside (root ignores permissions, so an unwritable directory is tried only for other users)."""
    def link_out(rel):
        def damage(case_dir: Path):
            p = case_dir / rel
            p.parent.mkdir(parents=True, exist_ok=True)
            p.symlink_to(case_dir / "victim", target_is_directory=True)
        return damage

    def a_file(rel):
        def damage(case_dir: Path):
            p = case_dir / rel
            p.parent.mkdir(parents=True, exist_ok=True)
            p.write_text("a file\n")
        return damage

    outs = {  # command: (argv with its output at {out}/o, the output's rel path)
        "rollout --out": (rollout("--out", "{out}/o"), "out/o"),
        "diagnose --out": (diagnose("--out", "{out}/o"), "out/o"),
        "diagnose --filmstrips": (diagnose("--filmstrips", "{out}/o"), "out/o"),
        "train --train.workdir": (train(workdir="{out}/o"), "out/o"),
        "sweep --out": (sweep(out="{out}/o"), "out/o"),
        "report --out": (report("--out", "{out}/o"), "out/o"),
        "import-lerobot --out": (imp("--out", "{out}/o"), "out/o"),
        "export-lerobot --out": (exp("--out", "{out}/o"), "out/o"),
        "train-tokenizer --workdir": (tokenizer("--workdir", "{out}/o"), "out/o"),
        "demo --out": (["demo", "--out", "{out}/o", "--steps", "1", "--episodes", "2", "--batch", "2"], "out/o"),
        "curve --out": (["curve", "1={in}/results", "--out", "{out}/o"], "out/o"),
        "diagnose-table --out": (["diagnose-table", "--world-model", WM, "--out", "{out}/o"], "out/o"),
    }
    cases = []
    for name, (argv, rel) in outs.items():
        file_ok = name in ("diagnose --out", "diagnose-table --out")  # these name a file
        cases.append(Case(f"{name} is a symlink out", argv, damage=link_out(rel), timeout=150,
                          expect="error", quick=name.startswith(("report", "rollout"))))
        if not file_ok:
            cases.append(Case(f"{name} is a file", argv, damage=a_file(rel), timeout=150))
        under = [a.replace("{out}/o", "{out}/f/o") for a in argv]
        cases.append(Case(f"{name} is under a file", under, damage=a_file("out/f"), timeout=150))
    return cases


def interrupt_cases() -> list[Case]:
    return [
        Case("Ctrl-C rollout while importing", rollout(), expect="interrupt", interrupt_after=0.5, quick=True),
        Case("Ctrl-C rollout while compiling", rollout("--episodes", "4", "--rollout.episode-seconds", "4"),
             expect="interrupt", interrupt_after=6.0),
        Case("Ctrl-C diagnose while running", diagnose(), expect="interrupt", interrupt_after=8.0),
        Case("Ctrl-C sweep while loading", sweep("--episodes", "12", "--episode-seconds", "3"), expect="interrupt",
             interrupt_after=4.0, quick=True),
        Case("Ctrl-C train while loading data", train("--train.steps", "50"), expect="interrupt",
             interrupt_after=3.0),
        Case("Ctrl-C train after its first step", train("--train.steps", "400", "--train.log-every", "1"),
             expect="interrupt", interrupt_after="step", interrupt_delay=2.0, timeout=240),
        Case("Ctrl-C demo while generating", ["demo", "--out", "{out}/demo", "--steps", "2", "--episodes", "40",
                                              "--batch", "2"], expect="interrupt", interrupt_after="[1/3]"),
        Case("Ctrl-C demo while training", ["demo", "--out", "{out}/demo", "--steps", "200", "--episodes", "2",
                                            "--batch", "2"], expect="interrupt", interrupt_after="[2/3]",
             interrupt_delay=12.0, timeout=240),
        Case("Ctrl-C import-lerobot", imp(), expect="interrupt", interrupt_after=0.15),  # it ends within a second
        Case("Ctrl-C export-lerobot", exp(data=STORE), expect="interrupt", interrupt_after=0.8),
        Case("Ctrl-C report", report("--draws", "100000"), expect="interrupt", interrupt_after=4.0),
        Case("Ctrl-C train-tokenizer", tokenizer("--steps", "200"), expect="interrupt", interrupt_after=6.0),
        Case("Ctrl-C plan while compiling", ["plan", "--config", "tiny", "--compile"], expect="interrupt",
             interrupt_after=3.0),
        Case("Ctrl-C serve-policy", serve("--port", "0"), expect="interrupt", interrupt_after="serving"),
    ]


def resume_cases() -> list[Case]:
    """Resumes with changed flags: a changed model shape / data / steps of a training run, a sweep's conditions,
    policies, scorer, model."""
    wd, recorded = "{in}/demo/train", "{fix}/demo/episodes"  # the copied workdir names the fixtures' store
    sw = SWEEP1("{fix}", out="{in}/sweep1")  # the copy of the fixtures' sweep, resumed on its own inputs
    cases = [
        Case("train resumed with another --model.dim", ["train", "--config", "tiny", "--data", recorded,
                                                          "--train.workdir", wd, "--train.steps", "3", "--model.dim",
                                                          "48", "--train.no-progress"]),
        Case("train resumed on other data", ["train", "--config", "tiny", "--data", STORE, "--train.workdir", wd,
                                             "--train.steps", "3", "--train.no-progress", "--batch", "4"],
             expect="either"),
        Case("train resumed with more steps", ["train", "--config", "tiny", "--data", recorded, "--train.workdir", wd,
                                               "--train.steps", "3", "--batch", "4", "--train.no-progress",
                                               "--train.no-tensorboard"], expect="either",
             writes=("in/demo/train",), timeout=240, check=_one_row_per_step),
        Case("train resumed with fewer steps", ["train", "--config", "tiny", "--data", recorded, "--train.workdir", wd,
                                                "--train.steps", "1", "--batch", "4", "--train.no-progress"],
             expect="either", writes=("in/demo/train",)),
        Case("sweep resumed with other --episode-seconds", [*sw[:-2], "1.2", "--no-progress"]),
        Case("sweep resumed with other --policies", [*sw, "--policies", "z=zero", "l=linear"]),
        Case("sweep resumed with other --scorer", [*sw, "--scorer", "probe_scorer:nope"]),
        Case("sweep resumed with another --world-model", [*sw, "--world-model", "{fix}/export"]),
        Case("sweep resumed with more --episodes", [*sw, "--episodes", "3"], expect="either",
             writes=("in/sweep1",), timeout=240),
        Case("sweep resumed with other --taus", [*sw, "--taus", "0.5"]),
        Case("sweep resumed with other --sample-steps", [*sw, "--sample-steps", "1"]),
        Case("sweep resumed with other --rollout-seed", [*sw, "--rollout-seed", "7"]),
        Case("sweep resumed as it was", sw, expect="either", writes=("in/sweep1",), quick=True),
        Case("import-lerobot resumed with another --image-size", imp("--image-size", "4", "4"),
             pre=[imp()], quick=True),
        Case("import-lerobot resumed with another --action-space", [*imp()[:-2], "--action-space", "velocity"],
             pre=[imp()]),
        Case("demo resumed with another --config", ["demo", "--out", "{in}/demo", "--config", "bussing_sim",
                                                    "--steps", "3"]),
    ]
    return cases


def _one_row_per_step(case_dir: Path, res: Result) -> str | None:
    p = case_dir / "in" / "demo" / "train" / "metrics.jsonl"
    steps = [json.loads(x)["step"] for x in p.read_text().splitlines() if x.startswith("{")]
    return f"metrics.jsonl steps {steps}" if len(steps) != len(set(steps)) else None


# -- the policy server's bad clients (in the probe, against a `sc3 serve-policy` subprocess) --------------------------
def _serve(case_dir: Path, *extra):
    env = env_for(case_dir)
    proc = subprocess.Popen(["nice", "-n", "5", *SC3, "serve-policy", "--policy", "linear", "--port", "0",
                             "--num-views", "1", "--image-size", "8", "8", "--log-level", "error", *extra], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    line = proc.stdout.readline()
    if "ws://" not in line:
        proc.kill()
        raise RuntimeError(f"no server: {line!r} {proc.stderr.read()[-500:]}")
    return proc, line.split(" on ", 1)[1].split(" ", 1)[0]


def _send(url, payload, raw=False, timeout=60):
    import websockets.exceptions
    import websockets.sync.client

    from sc3_jax.policies import msgpack_numpy
    with websockets.sync.client.connect(url, max_size=None, compression=None, open_timeout=30) as ws:
        ws.recv(timeout=30)
        try:
            ws.send(payload if raw else msgpack_numpy.packb(payload))
            reply = ws.recv(timeout=timeout)
        except websockets.exceptions.ConnectionClosed as e:
            return "closed", e.rcvd.code if e.rcvd else None
    return ("error", reply) if isinstance(reply, str) else ("actions", msgpack_numpy.unpackb(reply))


def _good():
    import numpy as np
    return {"images": np.full((1, 8, 8, 3), 50, np.uint8), "state": np.zeros(7, np.float32),
            "task": np.asarray(0, np.int32)}


def server_case(name: str, bad, first_bad: bool = True, answer_ok: bool = False):
    """A bad client (``bad(url)`` -> what it got) and then a good one: handled when the bad one got one line or a
    close, the good one actions, the server still up, and no internals in what was said."""
    def fn(case_dir: Path):
        import numpy as np
        proc, url = _serve(case_dir)
        try:
            if not first_bad:
                k, r = _send(url, _good())
                if k != "actions":
                    return "silent", f"a good first client got {k}: {str(r)[:160]}"
            try:
                got = bad(url)
            except Exception as e:  # noqa: BLE001
                got = ("client", f"{type(e).__name__}: {e}")
            if proc.poll() is not None:
                return "traceback", f"the server died (rc {proc.returncode}): {last_line(proc.stderr.read())[:160]}"
            kind, msg = got
            if kind == "actions" and answer_ok:
                return "handled", "answered (no fault for this policy)"
            if kind == "actions":
                acts = np.asarray(msg.get("actions")) if isinstance(msg, dict) else None
                if acts is not None and acts.dtype.kind == "f" and not np.isfinite(acts).all():
                    return "silent", "non-finite actions left the server"
                return "silent", "a bad observation was answered with actions"
            text = str(msg)
            if kind == "error" and ("\n" in text or "Traceback" in text or "/" in text.replace("(fixed", "")
                                    or "dot_general" in text):
                return "silent", f"the error carries internals: {text[:200]!r}"
            k, r = _send(url, _good())
            if k != "actions":
                return "silent", f"a good client after it got {k}: {str(r)[:160]}"
            return "handled", f"{kind}: {text[:140]}; the next good client served"
        finally:
            proc.send_signal(signal.SIGINT)
            with contextlib.suppress(subprocess.TimeoutExpired):
                proc.wait(timeout=20)
            if proc.poll() is None:
                proc.kill()
    return Case(f"server: {name}", [], fn=fn, quick=name in ("garbage bytes", "NaN state"))


def server_cases() -> list[Case]:
    import numpy as np

    def obs(**kw):
        o = _good()
        o.update(kw)
        return o

    def connect_and_vanish(url):
        import socket
        host, port = url.split("//")[1].split(":")
        s = socket.create_connection((host, int(port)))
        s.sendall(b"GET / HTTP/1.1\r\nHost: x\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
                  b"Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n\r\n")
        s.recv(100)
        s.close()
        return "closed", None

    def half_frame(url):
        import socket
        host, port = url.split("//")[1].split(":")
        s = socket.create_connection((host, int(port)))
        s.sendall(b"GET / HTTP/1.1\r\nHost: x\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
                  b"Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n\r\n")
        s.recv(4096)
        s.sendall(b"\x82\xfe\x10\x00")  # a binary frame announcing 4096 bytes, none sent, then gone
        s.close()
        return "closed", None

    def not_websocket(url):
        import urllib.request
        try:
            urllib.request.urlopen(url.replace("ws://", "http://"), timeout=10).read()
        except Exception as e:  # noqa: BLE001
            return "closed", str(e)[:80]
        return "closed", "http answered"

    return [
        server_case("garbage bytes", lambda u: _send(u, b"\x00\xffgarbage\xc1", raw=True)),
        server_case("a text frame", lambda u: _send(u, "hello", raw=True)),
        server_case("msgpack of a list", lambda u: _send(u, [1, 2, 3])),
        server_case("msgpack of a string", lambda u: _send(u, "obs")),
        server_case("an empty observation", lambda u: _send(u, {})),
        server_case("NaN state", lambda u: _send(u, obs(state=np.full(7, np.nan, np.float32)))),
        server_case("inf image", lambda u: _send(u, obs(images=np.full((1, 8, 8, 3), np.inf, np.float32)))),
        server_case("wrong image shape first", lambda u: _send(u, obs(images=np.zeros((2, 9, 8, 3), np.uint8)))),
        server_case("wrong image shape later", lambda u: _send(u, obs(images=np.zeros((1, 9, 8, 3), np.uint8))),
                    first_bad=False),
        server_case("state too long", lambda u: _send(u, obs(state=np.zeros(9, np.float32)))),
        server_case("state as a string", lambda u: _send(u, obs(state="zeros"))),
        # a task id is the policy's to read (the linear policy takes any number): answered or one line
        server_case("task out of range", lambda u: _send(u, obs(task=np.asarray(10**9, np.int64))), answer_ok=True),
        server_case("image of strings", lambda u: _send(u, obs(images=np.full((1, 8, 8, 3), "a")))),
        server_case("deep nesting", lambda u: _send(u, {"a": json.loads("[" * 500 + "]" * 500)})),
        server_case("a message over the bound", lambda u: _send(u, {"images": np.zeros(9 * 2**20, np.uint8)})),
        server_case("connect and vanish", connect_and_vanish),
        server_case("half a frame", half_frame),
        server_case("plain http", not_websocket),
    ]


# -- issue 66's cases, as written ------------------------------------------------------------------------------------
def _ic_for(model: Path, dest: Path) -> None:
    """One initial condition of ``model``'s views, size and context, zeros; its action size in state."""
    import numpy as np
    sys.path.insert(0, str(ROOT))
    from sc3_jax.model import checkpoint
    cfg = checkpoint.read_config(model)
    h, w = cfg.data.image_size
    np.savez(dest, frames=np.full((1, cfg.model.num_views, cfg.data.context_frames, h, w, 3), 90, np.uint8),
             state=np.zeros((1, cfg.model.action_dim), np.float32))


def issue_cases() -> list[Case]:
    import numpy as np
    cases = []
    models = sorted(p for p in [*(ROOT / "exports").iterdir(), *(ROOT / "sc3_jax/benchmarks/bussing/shipped").iterdir()]
                    if (p / "config.json").is_file())
    for m in models:
        def damage(case_dir: Path, m=m):
            _ic_for(m, case_dir / "in" / f"ic_{m.name}.npz")
        cases.append(Case(f"issue: {m.relative_to(ROOT)} rolls out one chunk", [
            "rollout", "--world-model", str(m), "--policy", "zero", "--data", f"{{in}}/ic_{m.name}.npz", "--out",
            "{out}/r", "--no-video", "--no-progress", "--benchmark", "none", "--no-learned-state",
            "--rollout.episode-seconds", "0.5"], group="issue", expect="ok", damage=damage, timeout=300,
            check=has("out/r/summary.json"), quick=m.name == "bussing_latent_gpu_student"))

    def demo_fps(case_dir: Path, res: Result):
        d = json.loads((case_dir / "out" / "demo" / "train" / "config.json").read_text())["data"]
        return None if d.get("fps") == 20.0 and d.get("state_dim") == 0 else f"data {d}"
    cases.append(Case("issue: sc3 demo records data.fps", ["demo", "--out", "{out}/demo", "--steps", "1",
                                                           "--episodes", "2", "--batch", "2"], group="issue",
                      expect="ok", check=demo_fps, timeout=300))

    def relative(case_dir: Path):
        cfgp = case_dir / "in" / "export" / "config.json"
        cfg = json.loads(cfgp.read_text())
        cfg["data"]["path"] = "train"
        cfg["data"].pop("fps", None)
        cfgp.write_text(json.dumps(cfg))
        (case_dir / "cwd" / "train").mkdir()
        ds = json.loads((case_dir / "in" / "demo" / "episodes" / "dataset.json").read_text())
        ds["fps"] = 5
        (case_dir / "cwd" / "train" / "dataset.json").write_text(json.dumps(ds))
    cases.append(Case("issue: relative data.path is not read against the cwd", rollout(wm=EXPORT), group="issue",
                      damage=relative, expect="either", check=_not_at_5fps))

    def set_cfg(**data):
        def damage(case_dir: Path):
            p = case_dir / "in" / "export" / "config.json"
            cfg = json.loads(p.read_text())
            cfg["data"].update(data)
            p.write_text(json.dumps(cfg))
        return damage
    cases.append(Case("issue: data.fps 7 does not divide the control rate", rollout(wm=EXPORT), group="issue",
                      damage=set_cfg(fps=7.0), quick=True))
    cases.append(Case("issue: data.views twice", rollout(wm=EXPORT), group="issue",
                      damage=set_cfg(views=["wrist", "wrist", "left"])))
    cases += [
        Case("issue: Ctrl-C sweep (process group)", sweep("--episodes", "12", "--episode-seconds", "3"),
             group="issue", expect="interrupt", interrupt_after=9.0, quick=True),
        Case("issue: Ctrl-C sweep after its first record", sweep("--episodes", "16", "--batch", "1",
                                                                 "--episode-seconds", "6"), group="issue",
             expect="interrupt", interrupt_after=14.0, timeout=200),
        Case("issue: Ctrl-C train while compiling", train("--train.steps", "50"), group="issue",
             expect="interrupt", interrupt_after="to cut it:", interrupt_delay=2.0),
        Case("issue: Ctrl-C demo", ["demo", "--out", "{out}/demo", "--steps", "20", "--episodes", "4", "--batch",
                                    "4"], group="issue", expect="interrupt", interrupt_after="[2/3]",
             interrupt_delay=3.0),
    ]
    sw = SWEEP1("{in}", out="{out}/s1")  # a sweep of the case's own copy of the model, which then trains on
    cases.append(Case("issue: sweep resumed after its model trained on", sw, group="issue", pre=[sw,
        ["train", "--config", "tiny", "--data", "{fix}/demo/episodes", "--train.workdir", WM, "--train.steps", "3",
         "--batch", "4",
         "--train.no-progress", "--train.no-tensorboard"]], writes=("in/demo/train",), timeout=200, quick=True))
    cases.append(Case("issue: metrics.jsonl after a resume", train("--train.steps", "4"), group="issue",
                      expect="ok", check=_one_row_per_step_wd, timeout=300, pre=[
                          train("--train.steps", "3", "--train.ckpt-every", "2", "--train.log-every", "1",
                                "--train.no-async-checkpointing")], damage=_drop_last_checkpoint))

    def link_report(case_dir: Path):
        (case_dir / "in" / "results" / "report").symlink_to(case_dir / "victim", target_is_directory=True)
    cases.append(Case("issue: report/ a symlink", ["report", "{in}/results", "--draws", "10"], group="issue",
                      damage=link_report, quick=True))

    def records(edit):
        def damage(case_dir: Path):
            p = case_dir / "in" / "results_ep" / "results.jsonl"
            lines = p.read_text().splitlines()
            lines = edit(lines)
            p.write_text("\n".join(lines) + "\n")
        return damage

    def dup(lines):
        r = json.loads(lines[0])
        r["success"] = not r.get("success")
        return [*lines, json.dumps(r)]

    def foreign(lines):
        r = json.loads(lines[0])
        r["episode"] = "elsewhere"
        return [json.dumps(r), *lines[1:]]

    def negu(lines):
        for i, x in enumerate(lines):
            r = json.loads(x)
            if r.get("u_chunk"):
                r["u_chunk"] = [-abs(float(v)) for v in r["u_chunk"]]
                lines[i] = json.dumps(r)
                return lines
            for k in ("U", "u"):
                if k in r:
                    r[k] = -1.0
                    lines[i] = json.dumps(r)
                    return lines
        raise AssertionError("no U in the records")
    rep_ep = ["report", "{in}/results_ep", "--out", "{out}/rep", "--draws", "10"]
    cases += [Case("issue: duplicate record ids", rep_ep, group="issue", damage=records(dup)),
              Case("issue: a foreign record (episode not in sweep.json)", rep_ep, group="issue",
                   damage=records(foreign)),
              Case("issue: negative U", rep_ep, group="issue", damage=records(negu))]

    def edit_names(case_dir: Path):
        p = case_dir / "in" / "results_ep" / "sweep.json"
        cfg = json.loads(p.read_text())
        cfg["policy_names"][0] = "so_best"
        p.write_text(json.dumps(cfg))
    cases.append(Case("issue: an edited policy_names", rep_ep, group="issue", damage=edit_names))
    cases.append(Case("issue: ties in P(best)", ["report", "{in}/sweep1", "--out", "{out}/rep", "--draws", "50"],
                      group="issue", expect="ok", check=_ties_said, damage=_all_fail))
    ep = lambda d: first_episode(d)  # noqa: E731
    cases += [
        Case("issue: a frames file symlinked to another store", exp(), group="issue",
             damage=damage_file("symlink out", lambda d: sorted((ep(d) / "frames").iterdir())[0])),
        Case("issue: a FIFO actions.npy", exp(), group="issue",
             damage=damage_file("fifo", lambda d: ep(d) / "actions.npy"), timeout=60, quick=True),
        Case("issue: an .npy header claiming 1e11 rows", exp(), group="issue", damage=_huge_header),
    ]
    cases += [server_case(n, b) for n, b in (
        ("issue: a rejected first observation fixes nothing",
         lambda u: _send(u, {**_good(), "images": np.zeros((2, 8, 8, 3), np.uint8)})),
        ("issue: a NaN state", lambda u: _send(u, {**_good(), "state": np.full(7, np.nan, np.float32)})),
        ("issue: a wrong shape says no dot_general",
         lambda u: _send(u, {**_good(), "state": np.zeros(3, np.float32)})))]
    for c in cases[-3:]:
        c.group = "issue"
    cases.append(Case("issue: 8 idle connections then a client", [], group="issue", fn=_idle_lockout))
    bounds = [
        ("diagnose --episodes 0", diagnose("--episodes", "0")), ("diagnose --batch 0", diagnose("--batch", "0")),
        ("diagnose --cf-starts -1", diagnose("--cf-starts", "-1")),
        ("diagnose --max-seconds nan", diagnose("--max-seconds", "nan")),
        ("diagnose --filmstrips FILE", diagnose("--filmstrips", "{in}/real.csv")),
        ("diagnose --out FILE/x.json", diagnose("--out", "{in}/real.csv/x.json")),
        ("import --image-size 0 -5", imp("--image-size", "0", "-5")),
        ("import --image-size 20000 20000", imp("--image-size", "20000", "20000")),
        ("import --fps 0", imp("--fps", "0")),
        ("train --batch 0", train("--batch", "0")), ("train --train.steps 0", train("--train.steps", "0")),
        ("train --train.lr nan", train("--train.lr", "nan")), ("train --train.lr -1", train("--train.lr", "-1")),
        ("rollout --episodes -1", rollout("--episodes", "-1")), ("rollout --start -5", rollout("--start", "-5")),
        ("rollout --policy nosuchname", rollout("--policy", "nosuchname")),
        ("sweep --scorer os:getcwd", sweep("--scorer", "os:getcwd")),
    ]
    cases += [Case(f"issue: {n}", a, group="issue", quick=n.startswith("diagnose --b")) for n, a in bounds]
    cases.append(Case("issue: import --image-size 0 -5 then the corrected rerun", imp("--image-size", "4", "4"),
                      group="issue", expect="ok", damage=_refused_import, check=has("out/st/dataset.json")))
    so = ROOT / "exports" / "so101_v3_cpu"  # int8 and kept; the campaign replaces its float32 exports

    def so_ic(case_dir: Path):
        _ic_for(so, case_dir / "in" / "ic_so.npz")
    cases += [
        Case("issue: report --store S", ["report", "--store", "{in}/results"], group="issue"),
        Case("issue: --policy zero on an SO-101 model", ["rollout", "--world-model", str(so), "--policy", "zero",
                                                         "--data", "{in}/ic_so.npz", "--out", "{out}/r",
                                                         "--no-video", "--no-progress", "--benchmark", "none",
                                                         "--rollout.episode-seconds", "0.5"], group="issue",
             damage=so_ic, expect="either", check=_mentions_no_learned_state, timeout=300),
        Case("issue: rollout --benchmark none", rollout(), group="issue", expect="ok", check=has("out/r/summary.json"),
             quick=True),
    ]
    return cases


def _not_at_5fps(case_dir: Path, res: Result):
    s = case_dir / "out" / "r" / "summary.json"
    if res.rc != 0:
        return None if "fps" in last_line(res.stderr) or "frame rate" in last_line(res.stderr) else \
            f"refused for another reason: {last_line(res.stderr)[:100]}"
    text = s.read_text() if s.exists() else ""
    return "read the cwd's 5 fps" if "5 Hz" in res.stdout or '"data_fps": 5' in text else None


def _one_row_per_step_wd(case_dir: Path, res: Result):
    p = case_dir / "out" / "wd" / "metrics.jsonl"
    steps = [json.loads(x)["step"] for x in p.read_text().splitlines() if x.startswith("{")]
    return None if steps == sorted(set(steps)) and steps[-1] == 4 else f"steps {steps}"


def _drop_last_checkpoint(case_dir: Path):
    ckpts = case_dir / "out" / "wd" / "checkpoints"
    steps = sorted(int(p.name) for p in ckpts.iterdir() if p.name.isdigit())
    assert len(steps) >= 2, steps
    shutil.rmtree(ckpts / str(steps[-1]))  # stopped after logging the last steps, before their checkpoint was kept


def _all_fail(case_dir: Path):
    p = case_dir / "in" / "sweep1" / "results.jsonl"
    rows = [json.loads(x) for x in p.read_text().splitlines()]
    for r in rows:
        for k in list(r):
            if k in ("success", "outcomes"):
                r[k] = False if k == "success" else {c: False for c in r[k]}
    p.write_text("".join(json.dumps(r) + "\n" for r in rows))


def _ties_said(case_dir: Path, res: Result):
    text = "\n".join(p.read_text(errors="replace") for p in (case_dir / "out" / "rep").glob("*.md"))
    text += res.stdout
    if "100% of draws" in text:
        return "a tie reads 'ranks first in 100% of draws'"
    return None


def _huge_header(case_dir: Path):
    import numpy as np
    p = first_episode(case_dir) / "actions.npy"
    x = np.load(p)
    with open(p, "wb") as f:
        np.lib.format.write_array_header_1_0(f, {"descr": np.lib.format.dtype_to_descr(x.dtype),
                                                 "fortran_order": False, "shape": (10**11, *x.shape[1:])})
        f.write(x.tobytes())


def _refused_import(case_dir: Path):
    r = run_cmd([*SC3, *fill(imp("--image-size", "0", "-5"), case_dir)], case_dir / "cwd", env_for(case_dir), 120)
    assert r.rc not in (0, None), r.stderr[-500:]


def _mentions_no_learned_state(case_dir: Path, res: Result):
    if res.rc == 0:
        return None
    return None if "--no-learned-state" in last_line(res.stderr) else "the refusal does not name --no-learned-state"


def _idle_lockout(case_dir: Path):
    """8 silent clients hold every slot; a 9th is refused (503) until idle_seconds closes them (here 2 s)."""
    code = textwrap.dedent("""
        import contextlib, time, numpy as np, websockets.sync.client, websockets.exceptions, jax
        from sc3_jax.policies.openpi_server import PolicyServer
        from sc3_jax.policies.simple import linear_policy
        from sc3_jax.policies import msgpack_numpy
        pol = linear_policy(jax.random.key(0), num_views=1, chunk=4, action_dim=2)
        obs = {"images": np.full((1, 8, 8, 3), 50, np.uint8), "state": np.zeros(2, np.float32),
               "task": np.asarray(0, np.int32)}
        def send(url):
            with websockets.sync.client.connect(url) as ws:
                ws.recv(timeout=10); ws.send(msgpack_numpy.packb(obs)); return ws.recv(timeout=60)
        with PolicyServer(pol, port=0, idle_seconds=2.0).start() as server, contextlib.ExitStack() as stack:
            for _ in range(8):
                stack.enter_context(websockets.sync.client.connect(server.url)).recv(timeout=10)
            try:
                send(server.url); print("SERVED_WHILE_FULL")
            except websockets.exceptions.InvalidStatus as e:
                print("503" if "503" in str(e) else str(e))
            time.sleep(3.5)
            r = send(server.url)
            print("SERVED" if isinstance(r, bytes) else "ERR " + r)
    """)
    r = subprocess.run(["nice", "-n", "5", sys.executable, "-c", code], env=env_for(case_dir), capture_output=True,
                       text=True, timeout=120)
    if "Traceback" in r.stderr:
        return "traceback", last_line(r.stderr)[:160]
    return ("handled", "503 while 8 idle, served once they timed out") if r.stdout.split()[-1:] == ["SERVED"] \
        else ("silent", r.stdout.strip()[-160:])


# -- a store's own truth (issue 76): the report reads the real outcomes the store keeps, never a path -------------
def _plant_cwd(case_dir: Path):
    """An all-true sweep/real.csv in the current directory: the path so101_sweep36's sweep was given."""
    cfg = json.loads((case_dir / "in" / "results_ep" / "sweep.json").read_text())
    (case_dir / "cwd" / "sweep").mkdir()
    (case_dir / "cwd" / "sweep" / "real.csv").write_text("policy,episode,success\n" + "".join(
        f"{p},seed{20000000 + i},true\n" for p in cfg["policy_names"] for i in range(cfg["episodes"])))


def _as_before(case_dir: Path, path: str):
    """results_ep's real.json as sweeps wrote it before the outcomes were kept: the path as given."""
    (case_dir / "in" / "results_ep" / "real.json").write_text(json.dumps({"real": [path]}))


def _the_stores_own(case_dir: Path, res: Result):
    t = json.loads((case_dir / "out" / "rep" / "report.json").read_text())
    real = {p: v["rates"]["success"]["value"] for p, v in ((t.get("real") or {}).get("policies") or {}).items()}
    return None if real.get("so_noise2") == 0.0 else f"real rates {real}: not the store's (so_noise2 0.00)"


def kept_real_cases() -> list[Case]:
    rep_ep = report(store="{in}/results_ep")

    def outside(case_dir: Path):
        _plant_cwd(case_dir)
        _as_before(case_dir, str(case_dir / "cwd" / "sweep" / "real.csv"))
    return [
        Case("report beside a planted all-true sweep/real.csv", rep_ep, expect="ok", damage=_plant_cwd,
             check=_the_stores_own, quick=True),
        Case("report of a store from before, its sweep/real.csv planted beside", rep_ep, expect="ok",
             damage=lambda d: (_plant_cwd(d), _as_before(d, "sweep/real.csv")), check=_the_stores_own),
        Case("report of a real.json naming a file outside the store", rep_ep, damage=outside, quick=True),
    ]


# -- issue 76's other faults: a saved model's every field at the door, the machine's and a server's faults, nothing
# silent, the rough edges -------------------------------------------------------------------------------------------
def _edit(rel: str, fn):
    """``fn(obj)`` done to the JSON file ``rel`` of the case's inputs."""
    def damage(case_dir: Path):
        p = case_dir / "in" / rel
        obj = json.loads(p.read_text())
        fn(obj)
        p.write_text(json.dumps(obj))
    return damage


def _so101(rel: str, fn):
    """exports/so101_v7_cpu (a learned tokenizer's model) copied into the inputs as so101/, ``rel`` edited."""
    def damage(case_dir: Path):
        shutil.copytree(ROOT / "exports" / "so101_v7_cpu", case_dir / "in" / "so101")
        _edit(f"so101/{rel}", fn)(case_dir)
    return damage


def _empty_first(case_dir: Path):
    """The held-out store's first episode emptied (its directory kept): the rollout took the next one."""
    first = sorted(p for p in (case_dir / "in" / "demo" / "heldout").iterdir() if p.is_dir())[0]
    shutil.rmtree(first)
    first.mkdir()


def _cut_data_parquet(case_dir: Path):
    p = sorted((case_dir / "in" / "lerobot" / "data").rglob("*.parquet"))[0]
    p.write_bytes(p.read_bytes()[: p.stat().st_size // 2])


def _not_fail(case_dir: Path, res: Result):
    return "an unmeasurable gate printed FAIL" if "FAIL offline per-object outcome" in res.stdout else None


def _odd_client(case_dir: Path):
    """One client's [3, 4, 4, 3] images (answered: the zero policy takes any shape) fixed the server's shapes for
    everyone until restart while /healthz said OK; each refusal was a traceback on the server's terminal."""
    import urllib.request

    import numpy as np
    import websockets.sync.client

    from sc3_jax.policies import msgpack_numpy
    proc, url = _serve(case_dir, "--policy", "zero")
    try:
        with websockets.sync.client.connect(url, open_timeout=30) as odd:
            odd.recv(timeout=30)
            odd.send(msgpack_numpy.packb({"images": np.zeros((3, 4, 4, 3), np.uint8), "state": np.zeros(7, "f4")}))
            if not isinstance(odd.recv(timeout=60), bytes):
                return "silent", "the odd client itself was refused"
            k, r = _send(url, _good())
            if k != "actions":
                return "silent", f"a correct client after an odd one got {k}: {str(r)[:160]}"
            with urllib.request.urlopen(url.replace("ws://", "http://") + "/healthz", timeout=10) as h:
                health = h.read().decode()
            if "[3, 4, 4, 3]" not in health:
                return "silent", f"/healthz does not say the shapes it serves: {health[:160]!r}"
        _send(url, "hello", raw=True)  # refused: one line in the server's log
    finally:
        proc.send_signal(signal.SIGINT)
        with contextlib.suppress(subprocess.TimeoutExpired):
            proc.wait(timeout=20)
        if proc.poll() is None:
            proc.kill()
    log = proc.stderr.read()
    if "Traceback" in log or log.count("refused an observation") != 1:
        return "silent", f"the server's log of one refusal: {log[-300:]!r}"
    return "handled", "the odd client and a correct one each served on its own terms; /healthz says both"


def issue76_cases() -> list[Case]:
    so = lambda *extra: rollout(*extra, wm="{in}/so101", data="{in}/ic.npz")  # noqa: E731  (refused first)
    cases = [
        Case("76: ae.json latent_channels 'sixteen'", so(),
             damage=_so101("tokenizer/ae.json", lambda d: d["config"].update(latent_channels="sixteen")), quick=True),
        Case("76: config.json model.dim -192", so(), damage=_so101("config.json", lambda d: d["model"].update(
            dim=-192))),
        Case("76: config.json image_size [81, 79] (its tokenizer's is 80x80)", so(),
             damage=_so101("config.json", lambda d: d["data"].update(image_size=[81, 79]))),
        Case("76: config.json image_size [96, 128] against 16x16 data", rollout(wm=EXPORT),
             damage=_edit("export/config.json", lambda d: d["data"].update(image_size=[96, 128]))),
        Case("76: config.json data.views a string", rollout(wm=EXPORT),
             damage=_edit("export/config.json", lambda d: d["data"].update(views="abc"))),
        Case("76: train --config a run's config.json with data.fps 'ten'", train("--config", "{in}/export/config.json"),
             damage=_edit("export/config.json", lambda d: d["data"].update(fps="ten"))),
        Case("76: rollout --policy ws://127.0.0.1:1", rollout("--policy", "ws://127.0.0.1:1"), quick=True),
        Case("76: an episode directory emptied", rollout(), damage=_empty_first),
        Case("76: diagnose --filmstrips --benchmark none", diagnose("--filmstrips", "{out}/fs")),
        Case("76: diagnose's outcome gate without a scorer reads not measured", diagnose("--stages", "open_loop"),
             expect="ok", check=_not_fail, timeout=300),
        Case("76: sweep so101 of another robot's model", ["sweep", "so101", "--world-model", WM, "--out", "{out}/so",
                                                          "--scorer", "probe_scorer:score"]),
        Case("76: report of a store with sweep.json's kind removed", report(store="{in}/results_ep"),
             damage=_edit("results_ep/sweep.json", lambda d: d.pop("kind"))),
        Case("76: report of a store with sweep.json's episodes removed", report(store="{in}/results_ep"),
             damage=_edit("results_ep/sweep.json", lambda d: d.pop("episodes"))),
        Case("76: import --episodes 0:3 of a 2-episode dataset", imp("--episodes", "0:3")),
        Case("76: import of a truncated data parquet", imp(), damage=_cut_data_parquet),
        Case("76: server: an odd client locks no other out", [], fn=_odd_client, quick=True),
    ]
    cases += [Case(f"76: JAX_PLATFORMS={p} on this machine", rollout(), env={"JAX_PLATFORMS": p}, quick=p == "gpu")
              for p in ("gpu", "cuda", "bogus")]
    return cases


# -- the run --------------------------------------------------------------------------------------------------------
def all_cases() -> list[Case]:
    return [*issue_cases(), *numeric_cases(), *file_cases(), *output_cases(), *interrupt_cases(), *resume_cases(),
            *server_cases(), *kept_real_cases(), *issue76_cases()]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="a subset: a few cases of each kind")
    ap.add_argument("--set", choices=["all", "issue", "new"], default="all")
    ap.add_argument("--only", action="append", default=None, help="cases whose name holds this text (repeatable)")
    ap.add_argument("--failed", default=None, help="the cases not handled in this earlier --json output")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--keep", default=None, help="keep fixtures and case directories here (reused if present)")
    ap.add_argument("--json", default=None, help="write every case's result here")
    ap.add_argument("--list", action="store_true", help="list the cases and exit")
    ap.add_argument("--code", default=None, help="run this checkout's sc3_jax (e.g. `git archive` of an old commit)")
    args = ap.parse_args(argv)
    if args.code:
        CODE.append(str(Path(args.code).resolve()))
    cases = all_cases()
    if args.set != "all":
        cases = [c for c in cases if c.group == args.set]
    if args.quick:
        cases = [c for c in cases if c.quick]
    if args.only:
        cases = [c for c in cases if any(o in c.name for o in args.only)]
    if args.failed:
        again = {r["name"] for r in json.loads(Path(args.failed).read_text()) if r["cls"] != "handled"}
        cases = [c for c in cases if c.name in again]
    if args.list:
        for c in cases:
            print(f"{c.group:5s} {c.name}")
        print(f"{len(cases)} cases")
        return 0
    t0 = time.monotonic()
    base = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="probe_faults_"))
    fixtures, work = base / "fixtures", base / "cases"
    if not (fixtures / "sweep1" / "results.jsonl").exists():
        shutil.rmtree(fixtures, ignore_errors=True)
        make_fixtures(fixtures)
    FIXTURES.append(str(fixtures))
    pristine = snapshot(fixtures)
    results = []
    with concurrent.futures.ThreadPoolExecutor(args.jobs) as pool:
        futures = {pool.submit(run_case, c, fixtures, work, i): c for i, c in enumerate(cases)}
        for f in concurrent.futures.as_completed(futures):
            r = f.result()
            results.append(r)
            print(f"[{len(results):3d}/{len(cases)}] {r['cls']:9s} {r['seconds']:6.1f}s  {r['name']}: {r['said']}",
                  flush=True)
            if not args.keep:
                shutil.rmtree(work / f"{cases.index(futures[f]):03d}", ignore_errors=True)
    if snapshot(fixtures) != pristine:
        results.append(dict(name="the fixtures themselves", group="new", cls="outside", said="changed", seconds=0))
    order = {c.name: i for i, c in enumerate(cases)}
    results.sort(key=lambda r: order.get(r["name"], 1e9))
    wall = time.monotonic() - t0
    print()
    print("| set | cases | " + " | ".join(CLASSES) + " |")
    print("|---|---:|" + "---:|" * len(CLASSES))
    for group in ("issue", "new"):
        rs = [r for r in results if r["group"] == group]
        if rs:
            print(f"| {group} | {len(rs)} | " + " | ".join(str(sum(r['cls'] == k for r in rs)) for k in CLASSES)
                  + " |")
    bad = [r for r in results if r["cls"] != "handled"]
    for r in bad:
        print(f"NOT HANDLED [{r['cls']}] {r['name']}: {r['said']}\n    {r.get('argv', '')}")
    print(f"{len(results)} cases in {wall / 60:.1f} min; {len(bad)} not handled")
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1))
    if not args.keep:
        shutil.rmtree(base, ignore_errors=True)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())

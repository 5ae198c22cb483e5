"""The ``sc3`` command: one subcommand per stage (data -> train -> checkpoint -> rollout -> sweep -> report)."""
from __future__ import annotations

import ast
import errno
import importlib
import os
import signal
import sys
import textwrap
import threading
import time
import traceback
from pathlib import Path

CANNOT_WRITE = {errno.EACCES, errno.EPERM, errno.EROFS, errno.ENOSPC, errno.EDQUOT}
PACKAGE = Path(__file__).resolve().parent


def _command(module: str):
    """The `main` of the command module ``module``, imported when the command runs: `sc3 --help` and the other
    commands load none of its libraries."""
    def run(argv: list[str]) -> int:
        return importlib.import_module(module).main(argv)

    return run


def _benchmarks_commands() -> dict[str, str]:
    """Command -> module of each built-in benchmark's own commands: every ``sc3_jax/benchmarks/NAME/commands/CMD.py``
    is ``sc3 CMD``, found on disk (as evaluation/benchmark.py finds the benchmarks), so that this file names none."""
    return {p.stem.replace("_", "-"): f"sc3_jax.benchmarks.{p.parents[1].name}.commands.{p.stem}"
            for p in sorted(PACKAGE.glob("benchmarks/*/commands/*.py")) if p.stem != "__init__"}


# command -> its module in sc3_jax/commands/
CORE = {"demo": "demo", "train": "train", "train-tokenizer": "train_tokenizer", "train-state": "train_state",
        "train-detector": "train_detector", "diagnose": "diagnose", "diagnose-table": "diagnose_table",
        "rollout": "rollout", "sweep": "sweep", "report": "report", "check-scorer": "check_scorer", "curve": "curve",
        "data": "data", "serve-policy": "serve_policy", "configs": "configs", "convert": "convert", "plan": "plan",
        "trunk": "trunk"}
# every command -> its module: the core's, then the benchmarks' own
MODULES = {**{name: f"sc3_jax.commands.{m}" for name, m in CORE.items()}, **_benchmarks_commands()}
COMMANDS = {name: _command(m) for name, m in MODULES.items()}


def declared(module: str) -> dict[str, ast.expr]:
    """The module-level assignments of the command module ``module`` (name -> value), read from its source."""
    out = {}
    for node in ast.parse((PACKAGE.parent / (module.replace(".", "/") + ".py")).read_text()).body:
        target = node.target if isinstance(node, ast.AnnAssign) else (node.targets[0] if isinstance(node, ast.Assign)
                                                                      else None)
        if isinstance(target, ast.Name) and node.value is not None:
            out[target.id] = node.value
    return out


def describe(module: str) -> tuple[str, list[str]]:
    """(SUMMARY, the SUBCOMMANDS' names) of the command module ``module``, read from its source: `sc3 --help` imports
    no command (and so none of their libraries). A ``**benchmark.sweep_configs()`` among the SUBCOMMANDS (`sc3
    sweep`'s) stands for the built-in benchmarks' sweeps, whose names the registry reads from their sources."""
    found = declared(module)
    summary = ast.literal_eval(found["SUMMARY"]) if "SUMMARY" in found else ""
    subs = found.get("SUBCOMMANDS")
    if not isinstance(subs, ast.Dict):
        return summary, []
    return summary, [name for key, value in zip(subs.keys, subs.values)
                     for name in ([ast.literal_eval(key)] if key is not None else _unpacked(value))]


def _unpacked(node: ast.expr) -> list[str]:
    """The names of a ``**`` entry of SUBCOMMANDS: only the registry's sweeps, read as the registry reads them (its
    module imports no benchmark, nor numpy)."""
    if ast.unparse(node) != "benchmark.sweep_configs()":
        raise ValueError(f"SUBCOMMANDS: cannot list **{ast.unparse(node)} without importing it")
    from sc3_jax.evaluation import benchmark

    return benchmark.sweeps()


def usage() -> str:
    """The top-level help, made from the command modules (each one's SUMMARY and subcommands)."""
    width = max(map(len, MODULES)) + 2
    lines = ["usage: sc3 <command> [args]", "", "commands:"]
    for name, module in MODULES.items():
        summary, subs = describe(module)
        text = summary + (f" ({' | '.join(subs)})" if subs else "")
        lines += textwrap.wrap(f"{name:<{width}}{text}", 116, initial_indent="  ", subsequent_indent=" " * (width + 2),
                               break_on_hyphens=False)
    return "\n".join(lines + ["", "`sc3 <command> --help` for the arguments of each; a config's fields as "
                                  "--SECTION.FIELD VALUE", "wherever a command takes a config or a world model. One "
                                  "spelling in every command: --world-model DIR, --data DIR", "(a store), --batch N, "
                                  "--sample-steps N (sc3_jax/commands/flags.py)."])


def main(argv: list[str] | None = None) -> int:
    """Run ``sc3 ARGV``; returns its exit status. ``argv`` None: this process is the command (the ``sc3`` script,
    ``python -m sc3_jax.cli``), whose Ctrl-C ends it here (:func:`_interrupted`)."""
    own_process = argv is None
    argv = sys.argv[1:] if argv is None else argv
    if not argv or argv[0] in ("-h", "--help"):
        print(usage())
        return 0
    cmd = COMMANDS.get(argv[0])
    if cmd is None:
        print(f"sc3: unknown command {argv[0]!r}\n\n{usage()}", file=sys.stderr)
        return 2
    from sc3_jax.core.errors import UserError

    if own_process:
        _sigint(_raise_until_heard)
        sys.unraisablehook = _quiet_interrupts
    try:
        status = cmd(argv[1:])
        if not _HEARD.is_set():
            return status
        raise KeyboardInterrupt  # an interrupt the command's code swallowed: still an interrupt
    except KeyboardInterrupt:  # Ctrl-C: one line, not a traceback from wherever the command was
        before = _sigint(signal.SIG_IGN)  # a second Ctrl-C while the line is written: no traceback
        _HEARD.clear()
        # the command's own line (its module's RESUME: what a rerun keeps; from its source, in case the interrupt
        # came while the module was still being imported), else the general one
        own = declared(MODULES[argv[0]]).get("RESUME")
        resume = ast.literal_eval(own) if own is not None else "run it again to redo it"
        print(f"\nsc3 {argv[0]}: interrupted; nothing half-written is left; {resume}", file=sys.stderr)
        if own_process:
            _interrupted()
        _sigint(before)
        return 130
    except (FileNotFoundError, FileExistsError, UserError) as e:  # expected faults: the one-line message says it all
        print(f"sc3 {argv[0]}: error: {e}", file=sys.stderr)
        return 2
    except (ConnectionError, TimeoutError, RuntimeError, AssertionError) as e:  # faults of this machine's setup
        line = _unavailable_backend(e) or (_one_line(e) if _policy_client_fault(e) else None)
        if line is None:
            raise
        print(f"sc3 {argv[0]}: error: {line}", file=sys.stderr)
        return 2
    except OSError as e:  # a place the command cannot write (permissions, read-only, full): the user's to fix
        if e.errno not in CANNOT_WRITE:
            raise
        print(f"sc3 {argv[0]}: error: cannot write {e.filename or ''}: {e.strerror}; choose another place (or free "
              "space there)", file=sys.stderr)
        return 2


def _policy_client_fault(e: BaseException) -> bool:
    """Whether ``e`` is the policy client's (``policies/openpi_client.py``: a server that is not there, does not
    answer, or sent an error), in whichever command and whenever in its run it came: the user's to fix. Read from
    the loaded module: a command that connects to no server never imports it."""
    client = sys.modules.get("sc3_jax.policies.openpi_client")
    return client is not None and isinstance(e, (client.PolicyConnectionError, client.PolicyTimeoutError,
                                                 client.PolicyServerError))


def _unavailable_backend(e: BaseException) -> str | None:
    """The line for JAX_PLATFORMS naming a backend this machine lacks (gpu, cuda on a machine without one, a typo):
    JAX raised it from its backend setup (a RuntimeError, chained, or a bare AssertionError); None for anything
    else. Found where it fails, so that a command that never initialises JAX pays nothing for the check."""
    platforms = os.environ.get("JAX_PLATFORMS", "")
    frames = traceback.extract_tb(e.__traceback__)
    if not platforms or not frames or not frames[-1].filename.replace(os.sep, "/").endswith("jax/_src/xla_bridge.py"):
        return None
    try:
        from jax._src import xla_bridge

        known = sorted(xla_bridge._backend_factories)  # the backends this installation of JAX has
    except (ImportError, AttributeError):
        known = ["cpu"]
    return (f"JAX_PLATFORMS={platforms}: no such backend is available on this machine (JAX here knows "
            f"{', '.join(known)}; cpu always works): set JAX_PLATFORMS=cpu, or unset it to let JAX choose")


def _one_line(e: BaseException) -> str:
    """An error's first line and, where a server's text follows (openpi sends a traceback), its last line."""
    lines = [x.strip() for x in str(e).splitlines() if x.strip()]
    return " ".join(lines[:1] + lines[-1:] if len(lines) > 1 else lines) or type(e).__name__


_HEARD = threading.Event()  # a Ctrl-C came and main has not yet written its line


def _raise_until_heard(signum, frame):
    """SIGINT: raise KeyboardInterrupt, and again every 2 s until main's handler takes it (longer than a command's
    own cleanup, which a second raise would cut short). Python raises it
    at whatever bytecode runs next; when that is a garbage-collection callback or a ``__del__`` (JAX's, under XLA's
    compile), the interpreter prints "Exception ignored" and the command ran on to exit 0."""
    if not _HEARD.is_set():
        _HEARD.set()
        threading.Thread(target=_resend, daemon=True).start()
    raise KeyboardInterrupt


def _quiet_interrupts(unraisable):
    """An interrupt raised where Python cannot pass it on (a gc callback): no "Exception ignored" traceback, since
    :func:`_raise_until_heard` raises it again; anything else as Python reports it."""
    if not isinstance(unraisable.exc_value, KeyboardInterrupt):
        sys.__unraisablehook__(unraisable)


def _resend():
    while _HEARD.is_set():
        time.sleep(2.0)
        if _HEARD.is_set() and signal.getsignal(signal.SIGINT) is _raise_until_heard:
            signal.pthread_kill(threading.main_thread().ident, signal.SIGINT)


def _sigint(handler):
    """Set SIGINT's handler (None: leave it); the one it had, or None off the main thread (where none can be set)."""
    if handler is None:
        return None
    try:
        return signal.signal(signal.SIGINT, handler)
    except ValueError:
        return None


def _interrupted() -> None:
    """Exit 130 now, without the interpreter's teardown. An interrupt leaves XLA's compile threads and orbax's async
    checkpoint threads mid-work: tearing the interpreter down under them segfaulted (exit 139) or waited on them for
    ever. Nothing is lost by skipping it: every writer is atomic, and the command's own cleanup (its ``finally``
    blocks: locks released, temporaries removed, worker pools terminated) ran as the interrupt unwound to here."""
    mp_util = sys.modules.get("multiprocessing.util")
    if mp_util is not None:  # a terminated worker pool's semaphores, released (else the resource tracker warns of
        try:  # them after this command's last line); the finalizers the interpreter's exit would run first
            mp_util._run_finalizers(0)
        except Exception:  # noqa: BLE001  (exiting regardless: a finalizer's fault changes nothing)
            pass
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a closed pipe: nothing more to say there
            pass
    os._exit(130)


if __name__ == "__main__":
    sys.exit(main())

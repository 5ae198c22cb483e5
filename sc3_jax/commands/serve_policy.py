"""``sc3 serve-policy --policy SPEC [--family droid] [--port 8000] ...``: serve one of our policies over openpi's
WebSocket protocol until interrupted (Ctrl-C); the server is ``policies/openpi_server.py``, the observation
mappings ``policies/openpi_mappings.py`` (docs/openpi.md)."""
from __future__ import annotations

import dataclasses
import json
import logging
import sys
from typing import Annotated, Any, Callable, Literal

import tyro

from sc3_jax.commands import parse
from sc3_jax.core.errors import UserError

SUMMARY = "serve one of our policies over openpi's websocket protocol"  # the line `sc3 --help` shows

# openpi_mappings.PRESETS with "native" first (a test keeps them equal; spelled out so --help loads no policy code)
FAMILIES = ("native", "droid", "libero", "aloha")


@dataclasses.dataclass(frozen=True)
class Args:
    """Serve one of our policies over openpi's WebSocket protocol until Ctrl-C; an openpi client (or `--policy
    ws://HOST:PORT` in our own commands) queries it."""

    policy: str
    """zero | random | linear, package.module:attr of a JaxPolicy / HostPolicy or of a factory returning one, or a
    --benchmark's policy name, e.g. its zoo's (every spelling of policies/resolve.py)"""
    host: str = "127.0.0.1"
    """interface to listen on (127.0.0.1: this machine only; 0.0.0.0: every one, then set a key)"""
    port: int = 8000
    """port to listen on; 0 = any free port (printed)"""
    family: Literal["native", "droid", "libero", "aloha"] = "native"
    """observation keys the clients send (native = our own observation dict)"""
    image_size: Annotated[tuple[int, int] | None, tyro.conf.arg(metavar="H W")] = None
    """image size our policy expects (a family's images are un-letterboxed and resized to it)"""
    num_views: int | None = None
    """number of views our policy expects (None: the family's, e.g. 4 for aloha)"""
    task_prompt: Annotated[tyro.conf.UseAppendAction[tuple[str, ...]], tyro.conf.arg(metavar="ID=PROMPT")] = ()
    """a prompt -> task id entry of the family's table (repeatable; default: the --benchmark's prompts; no table
    without one, so any prompt is --default-task, else task 0)"""
    default_task: int | None = None
    """task id for prompts not in the table"""
    benchmark: str = "none"
    """whose policy names --policy takes and whose task prompts the table holds: a benchmark's name
    (sc3_jax/evaluation/benchmark.py: bussing, its zoo and its two tasks' prompts; so101) or package.module:attr;
    none: the built-in spellings alone, no table"""
    api_key_file: str | None = None
    """require the header 'Authorization: Api-Key <key>' from clients, the key read from this file (or from the
    environment variable SC3_POLICY_API_KEY; never from the command line, which `ps` shows)"""
    max_message_mb: float = 8.0
    """largest observation message accepted, in MB (a larger one closes its connection before it is read)"""
    log_level: str = "INFO"
    """logging level of the server (DEBUG, INFO, WARNING, ...)"""


def _prompts(entries: tuple[str, ...]) -> dict[int, str]:
    table = {}
    for entry in entries:
        tid, sep, prompt = entry.partition("=")
        if not sep or not tid.strip().lstrip("-").isdigit():
            raise UserError(f"--task-prompt expects ID=PROMPT with an integer ID, got {entry!r}")
        table[int(tid)] = prompt
    return table


def api_key(a: Args) -> str | None:
    """The key clients must send: from --api-key-file, else the environment, else none."""
    import os

    from sc3_jax.policies.openpi_server import API_KEY_ENV

    if a.api_key_file:
        try:
            key = open(a.api_key_file).read().strip()
        except OSError as e:
            raise UserError(f"--api-key-file {a.api_key_file}: {e.strerror}") from None
        if not key:
            raise UserError(f"--api-key-file {a.api_key_file}: the file is empty")
        return key
    return os.environ.get(API_KEY_ENV) or None


def loopback(host: str) -> bool:
    """Whether ``host`` is reachable from this machine only (127.0.0.0/8, ::1, localhost)."""
    import ipaddress

    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:  # a host name: it may resolve to any interface
        return False


def build_server(a: Args, resolve: Callable[[str], Any] | None = None):
    """The bound, not yet serving ``PolicyServer`` for ``a``. ``resolve`` (optional) turns ``a.policy`` into a
    policy instead of ``policies.resolve``."""
    from sc3_jax.evaluation import benchmark
    from sc3_jax.policies.openpi_mappings import get_mapping
    from sc3_jax.policies.openpi_server import PolicyServer

    bm = benchmark.get_or_none(a.benchmark)
    mapping = get_mapping(a.family)
    if mapping is not None:
        changes: dict[str, Any] = {"default_task": a.default_task}
        if a.num_views is not None:
            changes["num_views"] = a.num_views
        if a.image_size:
            changes["our_image_size"] = tuple(a.image_size)
        if a.task_prompt or bm.prompts:
            changes["prompts"] = _prompts(a.task_prompt) if a.task_prompt else dict(bm.prompts)
        mapping = mapping.replace(**changes)
    from sc3_jax.core.validate import in_range

    in_range("--port", a.port, 0, 65535, "0: any free port")
    if a.num_views is not None:
        in_range("--num-views", a.num_views, 1, 64, "cameras")
    for side in a.image_size or ():
        in_range("--image-size", side, 1, 4096, "pixels a side")
    if a.default_task is not None:
        in_range("--default-task", a.default_task, 0, 2**31 - 1, "a task id")
    in_range("--max-message-mb", a.max_message_mb, 0.001, 1024, "one observation message")
    key = api_key(a)
    if not loopback(a.host) and not key:  # anyone who reaches this machine could drive the policy
        raise UserError(f"--host {a.host} listens beyond this machine: set a key (--api-key-file FILE, or the "
                        "environment variable SC3_POLICY_API_KEY), or keep --host 127.0.0.1")
    if resolve is None:  # after the options are checked: loading a policy can take seconds
        from sc3_jax.policies.resolve import resolve as resolve_spec

        # a built-in policy sees --num-views cameras (ignored once: it saw the benchmark's 3 whatever was said)
        resolve = lambda spec: resolve_spec(spec, named=bm.named_policy, num_views=a.num_views).policy  # noqa: E731
    try:
        policy = resolve(a.policy)
    except (ValueError, ImportError) as e:  # a spelling, or a module:attr that does not import
        raise UserError(f"--policy {a.policy}: {' '.join(str(e).split())}") from e
    try:
        return PolicyServer(policy, a.host, a.port, None, mapping, key, int(a.max_message_mb * 2**20))
    except (OSError, OverflowError) as e:  # the address is taken, or not this machine's
        raise UserError(f"--host {a.host} --port {a.port}: {e.strerror or e}; choose another --port (0: any free "
                        "one)") from e
    except ValueError as e:  # the policy does not fit --family (its action dimension)
        raise UserError(f"--policy {a.policy} --family {a.family}: {e}") from e


def main(argv: list[str]) -> int:
    a = parse(Args, argv, "serve-policy")
    if not isinstance(logging.getLevelName(a.log_level.upper()), int):
        raise UserError(f"--log-level {a.log_level}: not a logging level (DEBUG, INFO, WARNING, ERROR)")
    logging.basicConfig(level=a.log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    from sc3_jax.policies.openpi_server import serve_until_interrupted

    server = build_server(a)
    if not loopback(a.host):
        print(f"sc3 serve-policy: warning: listening on {server.listening}, beyond this machine: clients need the "
              "key; the traffic is not encrypted (put it behind TLS or an SSH tunnel)", file=sys.stderr, flush=True)
    local = "" if server.listening == server.url else f"; from this machine: {server.url}"
    print(f"serving {server.metadata['policy']} on {server.listening}{local} (family {server.metadata['family']}); "
          f"health check: http://{server.url.split('://', 1)[1]}/healthz", flush=True)
    print(f"metadata sent to every client: {json.dumps(server.metadata, default=str)}", flush=True)
    print(f"query it from our commands as --policy NAME={server.url}@TASK; Ctrl-C stops it", flush=True)
    try:
        serve_until_interrupted(server)  # Ctrl-C comes through: the command exits 130
    finally:
        print(f"stopped serving {server.metadata['policy']} on {server.url}", flush=True)
    return 0

"""``sc3 serve-policy``: serve one of our policies over openpi's WebSocket protocol (``openpi_server.py``).

    sc3 serve-policy --policy bus_bc_full [--family droid] [--port 8000] ...

``--policy`` takes every spelling of ``policies/resolve.py`` (a zoo name, zero | random | linear,
package.module:attr, ...).
"""
from __future__ import annotations

import argparse
import logging
from typing import Any, Callable, Sequence

from sc3_jax.policies.base import HostPolicy, JaxPolicy
from sc3_jax.policies.openpi_mappings import PRESETS, get_mapping
from sc3_jax.policies.openpi_server import PolicyServer, serve_until_interrupted


def _serve_policy_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="sc3 serve-policy",
                                description="Serve one of our policies over openpi's WebSocket protocol.")
    p.add_argument("--policy", required=True, help="a zoo name, zero | random | linear, or module:attr of a "
                   "JaxPolicy/HostPolicy or a factory returning one (policies/resolve.py)")
    p.add_argument("--host", default="0.0.0.0")
    p.add_argument("--port", type=int, default=8000, help="0 = any free port (printed)")
    p.add_argument("--family", default="native", choices=["native", *PRESETS],
                   help="observation keys clients send (native = our own observation dict)")
    p.add_argument("--image-size", type=int, nargs=2, metavar=("H", "W"), default=None,
                   help="image size our policy expects (family images are un-letterboxed and resized to it)")
    p.add_argument("--num-views", type=int, default=None,
                   help="number of views our policy expects (default: the family's, e.g. 4 for aloha)")
    p.add_argument("--task-prompt", action="append", default=[], metavar="ID=PROMPT",
                   help="prompt -> task id table entry (repeatable); default: the bussing / reverse-bussing prompts")
    p.add_argument("--default-task", type=int, default=None, help="task id for prompts not in the table")
    p.add_argument("--api-key", default=None, help="require 'Authorization: Api-Key <key>'")
    p.add_argument("--log-level", default="INFO")
    return p


def build_policy_server(argv: Sequence[str] | None = None,
                        resolve: Callable[[str], JaxPolicy | HostPolicy] | None = None) -> PolicyServer:
    """Parse ``sc3 serve-policy`` arguments and return the (bound, not yet serving) :class:`PolicyServer`."""
    args = _serve_policy_parser().parse_args(list(argv) if argv is not None else None)
    logging.basicConfig(level=args.log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    if resolve is None:
        from sc3_jax.policies.resolve import resolve as resolve_spec
        resolve = lambda spec: resolve_spec(spec).policy  # noqa: E731
    policy = resolve(args.policy)
    mapping = get_mapping(args.family)
    if mapping is not None:
        changes: dict[str, Any] = {"default_task": args.default_task}
        if args.num_views is not None:
            changes["num_views"] = args.num_views
        if args.image_size:
            changes["our_image_size"] = tuple(args.image_size)
        if args.task_prompt:
            table = {}
            for entry in args.task_prompt:
                tid, sep, prompt = entry.partition("=")
                if not sep:
                    raise ValueError(f"--task-prompt expects ID=PROMPT, got {entry!r}")
                table[int(tid)] = prompt
            changes["prompts"] = table
        mapping = mapping.replace(**changes)
    return PolicyServer(policy, args.host, args.port, None, mapping, args.api_key)


def serve_policy_main(argv: Sequence[str] | None = None,
                      resolve: Callable[[str], JaxPolicy | HostPolicy] | None = None) -> int:
    """``sc3 serve-policy --policy SPEC [--family droid] [--port 8000] ...``: serve one of our policies over
    openpi's protocol until interrupted (Ctrl-C). ``resolve`` (optional) turns the ``--policy`` string into a policy
    instead of ``policies.resolve``."""
    server = build_policy_server(argv, resolve)
    print(f"serving {server.metadata['policy']} on {server.url} (family {server.metadata['family']}); "
          f"health check: http://{server.url.split('://', 1)[1]}/healthz", flush=True)
    serve_until_interrupted(server)
    return 0

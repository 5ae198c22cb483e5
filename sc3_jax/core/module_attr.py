"""Objects named ``package.module:attr``: the one spelling by which a user names a policy, a scorer or a benchmark
that lives in their own code (``attr`` may be dotted)."""
from __future__ import annotations

import importlib
from typing import Any

from sc3_jax.core.errors import UserError


def load(spec: str, what: str) -> Any:
    """The object ``spec`` names; a one-line UserError naming ``what spec`` when it is malformed, its module cannot
    be imported or has no such attribute."""
    mod_name, colon, attr = spec.partition(":")
    if not colon or not mod_name or not attr:
        raise UserError(f"{what} {spec!r}: expected package.module:attr")
    try:
        obj = importlib.import_module(mod_name)
        for part in attr.split("."):
            obj = getattr(obj, part)
    except ImportError as e:
        raise UserError(f"{what} {spec!r}: cannot import {mod_name!r} ({e}); is it on PYTHONPATH?") from None
    except AttributeError:
        raise UserError(f"{what} {spec!r}: {mod_name!r} has no attribute {attr!r}") from None
    return obj

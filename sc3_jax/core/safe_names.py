"""Names that come from data (camera keys, episode ids, policy names, criteria) and become file names.

A dataset, a results store or a policy server is often someone else's: a name such as ``../../x`` or ``/etc/x`` must
never turn into a path outside the directory the user named. Every such name is checked where it enters
(:func:`check_name`: one allow-list of characters), every path joined from one goes through :func:`join_inside`, and
a name that is only shown (a report's video of a policy) is mapped to a harmless file name (:func:`file_name`).
"""
from __future__ import annotations

import hashlib
import os
import re
from pathlib import Path

from sc3_jax.core.errors import UserError

# letters, digits and . _ - : + @ ; not starting with "." (hidden files, "..") and at most 128 characters
_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.:+@-]{0,127}")
ALLOWED = "letters, digits and . _ - : + @ (not first: .), at most 128 characters"


def is_safe(name) -> bool:
    return isinstance(name, str) and _NAME.fullmatch(name) is not None


def check_name(name, what: str) -> str:
    """``name`` if it is safe as one file name, else a one-line ``UserError`` saying ``what`` it is."""
    if not is_safe(name):
        raise UserError(f"{what} {name!r}: a name that becomes a file name may hold only {ALLOWED}")
    return name


def join_inside(root: str | os.PathLike, *parts: str) -> Path:
    """``root / parts...``, refused (``UserError``) when a part is absolute or climbs out of ``root`` (``..``). Lexical,
    so a symlink the user made inside ``root`` is theirs to follow."""
    root = Path(root)
    path = root.joinpath(*parts)
    base = os.path.normpath(os.path.abspath(root))
    full = os.path.normpath(os.path.abspath(path))
    if any(os.path.isabs(p) for p in parts) or os.path.commonpath([base, full]) != base:
        raise UserError(f"{'/'.join(parts)!r} would be written outside {root}: a name from the data may not hold "
                        "'..' or start with '/'")
    return path


def file_name(name: str, suffix: str = "") -> str:
    """A file name for a name that is only shown: ``name`` itself when safe, else its safe characters and a short
    digest of the whole (two unsafe names never share a file)."""
    if is_safe(name + suffix):
        return name + suffix
    clean = re.sub(r"[^A-Za-z0-9_.-]", "_", name).lstrip(".")[:64] or "_"
    return f"{clean}-{hashlib.sha256(name.encode()).hexdigest()[:8]}{suffix}"

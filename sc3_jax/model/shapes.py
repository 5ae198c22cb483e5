"""One shape check for every weight import (diffusers Cosmos3 / Wan VAE, ``train.init_from``): a mismatch lists
every missing, unexpected and wrong-shape entry at once, so a user fixes a checkpoint in one round."""
from __future__ import annotations


def check_shapes(expected: dict[str, tuple], got: dict[str, tuple], what: str) -> None:
    """Raise ValueError(``what`` + a listing) unless ``got`` has exactly ``expected``'s keys and shapes."""
    missing = sorted(set(expected) - set(got))
    unexpected = sorted(set(got) - set(expected))
    wrong = sorted(f"{k}: {tuple(got[k])} (expected {tuple(expected[k])})" for k in set(expected) & set(got)
                   if tuple(got[k]) != tuple(expected[k]))
    if missing or unexpected or wrong:
        lines = [what]
        for name, items in (("missing", missing), ("unexpected", unexpected), ("wrong shape", wrong)):
            if items:
                lines.append(f"  {name} ({len(items)}):")
                lines += [f"    {x}" for x in items]
        raise ValueError("\n".join(lines))

"""The tests marked ``lerobot`` need lerobot >= 0.6.1 beside sc3_jax (Python >= 3.12: .ci/run's last section makes
that environment); elsewhere their module skips whole. ``require()`` at a test module's top."""
import importlib.util
from importlib.metadata import version

import pytest


def require() -> None:
    ok = importlib.util.find_spec("lerobot") is not None and \
        tuple(int(x) for x in version("lerobot").split(".")[:2]) >= (0, 6)
    if not ok:
        pytest.skip("needs lerobot >= 0.6.1 beside sc3_jax (Python >= 3.12; .ci/run's last section)",
                    allow_module_level=True)

"""Every test process sees 8 host devices so sharded code paths run for real on a CPU."""
import os

os.environ.setdefault("JAX_PLATFORMS", "cpu")
if "--xla_force_host_platform_device_count" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=8").strip()
os.environ.setdefault("MUJOCO_GL", "egl")  # headless software rendering (Mesa)
# Almost every test is bound by XLA compile time, not run time: skipping LLVM's backend optimisations makes the
# suite ~40% faster. The one run-time-bound test (test_learning.py) runs its training in a subprocess without it.
FAST_COMPILE = "--xla_backend_optimization_level=0"
if "--xla_backend_optimization_level" not in os.environ["XLA_FLAGS"]:
    os.environ["XLA_FLAGS"] += " " + FAST_COMPILE


def optimised_env() -> dict:
    """The environment for a subprocess that compiles as a user's process does (run-time-bound work, and values
    that depend on the optimisation level, such as the bits of random initialisations)."""
    # XLA's default level, spelled out so that a conftest imported by the subprocess does not add FAST_COMPILE again
    default = "--xla_backend_optimization_level=3"
    return {**os.environ, "XLA_FLAGS": os.environ["XLA_FLAGS"].replace(FAST_COMPILE, default)}


def pytest_collection_modifyitems(config, items):
    """Slow tests first: under `-n auto` the longest module starts at once and the others fill the other workers
    around it, instead of it starting last and running alone (pyproject's --no-loadscope-reorder keeps this order:
    xdist would otherwise send the modules with the most tests first)."""
    items.sort(key=lambda item: item.get_closest_marker("slow") is None)  # stable: file order otherwise

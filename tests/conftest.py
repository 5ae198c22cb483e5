"""Every test process sees 8 host devices so sharded code paths run for real on a CPU."""
import os

os.environ.setdefault("JAX_PLATFORMS", "cpu")
if "--xla_force_host_platform_device_count" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=8").strip()
os.environ.setdefault("MUJOCO_GL", "egl")  # headless software rendering (Mesa)


def pytest_collection_modifyitems(config, items):
    """Slow tests first: under `-n auto` the longest module starts at once and the others fill the other workers
    around it, instead of it starting last and running alone."""
    items.sort(key=lambda item: item.get_closest_marker("slow") is None)  # stable: file order otherwise

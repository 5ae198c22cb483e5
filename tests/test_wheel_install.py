"""The named configs live at the top of the checkout (``configs/``) and install as the package ``sc3_jax.configs``
(pyproject's package-dir): the editable install finds them there, and a wheel (what ``pip install .`` installs) carries
them, lists them and trains ``tiny`` from them with the checkout nowhere on the path (slow)."""
import importlib.util
import json
import os
import re
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from sc3_jax.core import config

ROOT = Path(__file__).resolve().parents[1]
NAMES = {"ablation_forward_only", "ablation_no_cvi", "ablation_no_decouple", "ablation_no_id", "aloha_wan",
         "bussing_latent", "bussing_latent_gpu", "bussing_sim", "cpu_medium", "paper", "so101_latent", "tiny"}


def test_the_editable_install_maps_sc3_jax_configs_to_the_top_level_folder():
    import sc3_jax.configs

    assert [Path(p).resolve() for p in sc3_jax.configs.__path__] == [ROOT / "configs"]
    assert not (ROOT / "sc3_jax" / "configs").exists()  # one copy: the mapped folder, none inside the package
    assert config.configs_dir() == ROOT / "configs"
    assert set(config.available_configs()) == NAMES
    assert config.load_config("so101_latent").name == "so101_latent"  # a config built on another, by name


def test_a_checkout_with_no_install_reads_the_folder_beside_the_package(monkeypatch):
    """``PYTHONPATH=.`` (the GPU playbook's way): no package sc3_jax.configs, the folder beside sc3_jax/ instead."""
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, package=None: None)
    assert config.configs_dir() == ROOT / "configs"
    assert set(config.available_configs()) == NAMES


def test_pyproject_lists_every_package_and_maps_the_configs():
    """packages.find cannot be combined with a package mapped from another folder, so the list is explicit: what
    packages.find found before (every folder of sc3_jax/, its data folders included) plus the configs; a folder
    missing from it would be missing from a wheel."""
    from setuptools import find_namespace_packages

    setuptools = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    assert setuptools["package-dir"] == {"sc3_jax.configs": "configs"}
    found = set(find_namespace_packages(where=str(ROOT), include=["sc3_jax*"]))
    assert set(setuptools["packages"]) == found | {"sc3_jax.configs"}


def _can_build_here() -> bool:
    """Whether this environment's setuptools builds a wheel by itself (``--no-build-isolation``): from 70.1 on it
    has bdist_wheel, before that it needs the ``wheel`` package; otherwise pip builds in an isolated environment
    (from the package index configured here)."""
    try:
        import setuptools
    except ImportError:
        return False
    version = tuple(int(x) for x in re.findall(r"\d+", setuptools.__version__)[:2])
    return version >= (70, 1) or importlib.util.find_spec("wheel") is not None


@pytest.mark.slow
def test_a_wheel_lists_every_config_and_trains_tiny(tmp_path):
    # build from a copy of what the wheel is made of, so the checkout gets no build/ folder
    src = tmp_path / "src"
    ignore = shutil.ignore_patterns("__pycache__", "*.egg-info")
    for name in ("sc3_jax", "configs"):
        shutil.copytree(ROOT / name, src / name, ignore=ignore)
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, src / name)
    isolation = ["--no-build-isolation"] if _can_build_here() else []
    subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", *isolation, "-w", str(tmp_path / "whl"),
                    str(src)], check=True, cwd=tmp_path)
    wheel = next((tmp_path / "whl").glob("sc3_jax-*.whl"))
    site = tmp_path / "site"
    subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--no-index", "--target", str(site),
                    str(wheel)], check=True, cwd=tmp_path)
    # the wheel's package first, its dependencies from this environment; run from elsewhere than the checkout;
    # one host device (the suite's 8 would not divide a batch of 2)
    env = {**os.environ, "PYTHONPATH": str(site), "XLA_FLAGS": "--xla_backend_optimization_level=0"}

    def python(*args, check=True):
        return subprocess.run([sys.executable, *args], env=env, cwd=tmp_path, capture_output=True, text=True,
                              check=check)

    where = python("-c", "import sc3_jax, sc3_jax.configs; from sc3_jax.core.config import configs_dir; "
                   "print(sc3_jax.__file__); print(configs_dir())").stdout.split()
    assert all(w.startswith(str(site)) for w in where), f"imported {where}, not the wheel's in {site}"
    listed = python("-m", "sc3_jax.cli", "configs")
    names = {line.split()[0] for line in listed.stdout.splitlines()[1:] if line.strip()}
    assert names == NAMES, listed.stdout

    from sc3_jax.data import synthetic

    data = tmp_path / "episodes"
    synthetic.generate(data, 4, length=24, progress=False)
    run = python("-m", "sc3_jax.cli", "train", "--config", "tiny", "--data", str(data), "--batch", "2",
                 "--train.steps", "2", "--train.warmup-steps", "1", "--train.workdir", str(tmp_path / "w"),
                 "--train.no-progress", check=False)
    assert run.returncode == 0, run.stdout[-2000:] + run.stderr[-2000:]
    rows = [json.loads(line) for line in (tmp_path / "w" / "metrics.jsonl").read_text().splitlines()]
    assert rows[-1]["step"] == 2

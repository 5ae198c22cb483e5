"""``lerobot:PATH``: a LeRobot policy (a ``pretrained_model`` directory that ``lerobot-train`` wrote: ACT, diffusion
policy, ...) acting in the world model or a simulator, run by LeRobot's own code, unchanged.

Where lerobot is importable beside sc3_jax (Python >= 3.12 with lerobot 0.6: ``pip install -e ".[gym,lerobot]"
"lerobot[dataset]==0.6.1"``, what ``.ci/run``'s last section makes) and ``SC3_LEROBOT_PYTHON`` is unset, the policy
loads in-process (``lerobot_child.ChunkPolicy``, torch on the CPU beside JAX). The fallback, for a Python 3.11
environment (lerobot 0.4.4, the newest there, pins ``torch<2.11`` and ``diffusers<0.36``; our interop extra needs
``diffusers>=0.42``): the policy runs in a child process started with the Python of the user's LeRobot environment,
``SC3_LEROBOT_PYTHON=VENV/bin/python``. The child is ``lerobot_child.py`` (standard library, numpy, torch and lerobot
only); it talks over its stdin and stdout, so no port, no key and no websockets package are needed there, and it dies
with us. (An openpi-wire server in that environment would work as well, at the price of a port and a dependency; a
pipe is all a local policy needs.)

Either way the policy loads on the first ``infer``. The child ends with ``close()`` (or exit); its stderr goes to an
unnamed temporary file (nothing is left behind) whose last line is in the error when it fails."""
from __future__ import annotations

import importlib.util
import io
import json
import os
import struct
import subprocess
import sys
import tempfile
import weakref
from pathlib import Path

import numpy as np

from sc3_jax.core.errors import UserError

PREFIX = "lerobot:"
PYTHON_ENV = "SC3_LEROBOT_PYTHON"  # the Python of an environment with lerobot installed
CHILD = Path(__file__).with_name("lerobot_child.py")
# the child imported as a top-level module from its directory: none of sc3_jax (nor jax) loads in that environment
_RUN_CHILD = (f"import sys; sys.path.insert(0, {str(CHILD.parent)!r}); import lerobot_child; "
              "sys.exit(lerobot_child.main(sys.argv[1:]))")


def _declared(path: Path) -> tuple[int, int, int | None]:
    """(chunk, action_dim, state_dim) from PATH/config.json, read without lerobot: known before the child starts."""
    cfg_path = path / "config.json"
    if not cfg_path.is_file():
        raise UserError(f"lerobot:{path}: no config.json (give a LeRobot pretrained_model directory, e.g. "
                        "OUTPUT/checkpoints/last/pretrained_model)")
    try:
        cfg = json.loads(cfg_path.read_text())
        action = cfg["output_features"]["action"]["shape"][0]
        state = (cfg.get("input_features") or {}).get("observation.state")
        return int(cfg.get("n_action_steps", 1)), int(action), None if state is None else int(state["shape"][0])
    except (ValueError, KeyError, TypeError, IndexError) as e:
        raise UserError(f"{cfg_path}: not a LeRobot policy config ({type(e).__name__}: {e})") from None


class LeRobotPolicy:
    """A HostPolicy (``policies/base.py``) served by ``lerobot_child.py`` in the LeRobot environment."""

    def __init__(self, path: str | os.PathLike, python: str | None = None, device: str = "cpu"):
        self.path = Path(path).expanduser()
        self.chunk, self.action_dim, self.state_dim = _declared(self.path)
        self.python = python or os.environ.get(PYTHON_ENV) or sys.executable
        # in-process where this interpreter has lerobot and no other environment is named for it
        self.in_process = python is None and not os.environ.get(PYTHON_ENV) and _have_lerobot()
        self.device = device
        self.name = f"{PREFIX}{path}"
        self._proc: subprocess.Popen | None = None
        self._log = None
        self._here = None  # the in-process lerobot_child.ChunkPolicy, once loaded

    # -- the child ----------------------------------------------------------------------------------------------
    def _start(self) -> None:
        # an unnamed file: the child's stderr, read back for errors, gone with this process (nothing left in /tmp)
        self._log = tempfile.TemporaryFile("w+b")
        try:
            self._proc = subprocess.Popen([self.python, "-c", _RUN_CHILD, str(self.path), "--device", self.device],
                                          stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=self._log)
        except OSError as e:
            raise UserError(f"{self.name}: cannot start {self.python} ({e}); set {PYTHON_ENV} to the python of an "
                            "environment with lerobot installed") from None
        weakref.finalize(self, _stop, self._proc)
        kind, payload = self._receive()
        self._check_meta(json.loads(payload))

    def _receive(self) -> tuple[bytes, bytes]:
        head = self._proc.stdout.read(9)
        if len(head) < 9:
            raise UserError(f"{self.name}: the LeRobot child ({self.python}) ended: {self._tail()}")
        (n,) = struct.unpack("<Q", head[1:])
        kind, payload = head[:1], self._proc.stdout.read(n)
        if kind == b"E":
            said = payload.decode(errors="replace")
            hint = (f"; set {PYTHON_ENV} to the python of an environment with lerobot"
                    if said.startswith("ModuleNotFoundError") else "")
            raise UserError(f"{self.name}: {' '.join(said.split())} (python: {self.python}{hint})")
        return kind, payload

    def _send(self, kind: bytes, payload: bytes) -> None:
        try:
            self._proc.stdin.write(kind + struct.pack("<Q", len(payload)) + payload)
            self._proc.stdin.flush()
        except BrokenPipeError:
            raise UserError(f"{self.name}: the LeRobot child ended: {self._tail()}") from None

    def _tail(self) -> str:
        self._log.flush()
        self._log.seek(0)
        lines = self._log.read().decode(errors="replace").strip().splitlines()
        hint = f" (is lerobot installed for {self.python}? set {PYTHON_ENV})" if any(
            "No module named 'lerobot'" in x for x in lines) else ""
        return (lines[-1] if lines else "no output") + hint

    # -- HostPolicy -----------------------------------------------------------------------------------------------
    def infer(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        images, state = np.asarray(obs["images"], np.uint8), np.asarray(obs["state"], np.float32)
        if self.in_process:
            actions = self._infer_here(images, state)
        else:
            if self._proc is None:
                self._start()
            buf = io.BytesIO()
            np.savez(buf, images=images, state=state)
            self._send(b"N", buf.getvalue())
            _, payload = self._receive()
            actions = np.load(io.BytesIO(payload))["actions"].astype(np.float32)
        if actions.shape != (self.chunk, self.action_dim):
            raise UserError(f"{self.name}: answered actions of shape {actions.shape}, expected "
                            f"({self.chunk}, {self.action_dim})")
        return actions

    def reset(self) -> None:
        """A new episode: clear the policy's action queue and history."""
        if self._here is not None:
            self._here.reset()
        if self._proc is not None:
            self._send(b"J", json.dumps({"reset": True}).encode())

    # -- in-process ---------------------------------------------------------------------------------------------
    def _infer_here(self, images: np.ndarray, state: np.ndarray) -> np.ndarray:
        from sc3_jax.policies.lerobot_child import ChunkPolicy

        try:
            if self._here is None:
                self._here = ChunkPolicy(str(self.path), self.device)
                self._check_meta(self._here.meta)
            return np.asarray(self._here.infer(images, state), np.float32)
        except UserError:
            raise
        except Exception as e:  # noqa: BLE001 - lerobot's own failure, said in one line as the child says it
            first = (str(e).strip().splitlines() or [""])[0][:300]
            raise UserError(f"{self.name}: {type(e).__name__}: {first} (in-process lerobot)") from None

    def _check_meta(self, meta: dict) -> None:
        if meta["chunk"] != self.chunk or meta["action_dim"] != self.action_dim:
            raise UserError(f"{self.name}: the loaded policy acts {meta['chunk']} x {meta['action_dim']}-D, its "
                            f"config.json says {self.chunk} x {self.action_dim}-D")
        self.views = meta["views"]

    def close(self) -> None:
        self._here = None
        if self._proc is not None:
            _stop(self._proc)
            self._proc = None


def _have_lerobot() -> bool:
    """lerobot importable here, new enough to share the interpreter (0.5 and later: Python >= 3.12, torch beside
    JAX); an older one (0.4, the Python 3.11 line) runs through the child."""
    if importlib.util.find_spec("lerobot") is None:
        return False
    from importlib.metadata import PackageNotFoundError, version
    try:
        major, minor = (int(x) for x in version("lerobot").split(".")[:2])
    except (PackageNotFoundError, ValueError):
        return False
    return (major, minor) >= (0, 5)


def _stop(proc: subprocess.Popen) -> None:
    try:
        proc.stdin.close()
        proc.wait(timeout=10)
    except (OSError, subprocess.TimeoutExpired):
        proc.kill()

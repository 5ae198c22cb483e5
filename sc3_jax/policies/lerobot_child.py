"""The other end of ``lerobot:PATH`` (``lerobot_policy.py``): run by the Python of an environment that has ``lerobot``
(not ours: lerobot pins torch and diffusers versions that conflict with our extras), it loads a LeRobot
``pretrained_model`` directory the way a LeRobot user runs it and answers observations on its stdin with action
chunks on its stdout. It imports nothing of sc3_jax, only the standard library, numpy, torch and lerobot.

    VENV/bin/python -c "import sys; sys.path.insert(0, DIR); import lerobot_child; \
                        sys.exit(lerobot_child.main(sys.argv[1:]))" PATH [--device cpu]

(``lerobot_policy.LeRobotPolicy`` starts it so, DIR being this file's directory: imported as a top-level module it
loads nothing of sc3_jax.)

Frames, both ways: one kind byte (``J`` JSON, ``N`` an ``np.savez`` archive, ``E`` a one-line error), the payload's
length (8 bytes, little-endian), the payload. The child first sends ``J`` {chunk, action_dim, state_dim, views,
type}; then, per ``N`` observation {images uint8 [V, H, W, 3], state float32 [S]}, a ``N`` {actions [chunk, A]} or
an ``E`` line (the child stays up). A ``J`` {"reset": true} clears the policy's queues. End of stdin: it exits.

Inference (``ChunkPolicy``, also what runs in-process where lerobot sits beside sc3_jax), as ``lerobot-record`` does
it in lerobot 0.4 to 0.6: ``get_policy_class(type).from_pretrained(PATH)``,
``make_pre_post_processors(config, pretrained_path=PATH)`` (normalisation lives in those two pipelines),
``prepare_observation_for_inference`` -> preprocessor -> ``predict_action_chunk`` -> postprocessor; the first
``n_action_steps`` actions of the chunk are returned (what the policy would execute before predicting again). Our
views go to the policy's image features in their order; the state to ``observation.state``.
"""
from __future__ import annotations

import io
import json
import os
import struct
import sys


def _channel():
    """The real stdout for frames; fd 1 then points at stderr, so that whatever lerobot or torch print (from Python
    or C) cannot corrupt a frame."""
    out = os.fdopen(os.dup(1), "wb", buffering=0)
    os.dup2(2, 1)
    sys.stdout = sys.stderr
    return out


def send(out, kind: bytes, payload: bytes) -> None:
    out.write(kind + struct.pack("<Q", len(payload)) + payload)


def receive(inp) -> tuple[bytes, bytes] | None:
    head = inp.read(9)
    if len(head) < 9:
        return None
    (n,) = struct.unpack("<Q", head[1:])
    return head[:1], inp.read(n)


class ChunkPolicy:
    """A LeRobot ``pretrained_model`` loaded as ``lerobot-record`` loads it, answering one observation with the chunk
    of actions it would execute: used here, in the child, and in-process by ``lerobot_policy.LeRobotPolicy`` when
    lerobot is importable beside sc3_jax (Python >= 3.12, lerobot 0.6)."""

    def __init__(self, path: str, device: str = "cpu"):
        import torch
        from lerobot.policies.factory import get_policy_class, make_pre_post_processors

        with open(os.path.join(path, "config.json")) as f:
            kind = json.load(f)["type"]
        self.device = torch.device(device)
        self.policy = get_policy_class(kind).from_pretrained(path).to(device).eval()
        self.pre, self.post = make_pre_post_processors(self.policy.config, pretrained_path=path)
        feats = self.policy.config.input_features
        self.views = [k for k, ft in feats.items() if str(getattr(ft.type, "value", ft.type)) == "VISUAL"]
        self.state = feats.get("observation.state")
        act = self.policy.config.output_features["action"]
        self.chunk = int(getattr(self.policy.config, "n_action_steps", 1))
        self.meta = {"chunk": self.chunk, "action_dim": int(act.shape[0]), "type": kind, "views": self.views,
                     "state_dim": int(self.state.shape[0]) if self.state is not None else None}

    def infer(self, images, state):
        """images uint8 [V, H, W, 3] (the policy's cameras in order), state float32 [S] -> actions float32 [chunk, A]"""
        import numpy as np
        import torch
        from lerobot.policies.utils import prepare_observation_for_inference

        if len(images) != len(self.views):
            raise ValueError(f"the policy reads {len(self.views)} camera(s) {self.views}, the observation has "
                             f"{len(images)}")
        obs = {k: np.array(images[i]) for i, k in enumerate(self.views)}  # a copy: torch wants it writable
        if self.state is not None:
            obs["observation.state"] = np.array(state, np.float32)
        with torch.inference_mode():
            batch = self.pre(prepare_observation_for_inference(obs, self.device))
            actions = self.post(self.policy.predict_action_chunk(batch))[0, :self.chunk]
        return actions.float().cpu().numpy()

    def reset(self) -> None:
        self.policy.reset()


def main(argv: list[str]) -> int:
    out = _channel()
    inp = sys.stdin.buffer
    path = argv[0]
    device = argv[argv.index("--device") + 1] if "--device" in argv else "cpu"
    try:
        import numpy as np
        policy = ChunkPolicy(path, device)
    except Exception as e:  # noqa: BLE001 - told to the parent as one line, then exit
        send(out, b"E", f"{type(e).__name__}: {str(e).strip().splitlines()[0] if str(e).strip() else ''}".encode())
        return 1
    send(out, b"J", json.dumps(policy.meta).encode())
    while (msg := receive(inp)) is not None:
        kind_b, payload = msg
        try:
            if kind_b == b"J":
                if json.loads(payload).get("reset"):
                    policy.reset()
                continue
            z = np.load(io.BytesIO(payload))
            buf = io.BytesIO()
            np.savez(buf, actions=policy.infer(z["images"], z["state"]))
            send(out, b"N", buf.getvalue())
        except Exception as e:  # noqa: BLE001 - one line to the parent; the child stays up for the next request
            send(out, b"E", f"{type(e).__name__}: {(str(e).strip().splitlines() or [''])[0][:300]}".encode())
    return 0

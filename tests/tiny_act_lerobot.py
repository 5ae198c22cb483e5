"""Train a tiny LeRobot ACT policy for a few steps on random frames and write its pretrained_model directory (run by
the Python of an environment with lerobot: tests/test_lerobot_policy.py). Usage:
    python tiny_act_lerobot.py OUT --views N --image H W --state-dim S --action-dim A --chunk C [--steps K]"""
import sys

import numpy as np
import torch
from lerobot.configs.types import FeatureType, NormalizationMode, PolicyFeature
from lerobot.policies.act.configuration_act import ACTConfig
from lerobot.policies.act.modeling_act import ACTPolicy
from lerobot.policies.factory import make_pre_post_processors


def arg(name, n=1):
    i = sys.argv.index(name)
    return [int(x) for x in sys.argv[i + 1:i + 1 + n]]


out = sys.argv[1]
(views,), (h, w), (s,), (a,), (chunk,) = (arg("--views"), arg("--image", 2), arg("--state-dim"), arg("--action-dim"),
                                          arg("--chunk"))
steps = arg("--steps")[0] if "--steps" in sys.argv else 3
torch.manual_seed(0)
image_keys = [f"observation.images.cam{i}" for i in range(views)]
inputs = {"observation.state": PolicyFeature(FeatureType.STATE, (s,)),
          **{k: PolicyFeature(FeatureType.VISUAL, (3, h, w)) for k in image_keys}}
cfg = ACTConfig(input_features=inputs, output_features={"action": PolicyFeature(FeatureType.ACTION, (a,))},
                chunk_size=chunk, n_action_steps=chunk, dim_model=32, dim_feedforward=64, n_heads=2, n_encoder_layers=1,
                n_decoder_layers=1, n_vae_encoder_layers=1, latent_dim=8, pretrained_backbone_weights=None,
                device="cpu", normalization_mapping={"VISUAL": NormalizationMode.MEAN_STD,
                                                     "STATE": NormalizationMode.MEAN_STD,
                                                     "ACTION": NormalizationMode.MEAN_STD})
stats = {"observation.state": {"mean": np.zeros(s, np.float32), "std": np.ones(s, np.float32)},
         "action": {"mean": np.zeros(a, np.float32), "std": np.full(a, 0.5, np.float32)},
         **{k: {"mean": np.full((3, 1, 1), 0.5, np.float32), "std": np.full((3, 1, 1), 0.25, np.float32)}
            for k in image_keys}}
policy = ACTPolicy(cfg)
pre, post = make_pre_post_processors(cfg, dataset_stats=stats)
opt = torch.optim.AdamW(policy.parameters(), lr=1e-3)
for step in range(steps):
    batch = {"observation.state": torch.randn(4, s), "action": torch.randn(4, cfg.chunk_size, a) * 0.5,
             "action_is_pad": torch.zeros(4, cfg.chunk_size, dtype=torch.bool),
             **{k: torch.rand(4, 3, h, w) for k in image_keys}}
    loss, _ = policy.forward(pre(batch))
    opt.zero_grad()
    loss.backward()
    opt.step()
    print(f"step {step} loss {loss.item():.3f}", file=sys.stderr)
policy.save_pretrained(out)
pre.save_pretrained(out)
post.save_pretrained(out)
print(out)

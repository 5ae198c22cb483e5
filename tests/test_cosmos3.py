"""Cosmos3 compatibility: our DiT under a Cosmos3 config computes what diffusers' ``Cosmos3OmniTransformer``
computes, and ``model/convert.py`` maps its checkpoints both ways.

The interop tests build a tiny random Cosmos3OmniTransformer (torch + diffusers, extra [interop]); the others need
neither."""
import ast
import copy
import hashlib
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import optimised_env
from sc3_jax.core.config import ModelConfig, available_configs, load_config
from sc3_jax.model import convert, cosmos3, dit

TINY = {"hidden_size": 64, "num_hidden_layers": 2, "num_attention_heads": 4, "num_key_value_heads": 2,
        "head_dim": 32, "intermediate_size": 96, "rope_axes_dim": [6, 5, 5], "latent_channel": 4,
        "latent_patch_size": 2, "patch_latent_dim": 16, "action_gen": True, "action_dim": 8,
        "num_embodiment_domains": 3, "vocab_size": 50}
L_TEXT, F, LAT_H, LAT_W, N_ACT = 5, 3, 4, 6, 8  # text tokens, latent frames, latent size, actions (4 per frame)


# ----------------------------------------------------------------------------------------------------------------
# No torch needed
# ----------------------------------------------------------------------------------------------------------------
def _tiny_cfg(**overrides):
    return convert.config_from_diffusers({"_class_name": "Cosmos3OmniTransformer", **TINY}, **overrides)


def _param_digest(params) -> str:
    h = hashlib.sha256()
    for kp, v in jax.tree_util.tree_flatten_with_path(params)[0]:
        h.update(jax.tree_util.keystr(kp).encode())
        h.update(np.asarray(v).tobytes())
    return h.hexdigest()


def _spec_digest(cfg, token_dim, grid) -> str:
    specs = dit.param_specs(cfg, token_dim, grid)
    flat = jax.tree_util.tree_flatten_with_path(specs, is_leaf=lambda x: isinstance(x, dit.ParamSpec))[0]
    return hashlib.sha256(repr([(jax.tree_util.keystr(k), (s.shape, s.axes, s.init, s.fan_in))
                                for k, s in flat]).encode()).hexdigest()


# Recorded with the DiT as it was before the Cosmos3 options existed (git HEAD dit.py). If ModelConfig's defaults
# or param_specs change on purpose, re-record them.
DEFAULT_SPECS_SHA256 = "89c30fcb644efd1263a607db3473e6ab043adc70c7d3422287551468117059df"
DEFAULT_PARAMS_SHA256 = "d8c902ce6d9d3c3afb173c3a604b81160a98eb1e0819a1feda038b1535310608"  # CPU init values


def test_default_param_trees_unchanged():
    """The Cosmos3 options default off: no named config gains a parameter, and the default config's parameter
    specs and initial values are bit-identical to what they were before those options existed."""
    for name in available_configs():
        cfg = load_config(name).model
        assert (cfg.layout == "sc3" or cfg.tokenizer in ("wan2.1", "wan2.2")) and not cfg.text_pathway, name
        specs = dit.param_specs(cfg, 48, (4, 4))
        assert not {"text_layers", "text_norm", "embed_tokens", "lm_head"} & set(specs), name
    assert _spec_digest(ModelConfig(), 48, (4, 4)) == DEFAULT_SPECS_SHA256
    if jax.default_backend() == "cpu":  # the init values as a user's process compiles them (the suite uses -O0)
        code = ("import jax, sys; from sc3_jax.core.config import ModelConfig; from sc3_jax.model import dit; "
                "sys.path.insert(0, 'tests'); from test_cosmos3 import _param_digest; "
                "print(_param_digest(dit.init_params(ModelConfig(), 48, jax.random.key(0), (4, 4))))")
        out = subprocess.run([sys.executable, "-c", code], env=optimised_env(), check=True, capture_output=True,
                             text=True, cwd=Path(__file__).parents[1])
        assert out.stdout.split()[-1] == DEFAULT_PARAMS_SHA256


def test_cosmos3_config_and_param_tree():
    cfg = _tiny_cfg()
    assert (cfg.layout, cfg.text_pathway, cfg.view_embedding, cfg.prediction) == ("cosmos3", True, False, "velocity")
    assert (cfg.dim, cfg.depth, cfg.num_heads, cfg.num_kv_heads, cfg.mlp_dim, cfg.channels, cfg.patch_size) == (
        64, 2, 4, 2, 96, 4, 2)
    specs = dit.param_specs(cfg, convert.token_dim(cfg))
    assert set(specs["text_layers"]) == set(specs["layers"])
    # every parameter has a diffusers key, and the map covers all of them once
    emap = convert.key_map(cfg)
    assert len(emap) == 17 + 2 * 11 * cfg.depth
    # keys a config leaves out take diffusers' defaults, not ours
    full = convert.config_from_diffusers({"action_gen": True, "action_dim": 7})
    assert (full.dim, full.depth, full.head_dim, full.rope_axes_dim, full.rope_theta, full.channels) == (
        4096, 36, 128, (24, 20, 20), 5e6, 48)
    with pytest.raises(ValueError, match="unsupported Cosmos3OmniTransformer options: sound_gen=True"):
        convert.config_from_diffusers({**TINY, "sound_gen": True})
    with pytest.raises(ValueError, match="action_gen"):
        convert.config_from_diffusers({k: v for k, v in TINY.items() if k != "action_gen"})
    with pytest.raises(ValueError, match="unknown .* config keys \\['new_option'\\]"):
        convert.config_from_diffusers({**TINY, "new_option": 1})
    with pytest.raises(ValueError, match="view_embedding"):
        convert.config_to_diffusers(ModelConfig())


def test_state_dict_round_trip_and_key_errors():
    cfg = _tiny_cfg()
    params = dit.init_params(cfg, convert.token_dim(cfg), jax.random.key(0))
    sd = convert.state_dict_from_params(cfg, params)
    assert sd["layers.1.self_attn.to_q.weight"].shape == (4 * 32, 64)
    assert sd["layers.0.self_attn.to_out.weight"].shape == (64, 4 * 32)
    assert sd["action_proj_in.fc.weight"].shape == (3, 8 * 64)
    back = convert.params_from_state_dict(cfg, sd)
    assert jax.tree.structure(back) == jax.tree.structure(params)
    assert all(np.array_equal(a, b) for a, b in zip(jax.tree.leaves(back), jax.tree.leaves(params)))
    # torch Linear layout: y = x @ W.T  <->  ours y = x @ w
    np.testing.assert_array_equal(sd["layers.1.self_attn.add_k_proj.weight"].T.reshape(64, 2, 32),
                                  params["layers"]["wk"][1])

    bad = dict(sd)
    del bad["layers.1.mlp_moe_gen.down_proj.weight"]
    bad["model.layers.0.extra.weight"] = np.zeros(3, np.float32)
    bad["proj_in.bias"] = np.zeros(65, np.float32)
    with pytest.raises(ValueError) as e:
        convert.params_from_state_dict(cfg, bad)
    msg = str(e.value)
    assert "missing (1):\n    layers.1.mlp_moe_gen.down_proj.weight" in msg
    assert "unexpected (1):\n    model.layers.0.extra.weight" in msg
    assert "wrong shape (1):\n    proj_in.bias: (65,) (expected (64,))" in msg

    wrong = jax.tree.map(lambda x: x, params)
    del wrong["lm_head"]
    with pytest.raises(ValueError, match="missing \\(1\\):\n    lm_head"):
        convert.state_dict_from_params(cfg, wrong)


def test_cosmos3_positions_layout():
    cfg = _tiny_cfg(fps=30.0)
    stride = jnp.array([1, 2])
    pos = cosmos3.positions(cfg, stride, L_TEXT, 1, F, 1, (2, 3), N_ACT)
    assert pos.shape == (2, F * 6 + N_ACT, 3)
    off = L_TEXT + 15000
    # video: t = offset + frame * base_fps / fps, row/col = patch row/col
    np.testing.assert_allclose(pos[0, :F * 6:6, 0], off + np.arange(F) * 24 / 30)
    np.testing.assert_allclose(pos[1, :F * 6:6, 0], off + np.arange(F) * 24 / 15)
    np.testing.assert_array_equal(pos[0, :6, 1:], [[0, 0], [0, 1], [0, 2], [1, 0], [1, 1], [1, 2]])
    # actions: t = offset + (i + 1) * (base_fps / 4) / fps, row = col = 0 (4 actions per latent frame)
    np.testing.assert_allclose(pos[0, F * 6:, 0], off + (np.arange(N_ACT) + 1) * 6 / 30)
    np.testing.assert_array_equal(pos[0, F * 6:, 1:], 0)
    np.testing.assert_array_equal(cosmos3.text_positions(3), [[0, 0, 0], [1, 1, 1], [2, 2, 2]])
    # the timestep embedding sees the quantised scheduler timestep int(1000 t) * 0.001
    e = cosmos3.timestep_embedding(jnp.array([0.7349, 0.7341]), 256, 0.001)
    np.testing.assert_array_equal(e[0], e[1])
    np.testing.assert_allclose(e[0, :128], np.cos(0.734 * np.exp(-math.log(1e4) * np.arange(128) / 128)),
                               atol=1e-6)


# ----------------------------------------------------------------------------------------------------------------
# Against diffusers
# ----------------------------------------------------------------------------------------------------------------
def _pipeline_position_fns():
    """The omni pipeline's own mRoPE id builders, taken from its source (importing the pipeline module needs the
    `transformers` package, which the model itself does not)."""
    import diffusers
    import torch

    path = os.path.join(os.path.dirname(diffusers.__file__), "pipelines", "cosmos", "pipeline_cosmos3_omni.py")
    with open(path) as f:
        tree = ast.parse(f.read())
    names = {"get_3d_mrope_ids_text_tokens", "get_3d_mrope_ids_vae_tokens"}
    fns = [n for n in tree.body if isinstance(n, ast.FunctionDef) and n.name in names]
    assert len(fns) == 2
    ns = {"torch": torch, "math": math}
    exec(compile(ast.Module(body=fns, type_ignores=[]), path, "exec"), ns)  # noqa: S102 (diffusers' own code)
    return ns["get_3d_mrope_ids_text_tokens"], ns["get_3d_mrope_ids_vae_tokens"]


@pytest.fixture(scope="module")
def tiny_diffusers(tmp_path_factory):
    torch = pytest.importorskip("torch")
    tc3 = pytest.importorskip("diffusers.models.transformers.transformer_cosmos3")
    torch.manual_seed(0)
    model = tc3.Cosmos3OmniTransformer(**TINY).eval()
    with torch.no_grad():  # perturb everything (norm gains are ones, action_modality_embed zeros at init)
        for p in model.parameters():
            p.add_(0.1 * torch.randn_like(p))
    path = str(tmp_path_factory.mktemp("cosmos3") / "transformer")
    model.save_pretrained(path, safe_serialization=True)
    return model, path


def _patchify(latent: np.ndarray, p: int) -> np.ndarray:
    """[C, T, H, W] -> [T, (H/p)(W/p), p*p*C] in Cosmos3's (t, h, w) token order with (pi, pj, c) features."""
    C, T, H, W = latent.shape
    x = latent.reshape(C, T, H // p, p, W // p, p)
    return np.einsum("cthpwq->thwpqc", x).reshape(T, (H // p) * (W // p), p * p * C)


def _unpatchify(tokens: np.ndarray, p: int, H: int, W: int) -> np.ndarray:
    T, _, D = tokens.shape
    C = D // (p * p)
    x = tokens.reshape(T, H // p, W // p, p, p, C)
    return np.einsum("thwpqc->cthpwq", x).reshape(C, T, H, W)


def _run_both(model, cfg, params, video_noisy, action_noisy, context_frames, seed):
    """Same packed [text | video | actions] inputs through diffusers (one sample at a time) and through dit.apply
    (batched). Returns (ours video [B, C, F-K, H, W], ours actions, theirs video [B, C, F, H, W], theirs actions)."""
    import torch

    text_ids_fn, vae_ids_fn = _pipeline_position_fns()
    rng = np.random.default_rng(seed)
    B, p, C = 2, cfg.patch_size, cfg.channels
    strides = np.array([1, 2])
    latents = rng.standard_normal((B, C, F, LAT_H, LAT_W)).astype(np.float32)
    actions = rng.standard_normal((B, N_ACT, cfg.action_dim)).astype(np.float32)
    text = rng.integers(0, cfg.vocab_size, (B, L_TEXT))
    s_video = rng.uniform(0.05, 1.0, (B, F)).astype(np.float32)
    s_action = rng.uniform(0.05, 1.0, (B, N_ACT)).astype(np.float32)
    domain = 1
    rows, cols = LAT_H // p, LAT_W // p
    P = rows * cols

    theirs_v, theirs_a = [], []
    for b in range(B):
        fps = cfg.fps / strides[b]
        t_ids, nxt = text_ids_fn(L_TEXT, 0, use_float_positions=True)
        off = nxt + cfg.mrope_margin
        v_ids, _ = vae_ids_fn(F, rows, cols, off, True, fps=fps, base_fps=float(cfg.base_fps),
                              temporal_compression_factor=4)
        a_ids, _ = vae_ids_fn(N_ACT, 1, 1, off, True, fps=fps, base_fps=float(cfg.base_fps),
                              temporal_compression_factor=1, base_temporal_compression_factor=4, start_frame_offset=1)
        pos = torch.cat([t_ids, v_ids, a_ids], dim=1)
        n_vis = F * P
        N = L_TEXT + n_vis + N_ACT
        v_noisy = np.flatnonzero(video_noisy[b])
        a_noisy = np.flatnonzero(action_noisy[b])
        steps = lambda s: np.floor(s * np.float32(1000.0)).astype(np.float32)
        with torch.no_grad():
            out = model(
                input_ids=torch.as_tensor(text[b]), text_indexes=torch.arange(L_TEXT), position_ids=pos,
                und_len=L_TEXT, sequence_length=N,
                vision_tokens=[torch.as_tensor(latents[b:b + 1])], vision_token_shapes=[(F, rows, cols)],
                vision_sequence_indexes=torch.arange(L_TEXT, L_TEXT + n_vis),
                vision_mse_loss_indexes=torch.as_tensor(
                    [L_TEXT + f * P + j for f in v_noisy for j in range(P)], dtype=torch.long),
                vision_timesteps=torch.as_tensor(np.repeat(steps(s_video[b, v_noisy]), P)),
                vision_noisy_frame_indexes=[torch.as_tensor(v_noisy, dtype=torch.long)],
                action_tokens=[torch.as_tensor(actions[b])], action_token_shapes=[(N_ACT, 1, 1)],
                action_sequence_indexes=torch.arange(L_TEXT + n_vis, N),
                action_mse_loss_indexes=torch.as_tensor(L_TEXT + n_vis + a_noisy, dtype=torch.long),
                action_timesteps=torch.as_tensor(steps(s_action[b, a_noisy])),
                action_noisy_frame_indexes=[torch.as_tensor(a_noisy, dtype=torch.long)],
                action_domain_ids=[torch.tensor(domain)],
            )
        theirs_v.append(out.sample[0][0].numpy())
        theirs_a.append(out.action[0].numpy())

    video = np.stack([_patchify(latents[b], p) for b in range(B)])[:, None]  # [B, 1, F, P, Dp]
    inp = dit.Inputs(jnp.asarray(video), jnp.asarray(actions), jnp.asarray(np.where(video_noisy, s_video, 0))[:, None],
                     jnp.asarray(video_noisy)[:, None], jnp.asarray(np.where(action_noisy, s_action, 0)),
                     jnp.asarray(action_noisy), jnp.asarray(strides), text=jnp.asarray(text, jnp.int32))
    out_v, out_a = jax.jit(lambda prm, i: dit.apply(prm, cfg, i, (rows, cols), domain,
                                                     context_frames=context_frames))(params, inp)
    ours_v = np.stack([_unpatchify(np.asarray(out_v[b, 0]), p, LAT_H, LAT_W) for b in range(B)])
    return ours_v, np.asarray(out_a), np.stack(theirs_v), np.stack(theirs_a), (inp, (rows, cols), domain)


@pytest.mark.interop
@pytest.mark.parametrize("layout", ["forward_dynamics", "inverse_dynamics"])
def test_matches_diffusers_cosmos3(tiny_diffusers, layout):
    model, path = tiny_diffusers
    cfg, params = convert.load_diffusers(path, fps=30.0)
    B = 2
    if layout == "forward_dynamics":  # frame 0 clean context, later frames noisy, actions clean
        K = 1
        video_noisy = np.zeros((B, F), bool)
        video_noisy[:, K:] = True
        action_noisy = np.zeros((B, N_ACT), bool)
    else:  # every frame clean, actions noisy
        K = 1
        video_noisy = np.zeros((B, F), bool)
        action_noisy = np.ones((B, N_ACT), bool)
    ours_v, ours_a, theirs_v, theirs_a, _ = _run_both(model, cfg, params, video_noisy, action_noisy, K, seed=1)
    assert ours_v.shape == theirs_v[:, :, K:].shape and ours_a.shape == theirs_a.shape
    np.testing.assert_array_equal(theirs_v[:, :, :K], 0)
    err_v = np.abs(ours_v - theirs_v[:, :, K:]).max()
    err_a = np.abs(ours_a - theirs_a).max()
    print(f"{layout}: max abs error video {err_v:.2e} actions {err_a:.2e}; "
          f"scale video {np.abs(theirs_v).max():.2f} actions {np.abs(theirs_a).max():.2f}")
    if layout == "forward_dynamics":
        assert np.abs(theirs_v[:, :, K:]).max() > 0.1 and np.all(theirs_a == 0) and np.all(ours_a == 0)
    else:
        assert np.all(theirs_v == 0) and np.all(ours_v == 0) and np.abs(theirs_a).max() > 0.1
    assert err_v <= 1e-4 and err_a <= 1e-4


@pytest.mark.interop
def test_text_kv_cache_and_context_cache(tiny_diffusers):
    """Precomputed prompt keys/values (once per prompt) and a causal context cache give the same outputs."""
    _, path = tiny_diffusers
    cfg, params = convert.load_diffusers(path, fps=30.0, context_attention="causal")
    B, K = 2, 1
    rng = np.random.default_rng(3)
    rows, cols = LAT_H // 2, LAT_W // 2
    video = jnp.asarray(rng.standard_normal((B, 1, F, rows * cols, 16)), jnp.float32)
    actions = jnp.asarray(rng.standard_normal((B, N_ACT, 8)), jnp.float32)
    vn = jnp.zeros((B, 1, F), bool).at[:, :, K:].set(True)
    an = jnp.zeros((B, N_ACT), bool)
    inp = dit.Inputs(video, actions, jnp.where(vn, 0.6, 0.0), vn, jnp.zeros((B, N_ACT)), an, jnp.array([1, 2]),
                     text=jnp.asarray(rng.integers(0, 50, (B, L_TEXT)), jnp.int32))
    ref = dit.apply(params, cfg, inp, (rows, cols), context_frames=K)
    tkv = dit.encode_text(params, cfg, inp.text)
    out = dit.apply(params, cfg, inp._replace(text=None), (rows, cols), context_frames=K, text_kv=tkv)
    ckv = dit.encode_context(params, cfg, inp, (rows, cols), context_frames=K, text_kv=tkv)
    cached = dit.apply_cached(params, cfg, inp, (rows, cols), ckv, context_frames=K, text_kv=tkv)
    for a, b, c in zip(ref, out, cached):
        np.testing.assert_allclose(a, b, atol=1e-6)
        np.testing.assert_allclose(a, c, atol=1e-5)


@pytest.mark.interop
def test_diffusers_round_trip(tiny_diffusers, tmp_path):
    torch = pytest.importorskip("torch")
    from safetensors.numpy import load_file

    tc3 = pytest.importorskip("diffusers.models.transformers.transformer_cosmos3")
    model, path = tiny_diffusers
    cfg, params = convert.load_diffusers(path)
    out = convert.save_diffusers(cfg, params, str(tmp_path / "again"))
    a = load_file(os.path.join(path, convert.WEIGHTS_NAME))
    b = load_file(os.path.join(out, convert.WEIGHTS_NAME))
    assert set(a) == set(b)
    for k in a:
        assert a[k].dtype == b[k].dtype and np.array_equal(a[k], b[k]), k
    # diffusers' from_pretrained needs `accelerate` for this class (it keeps time_embedder in fp32)
    pytest.importorskip("accelerate", reason="Cosmos3OmniTransformer.from_pretrained needs accelerate")
    reloaded = tc3.Cosmos3OmniTransformer.from_pretrained(out)
    sd0, sd1 = model.state_dict(), reloaded.state_dict()
    assert set(sd0) == set(sd1)
    for k in sd0:
        assert torch.equal(sd0[k], sd1[k]), k
    for k, v in model.config.items():
        if not k.startswith("_"):
            assert reloaded.config[k] == v or list(reloaded.config[k]) == list(v), k


@pytest.mark.interop
def test_bfloat16_checkpoint(tiny_diffusers, tmp_path):
    """Published Cosmos3 checkpoints are bfloat16: read without torch, written back bit for bit."""
    torch = pytest.importorskip("torch")
    import ml_dtypes

    from sc3_jax.model.wan_vae_convert import read_safetensors

    model, _ = tiny_diffusers
    src = str(tmp_path / "bf16")
    copy.deepcopy(model).to(torch.bfloat16).save_pretrained(src, safe_serialization=True)  # fixture stays fp32
    cfg, params = convert.load_diffusers(src)
    assert all(x.dtype == jnp.float32 for x in jax.tree.leaves(params))
    w = model.layers[1].self_attn.norm_added_q.weight.detach()
    np.testing.assert_array_equal(params["layers"]["q_norm"][1], w.to(torch.bfloat16).float().numpy())
    out = convert.save_diffusers(cfg, params, str(tmp_path / "again"), dtype=ml_dtypes.bfloat16)
    a = read_safetensors(os.path.join(src, convert.WEIGHTS_NAME))
    b = read_safetensors(os.path.join(out, convert.WEIGHTS_NAME))
    assert set(a) == set(b)
    for k in a:
        assert a[k].dtype == b[k].dtype == ml_dtypes.bfloat16 and np.array_equal(a[k], b[k]), k


@pytest.mark.interop
def test_full_size_key_map_matches_diffusers_shapes():
    """At the default (Cosmos3-Nano-sized) config every diffusers key and shape is mapped (meta tensors only)."""
    torch = pytest.importorskip("torch")
    tc3 = pytest.importorskip("diffusers.models.transformers.transformer_cosmos3")
    with torch.device("meta"):
        model = tc3.Cosmos3OmniTransformer(action_gen=True, action_dim=7)
    theirs = {k: tuple(v.shape) for k, v in model.state_dict().items()}
    cfg = convert.config_from_diffusers(dict(model.config))
    ours = {k: e.torch_shape for k, e in convert.key_map(cfg).items()}
    assert ours == theirs
    shapes = jax.eval_shape(lambda: dit.init_params(cfg, convert.token_dim(cfg), jax.random.key(0)))
    assert dit.count_params(shapes) == sum(math.prod(s) for s in theirs.values())


@pytest.mark.interop
def test_sc3_convert_cli_round_trip(tiny_diffusers, tmp_path):
    """`sc3 convert --from diffusers` writes an orbax params checkpoint that training/rollouts read (the same
    params as the library import), `--from sc3` writes it back bit for bit, and an occupied --to is refused."""
    from sc3_jax.model import checkpoint
    from sc3_jax import cli
    from sc3_jax.core.config import config_from_dict
    from sc3_jax.model.wan_vae_convert import read_safetensors

    _, src = tiny_diffusers
    ours, back = tmp_path / "ours", tmp_path / "back"
    assert cli.main(["convert", "--from", "diffusers", src, "--to", str(ours)]) == 0
    cfg = config_from_dict(json.loads((ours / "config.json").read_text()))
    _, want = convert.load_diffusers(src)
    assert cfg.model == convert.config_from_diffusers(json.loads(open(os.path.join(src, "config.json")).read()))
    got = checkpoint.load_params(ours, cfg)
    for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(want)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert cli.main(["convert", "--from", "sc3", str(ours), "--to", str(back)]) == 0
    a = read_safetensors(os.path.join(src, convert.WEIGHTS_NAME))
    b = read_safetensors(os.path.join(back, convert.WEIGHTS_NAME))
    assert set(a) == set(b) and all(np.array_equal(a[k], b[k]) for k in a)
    assert cli.main(["convert", "--from", "sc3", str(ours), "--to", str(back)]) == 2  # not overwritten
    assert sorted(p.name for p in back.iterdir()) == sorted([convert.CONFIG_NAME, convert.WEIGHTS_NAME])


def _tiny_wan_tokenizer():
    from sc3_jax.model import wan_tokenizer as wt
    from sc3_jax.model import wan_vae_convert as wc
    rng = np.random.default_rng(0)
    vae = wc.config_from_diffusers({"base_dim": 4, "z_dim": 4, "dim_mult": [1, 1, 1, 1], "num_res_blocks": 1,
                                    "attn_scales": [], "temperal_downsample": [False, True, True],
                                    "latents_mean": rng.normal(size=4).tolist(),
                                    "latents_std": rng.uniform(0.5, 2.0, size=4).tolist()})
    return wt.WanTokenizer.random(vae, seed=0, patch_size=2)


@pytest.mark.slow  # 25-55 s: kept out of the default run's 15 minutes (CI runs -m slow too)
def test_training_drives_the_cosmos3_layout_on_time_compressed_latents(monkeypatch):
    """A Cosmos3-layout model trains on Wan-VAE tokens: 5 context + 8 future frames are 2 + 2 token frames with 8
    actions (4 per token frame), the train step fits one batch, and impossible bookkeeping is refused."""
    from sc3_jax.train import train
    from sc3_jax.core.config import Config, DataConfig, FlowConfig, TrainConfig, replace
    from sc3_jax.model import tokenizer

    tok = _tiny_wan_tokenizer()
    monkeypatch.setattr(train, "make_tokenizer", lambda m: tok)
    monkeypatch.setattr(tokenizer, "make_tokenizer", lambda m: tok)  # the token geometry's
    model = _tiny_cfg(text_pathway=False, tokenizer="wan2.1", action_dim=7, num_views=3)
    cfg = Config(model=model, data=DataConfig(image_size=(16, 32), context_frames=5, future_frames=8, batch_size=2),
                 flow=FlowConfig(t_logit_mean=0.0), train=TrainConfig(lr=3e-3, warmup_steps=1, steps=40))
    assert tokenizer.context_token_frames(cfg) == 2
    rng = np.random.default_rng(0)
    batch = {"frames": rng.integers(0, 256, (2, 3, 13, 16, 32, 3)).astype(np.uint8),
             "actions": rng.normal(size=(2, 8, 7)).astype(np.float32), "stride": np.ones(2, np.int32)}
    step = jax.jit(train.make_train_step(cfg))
    state = train.init_state(cfg)
    losses = []
    for _ in range(40):
        state, m = step(state, batch)
        losses.append(float(m["loss"]))
    assert np.all(np.isfinite(losses)) and np.mean(losses[-5:]) < 0.7 * np.mean(losses[:5]), losses
    with pytest.raises(ValueError, match="context_frames = 1 \\+ 4 k"):
        tokenizer.context_token_frames(replace(cfg, data=dict(context_frames=4)))
    with pytest.raises(ValueError, match="need model.layout='cosmos3'"):
        tokenizer.context_token_frames(replace(cfg, model=dict(layout="sc3")))
    with pytest.raises(NotImplementedError, match="model.prompt_ids"):
        train.make_train_step(replace(cfg, model=dict(text_pathway=True)))
    # a text_pathway model (a converted Cosmos3 checkpoint) trains on one fixed prompt: exactly the embedding rows
    # of its tokens learn (embeddings are not weight-decayed, Adam moves nothing with zero gradient)
    tcfg = replace(cfg, model=dict(text_pathway=True, prompt_ids=(3, 1, 4)))
    tstate = train.init_state(tcfg)
    emb0 = np.asarray(tstate["params"]["embed_tokens"])
    tstep = jax.jit(train.make_train_step(tcfg))
    for _ in range(2):
        tstate, m = tstep(tstate, batch)
    assert np.isfinite(float(m["loss"]))
    moved = np.abs(np.asarray(tstate["params"]["embed_tokens"]) - emb0).max(-1) > 0
    assert sorted(np.flatnonzero(moved)) == [1, 3, 4]
    np.testing.assert_array_equal(tstate["params"]["lm_head"], train.init_state(tcfg)["params"]["lm_head"])
    with pytest.raises(ValueError, match="prompt_ids must lie in"):
        replace(tcfg, model=dict(prompt_ids=(10 ** 9,)))


@pytest.mark.slow  # 80 s: the default run stays under 15 min on 2 cores; CI runs it
def test_rollout_on_time_compressed_latents(monkeypatch):
    """Algorithm 1 with a 4x time-compressing VAE: the context is kept as frames and tokenised every chunk, the
    model predicts t = 2 token frames (8 frames) from k = 2 (5 frames), the *decoded* frames 5..8 are kept. Chunk 0
    equals a hand-written reference; closed loop runs every chunk; bad windows are refused."""
    from sc3_jax.model import flow, modes
    from sc3_jax.rollout import rollout
    from sc3_jax.core.config import Config, DataConfig, RolloutConfig, SampleConfig, replace
    from sc3_jax.data.norm_stats import NormStats
    from sc3_jax.model.tokenizer import to_uint8
    from sc3_jax.policies import simple
    from sc3_jax.policies.base import as_host

    tok = _tiny_wan_tokenizer()
    monkeypatch.setattr(rollout, "make_tokenizer", lambda m: tok)
    model = _tiny_cfg(text_pathway=False, tokenizer="wan2.1", action_dim=7, num_views=3)
    B, N, K, T, l, size = 2, 2, 5, 8, 4, (16, 32)
    cfg = Config(model=model, data=DataConfig(image_size=size, context_frames=K, future_frames=T),
                 rollout=RolloutConfig(policy_chunk=T, keep_frames=l), sample=SampleConfig(steps=2))
    stats = NormStats(np.full(7, 0.001, np.float32), np.full(7, 0.01, np.float32))
    ro = rollout.Rollout(cfg, stats, data_fps=20.0, num_chunks=N)
    assert ro.chunk_fns.window == (2, 2)
    params = dit.init_params(model, tok.token_dim, jax.random.key(0), tok.grid(size))
    params = jax.tree.map(lambda x: x + 0.05 * jax.random.normal(jax.random.key(1), x.shape), params)
    rng = np.random.default_rng(0)
    ics = rollout.InitialConditions(rng.integers(0, 256, (B, 3, K) + size + (3,), dtype=np.uint8),
                                    np.zeros((B, 7), np.float32), np.zeros(B, np.int32))
    keys = rollout.episode_keys(0, B)
    policy = simple.linear_policy(jax.random.key(7), 3, chunk=T)
    # closed loop (the host loop; its parity with the scan is tests/test_rollout.py's): every chunk runs
    ref = ro.run_host(params, as_host(policy), ics, keys, tau=np.inf)
    assert ref["frames"].shape == (B, 3, N * l) + size + (3,) and np.all(np.isfinite(ref["u"]))
    assert not np.array_equal(ref["frames"][:, :, :l], ref["frames"][:, :, l:])

    # chunk 0 by hand (offline replay, so the actions are known): encode 5 frames -> 2 token frames, sample 2
    # more, decode all 4 token frames -> 13 frames, keep frames 5..8
    actions = rng.normal(0.001, 0.01, (B, N, T, 7)).astype(np.float32)
    off = ro.run_offline(params, ics, actions, keys)

    @jax.jit
    def by_hand(frames, a, key_data):
        _, k_fd, _ = ro.chunk_fns.keys(key_data, 0)
        ctx = tok.encode(frames)[None]
        video = jnp.concatenate([ctx, jnp.zeros_like(ctx)], axis=2)
        vn, an = modes.fixed(modes.FD, 1, 3, 2, 2, num_actions=T)
        video, _ = flow.sample(params, model, video, a[None], jnp.full((1,), 2), vn, an, k_fd, 2, tok.grid(size),
                               fcfg=cfg.flow, context_frames=2)
        return to_uint8(tok.decode(video[0], size))[:, K:K + l]

    for b in range(B):
        want = np.asarray(by_hand(ics.frames[b], stats.normalize(actions[b, 0]), keys[b]))
        d = np.abs(off["frames"][b, :, :l].astype(int) - want.astype(int))
        assert d.max() <= 1 and np.mean(d > 0) < 0.05, (d.max(), np.mean(d > 0))  # eager vs jit float rounding
    with pytest.raises(ValueError, match="context_frames = 1 \\+ 4 k"):
        rollout.Rollout(replace(cfg, data=dict(context_frames=4)), stats, data_fps=20.0, num_chunks=N)

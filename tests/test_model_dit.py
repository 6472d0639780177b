"""DiT: shapes, block-causal masking, KV-context streaming hook, cross-view locality, presets."""

from dataclasses import replace

import pytest
import torch

from tests.model_fixtures import perturbed, tiny_conditions
from world_model.model import MultiViewDiT, get_preset
from world_model.model.attention import block_causal_mask
from world_model.model.config import PRESETS, ModelConfig
from world_model.sensors import DEFAULT_CAMERA_NAMES


def _model(cfg, seed=0):
    torch.manual_seed(seed)
    return perturbed(MultiViewDiT(cfg), seed)


def test_presets_derive_token_counts():
    for name in PRESETS:
        cfg = get_preset(name)
        h, w = cfg.latent_hw
        assert (h, w) == (cfg.sensors.height // cfg.vae.downsample, cfg.sensors.width // cfg.vae.downsample)
        assert cfg.tokens_per_frame == (h // cfg.dit.patch) * (w // cfg.dit.patch)
        assert ModelConfig.from_dict(cfg.to_dict()) == cfg
    d = get_preset("default")
    assert d.latent_hw == (8, 14) and d.sensors.num_views == 7 and d.cross_view_blocks == (4, 9)
    with pytest.raises(ValueError, match="unknown preset"):
        get_preset("huge")
    with pytest.raises(ValueError, match="divisible"):
        replace(d, dit=replace(d.dit, patch=3))


def test_forward_shapes_extra_channels_and_errors():
    cfg = get_preset("tiny")
    cfg = replace(cfg, dit=replace(cfg.dit, in_channels_extra=3))
    model = _model(cfg)
    cond = tiny_conditions(cfg, 2, batch=2)
    t_, v, c, h, w = cfg.latent_shape(2)
    out = model(torch.randn(2, t_, v, c + 3, h, w), torch.rand(2, 2), cond)
    assert out.shape == (2, t_, v, c, h, w) and out.dtype == torch.float32
    with pytest.raises(ValueError, match="x must be"):
        model(torch.randn(2, t_, v, c, h, w), torch.rand(2), cond)


def test_block_causal_mask_layout():
    m = block_causal_mask(frames=4, tokens_per_frame=2, chunk_frames=2, context_frames=1)
    assert m.shape == (8, 10)
    assert m[:, :2].all()  # context always visible
    assert m[0, 2:6].all() and not m[0, 6:].any()  # chunk 0 sees itself, not chunk 1
    assert m[7, 2:].all()


def test_block_causal_outputs_ignore_later_frames():
    cfg = get_preset("tiny")  # chunk_frames = 1
    model = _model(cfg)
    cond = tiny_conditions(cfg, 4)
    x = torch.randn(1, *cfg.latent_shape(4))
    t = torch.rand(1, 4)
    later = x.clone()
    later[:, 2:] = torch.randn_like(later[:, 2:])
    a, b = model(x, t, cond, causal=True), model(later, t, cond, causal=True)
    assert torch.allclose(a[:, :2], b[:, :2], atol=1e-5)
    assert not torch.allclose(a[:, 2:], b[:, 2:], atol=1e-3)
    # Bidirectional attention does look ahead (so the check above can fail).
    assert not torch.allclose(model(x, t, cond)[:, :2], model(later, t, cond)[:, :2], atol=1e-4)
    # Later frames' controls and timesteps do not reach earlier frames either.
    moved = cond.apply(lambda _name, v: v.clone())
    moved.ego[:, 2:] += 1.0
    moved.obj_corners[:, 2:] += 5.0
    noisier = t.clone()
    noisier[:, 2:] = 0.9
    for c, tt in ((moved, t), (cond, noisier)):
        out = model(x, tt, c, causal=True)
        assert torch.allclose(out[:, :2], a[:, :2], atol=1e-5)
        assert not torch.allclose(out[:, 2:], a[:, 2:], atol=1e-3)


def test_kv_context_streaming_matches_full_causal_forward():
    cfg = get_preset("tiny")
    model = _model(cfg)
    cond = tiny_conditions(cfg, 3)
    x = torch.randn(1, *cfg.latent_shape(3))
    t = torch.rand(1, 3)
    full = model(x, t, cond, causal=True)
    _, kv = model(x[:, :2], t[:, :2], cond.frames(0, 2), causal=True, return_kv=True)
    last = model(x[:, 2:], t[:, 2:], cond.frames(2, 3), causal=True, frame_offset=2, kv_context=kv)
    assert torch.allclose(last, full[:, 2:], atol=1e-5)


def test_context_only_frames_skip_outputs_but_not_keys_and_values():
    cfg = get_preset("tiny")
    model = _model(cfg)
    cond = tiny_conditions(cfg, 3, batch=2)
    x, t = torch.randn(2, *cfg.latent_shape(3)), torch.rand(2, 3)
    _, ctx = model(x[:, :2], t[:, :2], cond.frames(0, 2), return_kv=True)
    valid = torch.tensor([[True, True], [False, True]])
    kw = {"frame_offset": 2, "kv_context": ctx, "context_valid": valid, "return_kv": True}
    with torch.no_grad():
        full, full_kv = model(x, t, cond, **kw)
        for first in (1, 2, 3):  # a refreshed frame in front; all but one; a pure K/V pass
            part, part_kv = model(x, t, cond, context_only_frames=first, **kw)
            assert part.shape == (2, 3 - first, *full.shape[2:])
            assert torch.allclose(part, full[:, first:], atol=1e-5)
            for (k, v), (fk, fv) in zip(part_kv, full_kv, strict=True):
                assert torch.equal(k, fk) and torch.equal(v, fv)
    with pytest.raises(ValueError, match="context_only_frames"):
        model(x, t, cond, context_only_frames=4)


def test_cross_view_attention_only_mixes_overlapping_views():
    cfg = get_preset("tiny")  # 2 blocks, cross-view in block 2 only
    model = _model(cfg)
    cond = tiny_conditions(cfg, 1)
    names = list(DEFAULT_CAMERA_NAMES)
    front, front_left, back = names.index("FRONT"), names.index("FRONT_LEFT"), names.index("BACK")
    x = torch.randn(1, *cfg.latent_shape(1))
    t = torch.tensor([0.5])
    base = model(x, t, cond)
    x_back = x.clone()
    x_back[:, :, back] += 1.0
    assert torch.allclose(model(x_back, t, cond)[:, :, front], base[:, :, front], atol=1e-5)
    x_left = x.clone()
    x_left[:, :, front_left] += 1.0
    assert not torch.allclose(model(x_left, t, cond)[:, :, front], base[:, :, front], atol=1e-4)


def test_lora_friendly_layer_names():
    names = {n.split(".")[-1] for n, _ in MultiViewDiT(get_preset("tiny")).named_modules()}
    assert {"q", "k", "v", "o", "fc1", "fc2"} <= names


def test_deterministic_given_seed():
    cfg = get_preset("tiny")
    a, b = _model(cfg, 3), _model(cfg, 3)
    cond = tiny_conditions(cfg, 2)
    x = torch.randn(1, *cfg.latent_shape(2), generator=torch.Generator().manual_seed(1))
    assert torch.equal(a(x, torch.tensor([0.3]), cond), b(x, torch.tensor([0.3]), cond))


def test_analytic_flops_match_torch_flop_counter():
    from torch.utils.flop_counter import FlopCounterMode

    from world_model.model.flops import dit_forward_flops

    cfg = get_preset("tiny")
    model = MultiViewDiT(cfg).eval()
    cond = tiny_conditions(cfg, 2, batch=2)
    tokens = model.tokenize(cond)
    x, t = torch.randn(2, *cfg.latent_shape(2)), torch.rand(2)
    # On CPU attention is two matmuls per call, so torch counts it too: they must agree exactly.
    with torch.no_grad(), FlopCounterMode(display=False) as counter:
        model(x, t, cond)  # tokenizes inside (its small MLPs are not counted: subtract them)
    with torch.no_grad(), FlopCounterMode(display=False) as tokenizer:
        model.tokenizer(cond)
    full = dit_forward_flops(cfg, batch=2, frames=2)["total"]
    assert counter.get_total_flops() - tokenizer.get_total_flops() == full
    with torch.no_grad(), FlopCounterMode(display=False) as counter:
        model(x, t, tokens)  # tokens from tokenize() carry the cross-attention keys/values
    assert counter.get_total_flops() == dit_forward_flops(cfg, batch=2, frames=2, cross_kv=False)["total"] < full


def test_tokenized_controls_give_the_same_velocity_as_conditions():
    cfg = get_preset("tiny")
    model = MultiViewDiT(cfg).eval()
    for p in model.parameters():  # adaLN-zero starts at zero output: make every path count
        p.data.normal_(0, 0.05, generator=torch.Generator().manual_seed(p.numel()))
    cond = tiny_conditions(cfg, 2, batch=2)
    x, t = torch.randn(2, *cfg.latent_shape(2)), torch.rand(2)
    tokens = model.tokenize(cond)
    assert tokens.cross_kv is not None and len(tokens.cross_kv) == cfg.dit.depth
    with torch.no_grad():
        assert torch.allclose(model(x, t, cond), model(x, t, tokens), atol=1e-6)


def test_control_tokens_of_some_frames_equal_tokenizing_those_frames():
    cfg = get_preset("tiny")
    model = _model(cfg).eval()
    cond = tiny_conditions(cfg, 3, batch=2)
    with torch.no_grad():
        sliced, direct = model.tokenize(cond).frames(1, 3), model.tokenize(cond.frames(1, 3))
    for name in ("text", "text_mask", "sensor", "frame", "frame_mask", "view_adjacency"):
        assert torch.allclose(getattr(sliced, name).float(), getattr(direct, name).float(), atol=1e-6), name
    for (t1, c1), (t2, c2) in zip(sliced.cross_kv, direct.cross_kv, strict=True):
        for a, b in zip((*t1, *c1), (*t2, *c2), strict=True):
            assert a.shape == b.shape and torch.allclose(a, b, atol=1e-6)


def test_cpu_attention_matches_sdpa_and_survives_fully_masked_rows():
    import torch.nn.functional as F

    from world_model.model.attention import attention

    g = torch.Generator().manual_seed(0)
    q, k, v = (torch.randn(3, 2, 5, 8, generator=g) for _ in range(3))
    mask = torch.rand(3, 1, 5, 5, generator=g) > 0.4
    mask[..., 0] = True
    want = F.scaled_dot_product_attention(q, k, v, attn_mask=mask)
    assert torch.allclose(attention(q, k, v, mask), want, atol=1e-6)
    assert torch.allclose(attention(q, k, v), F.scaled_dot_product_attention(q, k, v), atol=1e-6)
    mask[0, 0, 2] = False  # a query that may attend to nothing: the mean of the values, not NaN
    out = attention(q, k, v, mask)
    assert torch.isfinite(out).all() and torch.allclose(out[0, :, 2], v[0].mean(dim=1), atol=1e-6)


def test_attention_layers_with_folded_norm_weights_equal_the_textbook_formulas():
    """QK-norm weights and the softmax scale are folded into the rotary tables / cross keys: the
    layers must still compute rms_norm(x W) * w -> RoPE -> softmax(q k^T / sqrt(d)) v."""
    import torch.nn.functional as F

    from world_model.model.attention import CrossAttention, SelfAttention
    from world_model.model.rope import apply_rope, rope_tables, rotation_tables

    torch.manual_seed(0)
    dim, heads, eps, hd = 32, 2, 1e-6, 16
    attn, cross = SelfAttention(dim, heads, eps), CrossAttention(dim, 24, heads, eps)
    for norm in (attn.q_norm, attn.k_norm, cross.q_norm, cross.k_norm):
        torch.nn.init.uniform_(norm.weight, 0.5, 2.0)  # not the identity they start as
    x, ctx = torch.randn(3, 2 * 6, dim), torch.randn(3, 5, 24)
    cos, sin = rotation_tables(*rope_tables(hd, 2, 2, 3), torch.float32)

    def heads_of(y, norm):
        y = F.rms_norm(y.unflatten(-1, (heads, hd)), (hd,), norm.weight, eps)
        return y.transpose(1, 2)

    def textbook(q, k, v, layer, mask=None):
        return layer.o(F.scaled_dot_product_attention(q, k, v, attn_mask=mask).transpose(1, 2).flatten(-2))

    q = apply_rope(heads_of(attn.q(x), attn.q_norm), cos, sin)
    k = apply_rope(heads_of(attn.k(x), attn.k_norm), cos, sin)
    v = attn.v(x).unflatten(-1, (heads, hd)).transpose(1, 2)
    out, (k_out, _) = attn(x, cos, sin)
    assert torch.allclose(out, textbook(q, k, v, attn), atol=1e-5)
    assert torch.allclose(k_out, k, atol=1e-5)  # the cached keys are the plain rotated ones
    out_late, _ = attn(x, cos, sin, queries_from=6)  # only the last frame's queries
    assert torch.allclose(out_late, textbook(q[:, :, 6:], k, v, attn), atol=1e-5)

    q = heads_of(cross.q(x), cross.q_norm)
    k = heads_of(cross.k(ctx), cross.k_norm)
    v = cross.v(ctx).unflatten(-1, (heads, hd)).transpose(1, 2)
    mask = torch.rand(3, 1, 12, 5) > 0.3
    mask[..., 0] = True
    assert torch.allclose(cross(x, ctx, mask), textbook(q, k, v, cross, mask), atol=1e-5)


@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
def test_additive_mask_bias_equals_boolean_mask(dtype):
    from world_model.model.attention import attention, mask_bias

    g = torch.Generator().manual_seed(1)
    q, k, v = (torch.randn(3, 2, 5, 8, generator=g).to(dtype) for _ in range(3))
    mask = torch.rand(3, 1, 5, 5, generator=g) > 0.4
    mask[0, 0, 2] = False  # fully masked row: still the mean of the values
    bias = mask_bias(mask, dtype)
    assert bias.dtype == dtype and bool((bias[mask] == 0).all()) and bool((bias[~mask] == torch.finfo(dtype).min).all())
    out = attention(q, k, v, bias)
    assert torch.isfinite(out).all()
    assert torch.equal(out, attention(q, k, v, mask))
    assert mask_bias(None, dtype) is None


@pytest.mark.slow
def test_compiled_blocks_match_eager_with_lora_adapters_swapped_in_and_out(tmp_path):
    from world_model.lora import (
        LoraConfig,
        add_adapter,
        apply_adapters,
        base_fingerprint,
        remove_adapters,
        save_adapter,
    )

    cfg = get_preset("tiny")
    torch.manual_seed(0)
    model = MultiViewDiT(cfg).eval()
    for p in model.parameters():  # adaLN-zero starts at zero output: perturb so every path counts
        torch.nn.init.normal_(p, std=0.05)
    cond = tiny_conditions(cfg, 2, batch=2)
    x, t = torch.randn(2, *cfg.latent_shape(2)), torch.rand(2)
    lora = LoraConfig(rank=2)
    with torch.no_grad():
        eager = model(x, t, cond)
        base = base_fingerprint(model)
        for p in add_adapter(model, "bump", lora):
            torch.nn.init.normal_(p, std=0.1)
        eager_adapted = model(x, t, cond)
        save_adapter(model, "bump", tmp_path / "bump", lora, base)
        remove_adapters(model)
        model.requires_grad_(False)
        model.compile_blocks()
        assert torch.allclose(model(x, t, cond), eager, atol=1e-4, rtol=1e-4)
        # An adapter loaded after compiling is seen (its layers recompile), and removing it
        # restores the base model's kernels.
        apply_adapters(model, [tmp_path / "bump"])
        adapted = model(x, t, cond)
        assert not torch.allclose(eager_adapted, eager, atol=1e-3)
        assert torch.allclose(adapted, eager_adapted, atol=1e-4, rtol=1e-4)
        remove_adapters(model)
        assert torch.allclose(model(x, t, cond), eager, atol=1e-4, rtol=1e-4)

"""Streaming engine: cached streaming == full recompute, context refresh, causality, restarts, memory."""

import dataclasses
import gc
import json

import pytest
import torch

from world_model.model import MultiViewDiT, get_preset
from world_model.model.config import with_layout
from world_model.model.flow import predict_x0
from world_model.streaming import REFRESH_EVERY_STEP
from world_model.student import StreamingEngine, StudentConfig, few_step_sample, rollout_blocks
from world_model.student.config import TRAINING_STREAMING

from .model_fixtures import perturbed, tiny_conditions

TOL = 1e-4


def streaming(renoise: str = "fresh", **changes) -> StudentConfig:
    """A student config streaming as the training rollouts do, with ``changes`` to it."""
    return StudentConfig(streaming=dataclasses.replace(TRAINING_STREAMING, **changes), renoise=renoise)


def _model(chunk: int, window: int, seed: int = 0, layout: bool = False) -> MultiViewDiT:
    cfg = with_layout(get_preset("tiny"), layout)
    cfg = dataclasses.replace(cfg, clip=dataclasses.replace(cfg.clip, chunk_frames=chunk, context_frames=window))
    torch.manual_seed(seed)
    return perturbed(MultiViewDiT(cfg), seed=seed)


def _reference_rollout(model, scfg, first, cond, noises):
    """The same rollout from the model's full-sequence definition: every chunk recomputes all
    history from scratch (one block-causal forward), no cache object. Denoising steps are counted
    here (the engine reads them from t) to pick where the refresh steps refresh."""
    c, f0, n = model.cfg.clip.chunk_frames, first.shape[1], model.cfg.tokens_per_frame
    steps = scfg.streaming.resolved_refresh_steps()
    hist, outs = first, []
    for k, noise in enumerate(noises):
        f = hist.shape[1]
        ccond = cond.frames(0, f + c)
        blocks = rollout_blocks(0, f + c, f0, c)
        step = iter(range(scfg.num_steps))

        def x0_fn(x, t, hist=hist, f=f, ccond=ccond, blocks=blocks, step=step):
            if next(step) not in steps:
                tt = torch.cat([torch.ones(x.shape[0], f), t[:, None].expand(-1, c)], dim=1)
                v = model(torch.cat([hist, x], 1), tt, ccond, causal=True, blocks=blocks)[:, f:]
                return predict_x0(x, v, t)
            ones = torch.ones(x.shape[0], f)
            _, kv = model(hist, ones, ccond.frames(0, f), causal=True, blocks=blocks[:f], return_kv=True)
            kv = [(a[:, :, : (f - 1) * n], b[:, :, : (f - 1) * n]) for a, b in kv]
            tt = torch.cat([ones[:, :1], t[:, None].expand(-1, c)], dim=1)
            x_in = torch.cat([hist[:, -1:], x], 1)
            v = model(x_in, tt, ccond.frames(f - 1, f + c), frame_offset=f - 1, kv_context=kv)[:, 1:]
            return predict_x0(x, v, t)

        with torch.no_grad():
            out = few_step_sample(x0_fn, noise, scfg.times(), "ddim")
        outs.append(out)
        hist = torch.cat([hist, out], 1)
        del k
    return torch.cat(outs, 1)


@pytest.mark.parametrize("refresh", [False, True, (0,), (1, 3)])  # (steps): refresh_steps
@pytest.mark.parametrize("chunk", [1, 2])
@pytest.mark.parametrize("layout", [False, True])  # pixel-aligned layout: each frame's enters with it
def test_cached_streaming_equals_full_recompute(refresh, chunk, layout):
    chunks, f0 = 3, 1
    model = _model(chunk, window=f0 + chunks * chunk, layout=layout)  # window holds everything: nothing evicted
    steps = refresh if isinstance(refresh, tuple) else REFRESH_EVERY_STEP
    scfg = streaming(context_refresh=bool(refresh), refresh_steps=steps, renoise="ddim")
    total = f0 + chunks * chunk
    cond = tiny_conditions(model.cfg, total, batch=2)
    gen = torch.Generator().manual_seed(1)
    first = torch.randn(2, *model.cfg.latent_shape(f0), generator=gen)
    noises = [torch.randn(2, *model.cfg.latent_shape(chunk), generator=gen) for _ in range(chunks)]

    engine = StreamingEngine(model, scfg)
    with torch.no_grad():
        engine.start(first, cond.frames(0, f0))
        got = torch.cat(
            [engine.step(cond.frames(f0 + k * chunk, f0 + (k + 1) * chunk), noises[k]) for k in range(chunks)], 1
        )
    want = _reference_rollout(model, scfg, first, cond, noises)
    assert (got - want).abs().max().item() <= TOL
    assert got.abs().mean() > 0.1  # a real signal, not zeros


def test_context_refresh_recomputes_the_last_frame_keys():
    model = _model(chunk=2, window=4)
    cond = tiny_conditions(model.cfg, 5, batch=1)
    gen = torch.Generator().manual_seed(2)
    first = torch.randn(1, *model.cfg.latent_shape(1), generator=gen)
    noise = [torch.randn(1, *model.cfg.latent_shape(2), generator=gen) for _ in range(2)]
    outs = {}
    for refresh in (False, True):
        eng = StreamingEngine(model, streaming(context_refresh=refresh, renoise="ddim"))
        with torch.no_grad():
            eng.start(first, cond.frames(0, 1))
            eng.step(cond.frames(1, 3), noise[0])
            if refresh:
                # The refreshed K/V of the previous chunk's last frame, computed with the new noisy chunk.
                n = model.cfg.tokens_per_frame
                ctx, valid = eng.cache.context(exclude_newest=True)
                cached, _ = eng.cache.context()
                x_in = torch.cat([eng.last, noise[1]], 1)
                t = torch.tensor([[1.0, 0.0, 0.0]])
                _, kv = model(x_in, t, cond.frames(2, 5), frame_offset=eng.position - 1, kv_context=ctx, return_kv=True)
                # Block 0 keys see no attention yet; the last block's keys carry the chunk noise.
                refreshed_k, cached_k = kv[-1][0][:, :, :n], cached[-1][0][:, :, -n:]
                assert refreshed_k.shape == cached_k.shape
                assert (refreshed_k - cached_k).abs().max() > 1e-3
            outs[refresh] = eng.step(cond.frames(3, 5), noise[1])
    assert (outs[True] - outs[False]).abs().max() > 1e-3


def test_causality_later_inputs_do_not_reach_earlier_chunks():
    model = _model(chunk=2, window=8)
    f = 7  # prefix 1 + three chunks of 2
    cond = tiny_conditions(model.cfg, f)
    x = torch.randn(1, *model.cfg.latent_shape(f), requires_grad=True)
    blocks = rollout_blocks(0, f, 1, 2)
    out = model(x, torch.full((1, f), 0.5), cond, causal=True, blocks=blocks)
    out[:, 1:3].sum().backward()  # chunk 1 (frames 1, 2)
    g = x.grad.abs().flatten(2).sum(-1)[0]
    assert torch.all(g[3:] == 0)  # later chunks: exactly no influence
    assert torch.all(g[:3] > 0)  # the prefix and the chunk itself do matter


def test_restarted_row_equals_a_fresh_rollout():
    model = _model(chunk=1, window=3)
    scfg = streaming(renoise="ddim", sink_frames=1)
    gen = torch.Generator().manual_seed(3)
    cond = tiny_conditions(model.cfg, 8, batch=2)
    first = torch.randn(2, *model.cfg.latent_shape(1), generator=gen)
    noise = [torch.randn(2, *model.cfg.latent_shape(1), generator=gen) for _ in range(7)]
    new_first = torch.randn(1, *model.cfg.latent_shape(1), generator=gen)
    row1 = cond.apply(lambda _, v: v[1:2])

    eng = StreamingEngine(model, scfg)
    fresh = StreamingEngine(model, scfg)
    with torch.no_grad():
        eng.start(first, cond.frames(0, 1))
        for k in range(4):
            eng.step(cond.frames(k + 1, k + 2), noise[k])
        before0 = eng.cache.layers[0][0][:7].clone()
        eng.start_rows([1], new_first, row1.frames(0, 1))
        assert torch.equal(eng.cache.layers[0][0][:7], before0)  # row 0 untouched
        fresh.start(new_first, row1.frames(0, 1))
        for j in range(3):
            both = eng.step(cond.frames(j + 1, j + 2), noise[4 + j])
            alone = fresh.step(row1.frames(j + 1, j + 2), noise[4 + j][1:2])
            assert (both[1:2] - alone).abs().max().item() <= TOL
    with pytest.raises(ValueError, match="rows must be in"):
        eng.start_rows([5], new_first, row1.frames(0, 1))


def _rss_mb() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return 0.0


def _live_tensor_mb() -> float:
    """Bytes of the distinct storages of every live tensor (deterministic, unlike RSS)."""
    gc.collect()
    storages = {}
    for obj in gc.get_objects():
        # exact types: fake/functional tensor subclasses left by compile tests have no storage
        if type(obj) in (torch.Tensor, torch.nn.Parameter) and obj.device.type == "cpu":
            st = obj.untyped_storage()
            storages[st.data_ptr()] = st.nbytes()
    return sum(storages.values()) / 2**20


def test_kv_cache_memory_is_bounded_over_600_frames():
    model = _model(chunk=10, window=10)  # long chunks: 60 engine steps cover 600 frames
    scfg = streaming(sink_frames=1)
    chunk, frames = model.cfg.clip.chunk_frames, 600
    cond = tiny_conditions(model.cfg, chunk + 1)
    eng = StreamingEngine(model, scfg, torch.Generator().manual_seed(0))
    shapes, rss, live = [], {}, {}
    with torch.no_grad():
        eng.start(torch.zeros(1, *model.cfg.latent_shape(1)), cond.frames(0, 1))
        while eng.position < frames:
            eng.step(cond.frames(1, 1 + chunk))
            shapes.append([tuple(k.shape) for k, _ in eng.cache.layers])
            for mark in (100, frames):
                if eng.position >= mark and mark not in rss:
                    rss[mark], live[mark] = _rss_mb(), _live_tensor_mb()
    assert all(s == shapes[0] for s in shapes)
    assert eng.cache.nbytes() == sum(k.nbytes + v.nbytes for k, v in eng.cache.layers)
    # A leak of one frame's K/V per chunk (50 chunks from frame 100 to 600) would exceed this:
    frame_kv_mb = eng.cache.nbytes() / eng.cache.layers[0][0].shape[2] * model.cfg.tokens_per_frame / 2**20
    assert live[frames] - live[100] < 10 * frame_kv_mb
    assert rss[frames] - rss[100] < 64.0  # MB; RSS also moves with the allocator, so only gross growth


def test_few_step_schedule_maps_the_step_list_to_flow_times():
    assert torch.allclose(StudentConfig().times(), torch.tensor([0.0, 0.25, 0.5, 0.75]))
    shifted = StudentConfig(timestep_shift=5.0).times()  # Wan's shift: 1 - 5s / (1 + 4s), s = step / 1000
    assert torch.allclose(shifted, torch.tensor([0.0, 1 - 3.75 / 4.0, 1 - 2.5 / 3.0, 1 - 1.25 / 2.0]))


def test_bad_input_is_rejected():
    model = _model(chunk=1, window=2)
    eng = StreamingEngine(model)
    cond = tiny_conditions(model.cfg, 2)
    with pytest.raises(RuntimeError, match="start"):
        eng.step(cond.frames(0, 1))
    with pytest.raises(ValueError, match="exceed the window"):
        eng.start(torch.zeros(1, *model.cfg.latent_shape(3)), tiny_conditions(model.cfg, 3))
    eng.start(torch.zeros(1, *model.cfg.latent_shape(1)), cond.frames(0, 1))
    with pytest.raises(ValueError, match="one chunk"):
        eng.step(cond)
    with pytest.raises(ValueError, match="streaming must be a StreamingConfig"):
        StudentConfig(streaming={"denoising_steps": 4})


def test_student_config_round_trips_its_streaming_and_reads_the_flat_form():
    scfg = streaming(refresh_steps=(2, 3), sink_frames=1)
    saved = json.loads(json.dumps(scfg.to_dict()))  # as a bundle manifest holds it
    assert StudentConfig.from_dict(saved) == scfg
    # A manifest that spells the streaming as flat fields: the diffusion-step list, null for every step.
    flat = {"denoising_steps": [1000, 750, 500, 250], "context_refresh": True, "refresh_steps": None, "sink_frames": 0}
    assert StudentConfig.from_dict(flat).streaming == TRAINING_STREAMING
    assert StudentConfig.from_dict({**flat, "refresh_steps": [2, 3]}).streaming.refresh_steps == (2, 3)
    with pytest.raises(ValueError, match="evenly spaced"):
        StudentConfig.from_dict({**flat, "denoising_steps": [1000, 500, 400]})


def test_partial_refresh_refuses_rows_at_different_times():
    model = _model(chunk=2, window=4)
    cond = tiny_conditions(model.cfg, 3, batch=2)
    engine = StreamingEngine(model, streaming(refresh_steps=(3,)))
    with torch.no_grad():
        engine.start(torch.randn(2, *model.cfg.latent_shape(1)), cond.frames(0, 1))
        x0_fn = engine.chunk_x0_fn(cond.frames(1, 3))
        x = torch.randn(2, *model.cfg.latent_shape(2))
        assert x0_fn(x, engine.times[[3, 3]]).shape == x.shape
        with pytest.raises(ValueError, match="same denoising time"):
            x0_fn(x, engine.times[[0, 3]])

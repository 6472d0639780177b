"""ReferenceGenerator: first frames from controls / one view / all views, object completion, overfit."""

from dataclasses import replace

import numpy as np
import pytest
import torch

from tests.model_fixtures import make_frames, make_sensors, perturbed, tiny_conditions
from world_model import Observation
from world_model.model import MultiViewDiT, SensorVAE, flow_matching_loss, get_preset, sample_timesteps
from world_model.model.conditions import Conditions
from world_model.model.reference import ReferenceConfig, ReferenceGenerator, expand_teacher, reference_input

CFG = get_preset("tiny")
UNGUIDED = replace(CFG.sampler, camera_cfg_scale=1.0, lidar_apg_scale=1.0)
OVERFIT_STEPS = 200
OVERFIT_BATCH = 4
OWN_VS_OTHER = 0.5  # generated view error vs its reference / vs another sample's view; measured 0.05 (200 steps)


@pytest.fixture(scope="module")
def parts():
    torch.manual_seed(0)
    vae = perturbed(SensorVAE(CFG), scale=0.05)
    model = perturbed(expand_teacher(MultiViewDiT(CFG)))  # perturbed after: reference weights non-zero
    return vae, model


def _front_image(seed: int) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (CFG.sensors.height, CFG.sensors.width, 3), dtype=np.uint8)


def test_first_frame_shapes_observations_and_determinism(parts):
    vae, model = parts
    gen = ReferenceGenerator(model, vae)
    cond = tiny_conditions(CFG, 3, batch=2)
    lat, obs = gen.first_frame(cond, steps=2, seed=7)
    assert lat.shape == (2, 1, *CFG.latent_shape(1)[1:]) and torch.isfinite(lat).all()
    assert len(obs) == 2 and all(isinstance(o, Observation) for o in obs)
    assert obs[0].cameras.shape == (CFG.sensors.num_cameras, CFG.sensors.height, CFG.sensors.width, 3)
    assert obs[0].lidar.shape == (CFG.sensors.lidar.beams, CFG.sensors.lidar.azimuth)
    again, _ = gen.first_frame(cond, steps=2, seed=7)
    other, _ = gen.first_frame(cond, steps=2, seed=8)
    assert torch.equal(lat, again) and not torch.equal(lat, other)


def test_guidance_replaces_the_samplers_camera_scale_only(parts):
    vae, model = parts
    gen = ReferenceGenerator(model, vae)
    cond = tiny_conditions(CFG, 3, batch=1)
    for scale in (1.0, 2.0):
        given = gen.sample(cond.frames(0, 1), steps=2, seed=3, guidance=scale)
        spelled = gen.sample(cond.frames(0, 1), seed=3, sampler=replace(CFG.sampler, steps=2, camera_cfg_scale=scale))
        assert torch.equal(given, spelled)
    assert not torch.equal(given, gen.sample(cond.frames(0, 1), steps=2, seed=3))  # the config's 3
    lat, _ = gen.first_frame(cond, steps=2, seed=3, guidance=2.0)
    assert torch.equal(lat, given)


def test_single_view_reference_is_pasted_and_anchors_the_frame(parts):
    vae, model = parts
    gen = ReferenceGenerator(model, vae)
    cond = tiny_conditions(CFG, 1)
    img = _front_image(0)
    front = CFG.sensors.rig().names.index("FRONT")
    lat, obs = gen.first_frame(cond, {"FRONT": img}, steps=2, seed=0)
    with torch.no_grad():
        expected = vae.encode(torch.from_numpy(img).permute(2, 0, 1)[None].float() / 127.5 - 1.0)[0]
    torch.testing.assert_close(lat[0, 0, front], expected)  # mask = 1: the latent is the reference's
    free, _ = gen.first_frame(cond, steps=2, seed=0)
    others = [v for v in range(CFG.sensors.num_views) if v != front]
    assert not torch.equal(lat[0, 0, others], free[0, 0, others])  # the reference conditions the rest
    nopaste = ReferenceGenerator(model, vae, ReferenceConfig(paste_observed=False))
    raw, _ = nopaste.first_frame(cond, {"FRONT": img}, steps=2, seed=0)
    assert torch.equal(raw[0, 0, others], lat[0, 0, others]) and not torch.equal(raw[0, 0, front], expected)


def test_all_views_reference_and_batched_references(parts):
    vae, model = parts
    gen = ReferenceGenerator(model, vae)
    cams, lidar, _ = make_sensors(CFG, 2)
    cond = tiny_conditions(CFG, 1, batch=2)
    lat, _ = gen.first_frame(cond, {"cameras": cams, "lidar": lidar.astype(np.float32)}, steps=2)
    enc = vae.encode_frames(cams, lidar.astype(np.float32))
    torch.testing.assert_close(lat[:, 0], enc)  # every view observed: both samples are the references
    one, _ = gen.first_frame(cond, {"cameras": cams[0]}, steps=2)  # unbatched: shared by the batch
    assert torch.equal(one[0, 0, :-1], one[1, 0, :-1])


def test_bad_references_get_actionable_errors(parts):
    vae, model = parts
    gen = ReferenceGenerator(model, vae)
    cond = tiny_conditions(CFG, 1)
    with pytest.raises(ValueError, match="resize camera images"):
        gen.first_frame(cond, {"FRONT": np.zeros((10, 10, 3), np.uint8)})
    with pytest.raises(ValueError, match="unknown reference key 'SIDE'"):
        gen.first_frame(cond, {"SIDE": _front_image(0)})
    with pytest.raises(ValueError, match="uint8"):
        gen.first_frame(cond, {"FRONT": _front_image(0).astype(np.float32)})
    teacher_only = ReferenceGenerator(perturbed(MultiViewDiT(CFG)), vae)
    lat, _ = teacher_only.first_frame(cond, steps=1)  # controls only works with a plain teacher
    assert lat.shape[1] == 1
    with pytest.raises(ValueError, match="--stage reference"):
        teacher_only.first_frame(cond, {"FRONT": _front_image(0)}, steps=1)


def test_complete_object_keeps_everything_but_the_object(parts):
    vae, model = parts
    gen = ReferenceGenerator(model, vae)
    frames = make_frames(CFG, 2)
    cams, lidar, _ = make_sensors(CFG, 2)
    cond = tiny_conditions(CFG, 2)
    lat, obs, mask = gen.complete_object(cond, frames, cams, lidar.astype(np.float32), "car1", steps=2)
    assert lat.shape == (1, *CFG.latent_shape(2)) and len(obs[0]) == 2
    enc = vae.encode_frames(cams, lidar.astype(np.float32))
    m = torch.from_numpy(mask).expand_as(enc).bool()
    assert (~m).any() and m.any()
    torch.testing.assert_close(lat[0][m], enc[m])  # observed regions kept
    assert not torch.allclose(lat[0][~m], enc[~m])  # the object's region is generated


def test_single_view_conditioning_reproduces_the_view_on_an_overfit_model():
    """Several different clips share one set of controls: only the reference tells them apart.
    After overfitting, the generated conditioned view (no pasting) is its reference's, not another's."""
    torch.manual_seed(0)
    vae = SensorVAE(CFG).eval()
    samples = []
    for i in range(3):
        cams, lidar, _ = make_sensors(CFG, 1, phase=0.9 * i)
        samples.append(vae.encode_frames(cams, lidar.astype(np.float32)))
    x_all = torch.stack(samples)  # (S, 1, V, C, h, w)
    x_all = (x_all - x_all.mean()) / x_all.std()
    model = expand_teacher(MultiViewDiT(CFG))
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    cond = Conditions.cat([tiny_conditions(CFG, 1)] * OVERFIT_BATCH)
    gen = torch.Generator().manual_seed(0)
    rng = np.random.default_rng(0)
    v, vc = CFG.sensors.num_views, CFG.sensors.num_cameras
    for _ in range(OVERFIT_STEPS):
        x0 = x_all[torch.from_numpy(rng.integers(len(samples), size=OVERFIT_BATCH))]
        mask = torch.zeros(OVERFIT_BATCH, 1, v, 1, *CFG.latent_hw)
        mask[torch.arange(OVERFIT_BATCH), 0, torch.from_numpy(rng.integers(vc, size=OVERFIT_BATCH))] = 1.0
        extra = reference_input(x0, mask)
        t = sample_timesteps((OVERFIT_BATCH,), CFG.flow, gen)
        noise = torch.randn(x0.shape, generator=gen)
        loss = flow_matching_loss(lambda xt, tt, e=extra: model(torch.cat([xt, e], 3), tt, cond), x0, t, noise)
        opt.zero_grad()
        loss.backward()
        opt.step()
    model.eval()
    refgen = ReferenceGenerator(model, vae, ReferenceConfig(paste_observed=False))
    view = CFG.sensors.rig().names.index("FRONT")
    one = tiny_conditions(CFG, 1)
    for i in range(len(samples)):
        mask = torch.zeros(1, 1, v, 1, *CFG.latent_hw)
        mask[0, 0, view] = 1.0
        out = refgen.sample(one, reference_input(x_all[i : i + 1], mask), steps=8, seed=i, sampler=UNGUIDED)
        own = (out[0, 0, view] - x_all[i, 0, view]).pow(2).mean()
        other = min((out[0, 0, view] - x_all[j, 0, view]).pow(2).mean() for j in range(len(samples)) if j != i)
        assert own < OWN_VS_OTHER * other, (i, float(own), float(other))

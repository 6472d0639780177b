"""Condition conversion, control tokens (object-order invariance, padding), text encoders."""

from dataclasses import replace

import numpy as np
import pytest
import torch

from tests.model_fixtures import make_frames, make_sensors, perturbed, tiny_conditions
from world_model import Box3D, SceneObject, default_rig
from world_model.model import (
    ControlTokenizer,
    HashTextEncoder,
    MiniLMTextEncoder,
    MultiViewDiT,
    SensorVAE,
    VaeCropEncoder,
    build_condition_arrays,
    get_preset,
    view_adjacency,
)
from world_model.model.conditions import ConditionOptions, Conditions, style_of_prompt


def test_default_rig_cross_view_neighbours():
    rig = default_rig()
    adj = view_adjacency(rig)
    idx = {n: i for i, n in enumerate(rig.names)}
    lidar = rig.num_views
    neighbours = {n: {rig.names[j] if j < lidar else "LIDAR" for j in np.flatnonzero(adj[i])} for n, i in idx.items()}
    assert neighbours["FRONT"] == {"FRONT_LEFT", "FRONT_RIGHT", "LIDAR"}
    assert neighbours["FRONT_LEFT"] == {"FRONT", "BACK_LEFT", "LIDAR"}
    assert neighbours["BACK"] == {"BACK_LEFT", "BACK_RIGHT", "LIDAR"}
    assert set(np.flatnonzero(adj[lidar])) == set(range(rig.num_views))
    assert not adj.diagonal().any() and (adj == adj.T).all()


def test_condition_arrays_shapes_cap_and_nearest_first():
    cfg = get_preset("tiny")
    frames = make_frames(cfg, 2, num_objects=7, seed=3)
    _, _, bev = make_sensors(cfg, 2)
    arr = build_condition_arrays(frames, bev, cfg, HashTextEncoder(cfg.text.dim))
    o = cfg.control.max_objects
    assert arr.obj_corners.shape == (2, o, 8, 3) and arr.obj_mask.sum(axis=1).tolist() == [o, o]
    centres = frames[0].object_corners_lidar().mean(axis=1)
    nearest = np.sort(np.linalg.norm(centres[:, :2], axis=1))[:o]
    kept = np.linalg.norm(arr.obj_corners[0].mean(axis=1)[:, :2], axis=1)
    assert np.allclose(kept, nearest, atol=1e-4)
    assert arr.camera.shape == (cfg.sensors.num_cameras, 7, 3) and arr.camera[:, 0, 2].max() <= 0.5 + 1e-6
    assert np.allclose(arr.ego[0], np.concatenate([np.eye(3), np.zeros((1, 3))]))
    assert arr.text_mask.any() and not arr.obj_has_image.any()


def test_a_scene_raster_of_another_config_is_refused():
    from world_model.model.config import with_layout
    from world_model.raster.maps import SceneRaster

    cfg = get_preset("tiny")
    frames = make_frames(cfg, 1)
    _, _, bev = make_sensors(cfg, 1)
    options = ConditionOptions(raster=SceneRaster(with_layout(cfg, True)))
    with pytest.raises(ValueError, match="options.raster draws the maps of another model config"):
        build_condition_arrays(frames, bev, cfg, HashTextEncoder(cfg.text.dim), options)


def test_bad_bev_shape_raises_actionable_error():
    cfg = get_preset("tiny")
    frames = make_frames(cfg, 2)
    with pytest.raises(ValueError, match="bev must have shape"):
        build_condition_arrays(frames, np.zeros((2, 3, 3, 3)), cfg, HashTextEncoder(cfg.text.dim))


def test_image_descriptions_from_crops_and_object_image():
    cfg = get_preset("tiny")
    frames = make_frames(cfg, 1, num_objects=2)
    _, _, bev = make_sensors(cfg, 1)
    enc = VaeCropEncoder(SensorVAE(cfg))
    arr = build_condition_arrays(
        frames,
        bev,
        cfg,
        HashTextEncoder(cfg.text.dim),
        ConditionOptions(image_encoder=enc, crops={"car1": np.full((9, 7, 3), 200, np.uint8)}),
    )
    assert arr.obj_has_image[0].sum() == 1 and arr.obj_image.shape[-1] == 2 * cfg.vae.latent_channels
    slot = int(np.flatnonzero(arr.obj_has_image[0])[0])
    car1 = [i for i, o in enumerate(frames[0].objects) if o.track_id == "car1"][0]
    assert np.allclose(arr.obj_corners[0, slot], frames[0].object_corners_lidar()[car1], atol=1e-5)
    with pytest.raises(ValueError, match="uint8"):
        enc.encode([np.zeros((4, 4, 3), np.float32)])


@pytest.mark.parametrize("layout", [False, True])
def test_field_specs_are_the_built_arrays_shapes_and_dtypes(layout):
    from world_model.model.conditions import condition_field_specs
    from world_model.model.config import with_layout

    cfg = with_layout(get_preset("tiny"), layout)
    frames = make_frames(cfg, 3, num_objects=2)
    _, _, bev = make_sensors(cfg, 3)
    options = ConditionOptions(image_encoder=VaeCropEncoder(SensorVAE(cfg)))
    arr = build_condition_arrays(frames, bev, cfg, HashTextEncoder(cfg.text.dim), options)
    specs = condition_field_specs(cfg, 3)
    assert {k: (getattr(arr, k).shape, getattr(arr, k).dtype) for k in specs} == {
        k: (s.shape, s.dtype) for k, s in specs.items()
    }


def test_a_crop_feature_does_not_depend_on_the_crops_encoded_with_it():
    cfg = get_preset("tiny")
    vae = perturbed(SensorVAE(cfg).eval())
    rng = np.random.default_rng(0)
    crops = [rng.integers(0, 255, (int(rng.integers(8, 40)), int(rng.integers(8, 40)), 3), np.uint8) for _ in range(4)]
    together = VaeCropEncoder(vae).encode(crops)
    alone = np.concatenate([VaeCropEncoder(vae).encode([c]) for c in crops])
    assert np.array_equal(together, alone)


def test_object_tokens_ignore_order_and_padding():
    cfg = get_preset("tiny")
    torch.manual_seed(0)
    model = perturbed(MultiViewDiT(cfg))
    cond = tiny_conditions(cfg, 2, num_objects=3)
    x = torch.randn(1, *cfg.latent_shape(2))
    t = torch.tensor([0.4])
    base = model(x, t, cond)
    perm = torch.tensor([2, 0, 1, 3])  # 3 real objects, 1 padding slot
    fields = [
        "obj_corners",
        "obj_category",
        "obj_text",
        "obj_image",
        "obj_mask",
        "obj_has_text",
        "obj_has_image",
    ]
    permuted = cond.apply(lambda k, v: v[:, :, perm] if k in fields else v)
    assert torch.allclose(model(x, t, permuted), base, atol=1e-5)
    # Garbage in the padding slot changes nothing; neither does the object's own token change.
    garbage = cond.apply(lambda k, v: v.clone() if k in fields else v)
    garbage.obj_corners[:, :, 3] = 33.0
    garbage.obj_category[:, :, 3] = 5.0
    assert torch.allclose(model(x, t, garbage), base, atol=1e-5)
    # Removing one object leaves the other objects' tokens unchanged (no interaction).
    tok = ControlTokenizer(cfg)
    fewer = cond.apply(lambda k, v: v.clone() if k in fields else v)
    fewer.obj_mask[:, :, 2] = False
    a, b = tok.object_tokens(cond), tok.object_tokens(fewer)
    assert torch.allclose(a[:, :, :2], b[:, :, :2]) and not torch.allclose(a[:, :, 2], b[:, :, 2])
    # Dropping conditions (guidance) does change the output: controls matter.
    assert not torch.allclose(model(x, t, cond.with_drop(True)), base, atol=1e-4)


def test_minilm_text_encoder_tokens_pooled_and_cache():
    enc = MiniLMTextEncoder()
    tokens = enc.tokens("a red truck hauling trees on a sunny highway")
    assert tokens.ndim == 2 and tokens.shape[1] == 384 and len(tokens) > 5
    assert enc.tokens("a red truck hauling trees on a sunny highway") is tokens  # cached by string
    pooled = enc.pooled(["car", "automobile", "pedestrian crossing"])
    assert pooled.shape == (3, 384) and np.allclose(np.linalg.norm(pooled, axis=1), 1.0, atol=1e-4)
    assert pooled[0] @ pooled[1] > pooled[0] @ pooled[2]  # a real sentence encoder, not a hash
    cfg = get_preset("default")
    frames = make_frames(cfg, 1, num_objects=2)
    _, _, bev = make_sensors(cfg, 1)
    arr = build_condition_arrays(frames, bev, cfg, enc)
    assert arr.text.shape == (cfg.text.max_tokens, 384) and arr.obj_category.shape[-1] == 384
    # the decoder's scene style is the sentence encoder's own pooled embedding of the prompt
    full = frames[0].prompt.full_text()
    assert np.allclose(arr.style, enc.pooled([full])[0], atol=1e-5)


def test_the_scene_style_pools_the_prompt_tokens_alike_in_numpy_and_torch():
    tiny = get_preset("tiny")
    cfg = replace(tiny, text=replace(tiny.text, max_tokens=64))  # the whole prompt, then padding
    text = HashTextEncoder(cfg.text.dim)
    frames = make_frames(cfg, 2, num_objects=1)
    _, _, bev = make_sensors(cfg, 2)
    arr = build_condition_arrays(frames, bev, cfg, text)
    assert 0 < arr.text_mask.sum() < cfg.text.max_tokens  # padding is left out of the mean
    assert np.allclose(arr.style, text.pooled([frames[0].prompt.full_text()])[0], atol=1e-6)
    assert np.allclose(arr.style, style_of_prompt(frames[0].prompt, cfg, text))
    batch = Conditions.collate([arr, arr])
    assert batch.style.shape == (2, cfg.text.dim) and np.allclose(batch.style.numpy(), arr.style[None], atol=1e-6)


def test_object_text_falls_back_to_colour_and_category():
    cfg = get_preset("tiny")
    frames = make_frames(cfg, 1, num_objects=1)
    obj = frames[0].objects[0]
    assert obj.description == ""
    bare = SceneObject(track_id="x", category="cone", box=Box3D((90.0, 0.0, 0.4), (0.4, 0.4, 0.75), 0.0), color_name="")
    _, _, bev = make_sensors(cfg, 1)
    enc = HashTextEncoder(cfg.text.dim)
    arr = build_condition_arrays([frames[0].with_objects((obj, bare))], bev, cfg, enc)
    assert arr.obj_has_text[0, :2].tolist() == [True, False]
    assert np.allclose(arr.obj_text[0, 0], enc.pooled(["red car"])[0])

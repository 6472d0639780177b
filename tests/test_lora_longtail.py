"""m4world bench longtail: base-set filtering, rare views, before/after scoring with a pluggable scorer."""

from dataclasses import replace

import cv2
import numpy as np
import pytest
import torch

from m4world_env.bench import longtail as bench
from tests.model_fixtures import make_frames, make_sensors, perturbed
from world_model.data import Clip, iter_clips, write_clip
from world_model.lora import LoraConfig, add_adapter, base_fingerprint, remove_adapters, save_adapter
from world_model.model import MultiViewDiT, SensorVAE, get_preset

CFG = get_preset("tiny")


def _clip(root, name, seed, rare):
    frames = make_frames(CFG, 3, seed=seed)
    if rare:
        frames = [
            fr.with_objects(tuple(replace(o, category="tree_truck") if o.track_id == "car1" else o for o in fr.objects))
            for fr in frames
        ]
    cams, lidar, bev = make_sensors(CFG, 3, phase=seed)
    write_clip(root, Clip(name, frames, cams, lidar, bev))


def views_shape(views, clips) -> tuple[int, ...]:
    """One camera image of the clips' recording: (H, W, 3)."""
    return tuple(clips[views[0].clip].cameras.shape[2:])


def test_filter_keeps_only_clips_without_the_case(tmp_path):
    _clip(tmp_path / "all", "plain", 0, False)
    _clip(tmp_path / "all", "rare", 1, True)
    kept = bench.filter_dataset(tmp_path / "all", tmp_path / "base", "tree_truck")
    assert kept == ["plain"] and [c.name for c in iter_clips(tmp_path / "base")] == ["plain"]


def test_evaluate_scores_rare_views_before_and_after_and_draws_the_figure(tmp_path):
    _clip(tmp_path / "rare", "rare", 1, True)
    clips = list(iter_clips(tmp_path / "rare"))
    views = bench.rare_views(clips, "tree_truck", 2, 0.1)
    assert views and all(any(o.category == "tree_truck" for o in clips[v.clip].frames[v.frame].objects) for v in views)
    torch.manual_seed(0)
    vae, model = perturbed(SensorVAE(CFG), scale=0.05), perturbed(MultiViewDiT(CFG))
    fingerprint = base_fingerprint(model)
    for p in add_adapter(model, "tree_truck", LoraConfig(rank=2)):
        torch.nn.init.normal_(p, std=0.3)
    save_adapter(model, "tree_truck", tmp_path / "adapters" / "tree_truck", LoraConfig(rank=2), fingerprint)
    remove_adapters(model)
    calls = []

    def scorer(generated, truth):
        calls.append((generated.shape, truth.shape))
        return float(np.abs(generated.astype(int) - truth).mean())

    result = bench.evaluate(
        model,
        vae,
        clips,
        views,
        ["tree_truck"],
        scorer,
        bench.RenderOptions(steps=1, search_dirs=[tmp_path / "adapters"]),
    )
    assert len(calls) == 3 * len(views) and all(g == t for g, t in calls)  # crops of the same box
    assert list(result["images"]) == ["truth", "autoencoder", "base", "adapted"]
    assert result["autoencoder_median"] >= 0 and result["images"]["autoencoder"][0].shape == views_shape(views, clips)
    assert result["scorer"] == "scorer" and np.isfinite([result["base_median"], result["adapted_median"]]).all()
    assert result["base_median"] != result["adapted_median"]  # the adapter changed the rendering
    assert base_fingerprint(model) == fingerprint and not any(".lora_" in k for k in model.state_dict())
    bench.figure(result, views, tmp_path / "fig.png")
    img = cv2.imread(str(tmp_path / "fig.png"))
    assert img is not None and img.shape[1] > bench.CROP_PX * len(views)
    # judge scores: a fake judge that says yes to tree trucks and records what it was asked
    asked = []

    class Judge:
        def is_category(self, crops, categories):
            asked.append(("category", len(crops), tuple(categories)))
            return np.array([c == "tree_truck" for c in categories])

        def is_weather(self, frames, weathers):
            asked.append(("weather", frames.shape, tuple(weathers)))
            return np.ones(len(frames), bool)

        def is_time_of_day(self, frames, times):
            return np.zeros(len(frames), bool)

    rows = ("truth", "autoencoder", "base", "adapted")
    assert bench.judge_rare(Judge(), result, views, "tree_truck") == dict.fromkeys(rows, 1.0)
    _clip(tmp_path / "base", "plain", 0, False)
    plain = list(iter_clips(tmp_path / "base"))
    frames = bench.ordinary_frames(plain, 3, 0.1)
    assert len(frames) == 1  # one clip: one frame
    scores = bench.judge_ordinary(
        Judge(), model, vae, plain, frames, ["tree_truck"], bench.RenderOptions(1, 0, [tmp_path / "adapters"])
    )
    assert set(scores) == {"truth", "base", "adapted"}
    assert all(s["weather"] == 1.0 and s["time_of_day"] == 0.0 and s["existence"] == 0.0 for s in scores.values())
    weather_calls = [a for a in asked if a[0] == "weather"]
    assert weather_calls and all(shape[1:] == (CFG.sensors.num_cameras,) + (16, 32, 3) for _, shape, _ in weather_calls)
    assert not any(".lora_" in k for k in model.state_dict())  # the adapter was removed again


def test_completion_task_regenerates_only_the_rare_object(tmp_path, monkeypatch):
    """--task completion: a reference model regenerates the view's object (its track) with the
    rest of the frame observed, so the scene away from the box stays the autoencoded truth,
    unlike a first frame from controls; a plain teacher is refused."""
    from world_model.model.reference import expand_teacher

    _clip(tmp_path / "rare", "rare", 1, True)
    clips = list(iter_clips(tmp_path / "rare"))
    views = bench.rare_views(clips, "tree_truck", 2, 0.1)
    assert all(v.track == "car1" for v in views)
    torch.manual_seed(0)
    vae, teacher = perturbed(SensorVAE(CFG), scale=0.05), perturbed(MultiViewDiT(CFG))
    reference = perturbed(expand_teacher(teacher))
    fingerprint = base_fingerprint(reference)
    for p in add_adapter(reference, "tree_truck", LoraConfig(rank=2)):
        torch.nn.init.normal_(p, std=0.3)
    save_adapter(reference, "tree_truck", tmp_path / "adapters" / "tree_truck", LoraConfig(rank=2), fingerprint)
    remove_adapters(reference)
    render = bench.RenderOptions(steps=1, search_dirs=[tmp_path / "adapters"])
    calls = []
    original = bench.ReferenceGenerator.complete_object

    def recording(self, cond, frames, cameras, lidar, track_id, **k):
        calls.append((frames[0].frame_index, track_id, cameras.shape[0], cond.num_frames))
        return original(self, cond, frames, cameras, lidar, track_id, **k)

    monkeypatch.setattr(bench.ReferenceGenerator, "complete_object", recording)
    done = bench.evaluate(reference, vae, clips, views, ["tree_truck"], options=replace(render, task="completion"))
    first = bench.evaluate(reference, vae, clips, views, ["tree_truck"], options=replace(render, task="first_frame"))

    def away_from_box(name, result):
        errs = []
        for rv, img, ae in zip(views, result["images"][name], result["images"]["autoencoder"], strict=True):
            keep = np.ones(img.shape[:2], bool)
            x0, y0, x1, y1 = rv.box
            keep[max(0, y0 - 8) : y1 + 8, max(0, x0 - 8) : x1 + 8] = False
            errs.append(np.abs(img.astype(int) - ae)[keep].mean())
        return float(np.mean(errs))

    want = [(clips[v.clip].frames[v.frame].frame_index, v.track, 1, 1) for v in views]
    assert calls == want * 2  # each view's own frame and object, without then with the adapter
    assert away_from_box("base", done) < away_from_box("base", first)
    assert done["base_median"] != done["adapted_median"]  # the adapter changed the completed object
    with pytest.raises(ValueError, match="reference model"):
        bench.evaluate(teacher, vae, clips, views, ["tree_truck"], options=replace(render, task="completion"))
    nameless = [replace(v, track="") for v in views]
    with pytest.raises(ValueError, match="names no object"):
        bench.evaluate(reference, vae, clips, nameless, ["tree_truck"], options=replace(render, task="completion"))
    # reset: the base row is the first frame from controls; the adapter redraws the category's boxes in it
    reset = bench.evaluate(
        reference,
        vae,
        clips,
        views,
        ["tree_truck"],
        options=replace(render, task="reset", category="tree_truck"),
    )
    for a, b in zip(reset["images"]["base"], first["images"]["base"], strict=True):
        assert np.array_equal(a, b)
    assert reset["adapted_median"] != reset["base_median"]  # (latent cells outside the boxes: test_env_world_model)


def test_blank_object_fills_the_grown_box_with_the_views_mean_colour(tmp_path):
    _clip(tmp_path / "rare", "rare", 1, True)
    clip = next(iter(iter_clips(tmp_path / "rare")))
    view = bench.rare_views([clip], "tree_truck", 1, 0.1)[0]
    cams = np.asarray(clip.cameras[view.frame])
    out = bench.blank_object(clip.frames[view.frame], cams, view.track, 2, 0.1)
    x0, y0, x1, y1 = view.box
    h, w = cams.shape[1:3]
    grown = (slice(max(0, y0 - 2), min(h, y1 + 2)), slice(max(0, x0 - 2), min(w, x1 + 2)))
    keep = np.ones((h, w), bool)
    keep[grown] = False
    region = out[view.view][grown]
    assert np.all(region == region[0, 0])  # one colour
    assert np.allclose(region[0, 0], cams[view.view][keep].mean(axis=0), atol=0.5)
    assert np.array_equal(out[view.view][keep], cams[view.view][keep])  # the rest untouched
    assert not np.shares_memory(out, cams)

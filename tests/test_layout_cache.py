"""The training data's layout and label-map caches: computed once per run (in worker processes for a
dataset's worth), read back by every later stage, equal to the raster computed in place."""

from dataclasses import replace

import numpy as np
import pytest
import torch

import world_model.train.data as train_data
from tests.model_fixtures import make_dataset
from world_model.model import get_preset, make_text_encoder
from world_model.model.config import with_layout, without_label_decoder
from world_model.sim.labels import LabelRasterizer
from world_model.train.data import LatentWindows, cached_label_maps, cached_layouts, load_clips
from world_model.train.vae_stage import picked_labels, view_labels

CFG = with_layout(get_preset("tiny"), True)


@pytest.fixture(scope="module")
def clips(tmp_path_factory):
    return load_clips(make_dataset(tmp_path_factory.mktemp("data"), CFG, lengths=(4, 3, 5)), CFG)


def _in_place(clips):
    latents = [torch.zeros(c.num_frames, 1) for c in clips]
    windows = LatentWindows(clips, latents, CFG, make_text_encoder(CFG.text), None)
    return [windows.clip_arrays(i).layout for i in range(len(clips))]


def test_layouts_from_worker_processes_equal_the_raster_computed_in_place(clips, tmp_path, monkeypatch):
    monkeypatch.setattr(train_data, "LAYOUT_POOL_MIN_FRAMES", 0)
    pooled = cached_layouts(clips, CFG, tmp_path, workers=2)
    for got, want in zip(pooled, _in_place(clips), strict=True):
        np.testing.assert_array_equal(got, want)


def test_a_second_stage_reads_the_cache_and_a_changed_setting_or_corrupt_entry_recomputes(clips, tmp_path, monkeypatch):
    first = cached_layouts(clips, CFG, tmp_path, workers=1)
    monkeypatch.setattr(train_data, "_clip_layout", lambda *a: pytest.fail("recomputed a cached layout"))
    again = cached_layouts(clips, CFG, tmp_path, workers=1)
    assert all(np.array_equal(a, b) for a, b in zip(first, again, strict=True))
    plain_decoder = without_label_decoder(CFG)
    cached_layouts(clips, plain_decoder, tmp_path, workers=1)  # the decoder's settings: the same rasters
    monkeypatch.undo()
    (tmp_path / f"{clips[0].name}.safetensors").write_bytes(b"garbage")
    finer = replace(CFG, layout=replace(CFG.layout, supersample=CFG.layout.supersample + 1))
    calls = []
    real = train_data._clip_layout
    monkeypatch.setattr(train_data, "_clip_layout", lambda *a: calls.append(1) or real(*a))
    cached_layouts(clips, CFG, tmp_path, workers=1)
    assert len(calls) == 1  # only the corrupt entry
    cached_layouts(clips, finer, tmp_path, workers=1)
    assert len(calls) == 1 + len(clips)  # another supersampling: every clip again


def test_no_layout_in_the_config_no_cache(clips, tmp_path):
    assert cached_layouts(clips, get_preset("tiny"), tmp_path) is None
    assert not tmp_path.joinpath(f"{clips[0].name}.safetensors").exists()


def test_label_maps_from_worker_processes_equal_the_decoders_view_labels_and_are_read_back(
    clips, tmp_path, monkeypatch
):
    monkeypatch.setattr(train_data, "LAYOUT_POOL_MIN_FRAMES", 0)
    pooled = cached_label_maps(clips, CFG, tmp_path, workers=2)
    raster, views = LabelRasterizer(), range(CFG.sensors.num_views)
    for c, (clip, maps) in enumerate(zip(clips, pooled, strict=True)):
        assert maps.dtype == np.uint8 and maps.shape[:2] == (clip.num_frames, CFG.sensors.num_cameras)
        for f, frame in enumerate(clip.frames):
            want = view_labels(raster, frame, CFG, views).numpy()
            got = np.stack([picked_labels(pooled, c, f, v, CFG) for v in views])
            np.testing.assert_array_equal(got, want)  # the LiDAR view too: no label
    monkeypatch.setattr(train_data, "camera_labels", lambda *a: pytest.fail("recomputed cached label maps"))
    again = cached_label_maps(clips, CFG, tmp_path, workers=1)
    assert all(np.array_equal(a, b) for a, b in zip(pooled, again, strict=True))


def test_one_process_reads_a_dataset_once_until_it_changes(tmp_path, monkeypatch):
    data = make_dataset(tmp_path / "data", CFG, lengths=(3, 2))
    reads = []
    real = train_data.iter_clips
    monkeypatch.setattr(train_data, "iter_clips", lambda root: reads.append(root) or real(root))
    first = load_clips(data, CFG)
    assert load_clips(data, CFG) is first and len(reads) == 1  # the next stage of the same process
    other = replace(CFG, sensors=replace(CFG.sensors, bev=replace(CFG.sensors.bev, m_per_px=2.0)))
    with pytest.raises(ValueError, match="bev"):
        load_clips(data, other)  # another config is checked again, not served from memory
    make_dataset(data, CFG, lengths=(3, 2, 4))  # a clip recorded into it
    again = load_clips(data, CFG)
    assert len(again) == 3 and len(reads) == 3

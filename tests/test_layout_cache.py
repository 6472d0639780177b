"""The training data's layout cache: computed once per run (in worker processes for a dataset's
worth), read back by every later stage, equal to the raster computed in place."""

from dataclasses import replace

import numpy as np
import pytest
import torch

import world_model.train.data as train_data
from tests.model_fixtures import make_dataset
from world_model.model import get_preset, make_text_encoder
from world_model.model.config import with_layout
from world_model.train.data import LatentWindows, cached_layouts, load_clips

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
    plain_decoder = replace(CFG, layout=replace(CFG.layout, decoder=False, decoder_style=False))
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

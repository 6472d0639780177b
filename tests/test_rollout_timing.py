"""The rollout pipeline times its stages only through an attached timer: without one a step reads
no clock and waits for no device; with one each stage's seconds add up, a device's kernels included."""

import pytest
import torch

from tests.model_fixtures import make_frames
from world_model.raster.crops import RecordedCrops
from world_model.rollout.batch import RolloutBatch
from world_model.rollout.conditions import RolloutConditions
from world_model.rollout.runtime import load_world_model
from world_model.rollout.timing import PIPELINE_STAGES, StageTimer, timed


def test_a_step_waits_for_the_device_only_when_timed(tiny_bundle, monkeypatch):
    wm = load_world_model(tiny_bundle, device="cpu", dtype="float32")
    frames = make_frames(wm.cfg, 1 + 2 * wm.cfg.clip.chunk_frames)
    chunk = wm.cfg.clip.chunk_frames
    waits = []
    # As if the student ran on a GPU: its kernels would be queued, and waiting for them costs a sync.
    monkeypatch.setattr(RolloutBatch, "_device", property(lambda self: torch.device("cuda", 0)))
    monkeypatch.setattr(torch.cuda, "synchronize", lambda device=None: waits.append(device))
    # The first frame's sampling is not what is timed here: a blank one seeds the student's cache.
    monkeypatch.setattr(wm, "first_latents", lambda *a, **k: torch.zeros(1, *wm.cfg.latent_shape(1)))
    conditions, rollouts = RolloutConditions(wm.conditions, 1), RolloutBatch(wm, 1)
    rollouts.start_row(0, frames[0], 0, conditions.restart(0, frames[0], RecordedCrops()))
    rollouts.step_arrays([conditions.advance(0, frames[1 : 1 + chunk])])
    assert waits == [] and rollouts.timer is None and conditions.timer is None

    timer = conditions.timer = rollouts.timer = StageTimer()
    rollouts.step_arrays([conditions.advance(0, frames[1 + chunk : 1 + 2 * chunk])])
    assert waits == [torch.device("cuda", 0)]  # once, after the student's chunk
    assert set(timer.seconds) == set(PIPELINE_STAGES)
    assert all(timer.seconds[k] > 0 for k in ("conditions", "student", "decode")) and timer.seconds["crops"] >= 0


def test_stage_timer_adds_up_and_refuses_an_unknown_stage():
    timer = StageTimer()
    for _ in range(2):
        with timed(timer, "decode"):
            pass
    with timed(None, "decode"):  # no timer: nothing is read or kept
        pass
    assert timer.seconds["decode"] > 0 and timer.seconds["student"] == 0.0
    with pytest.raises(KeyError, match="stage must be one of .*'render'"), timer.stage("render"):
        pass

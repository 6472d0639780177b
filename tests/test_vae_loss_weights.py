"""VAE training weights: object boxes are up-weighted exactly where the simulator draws objects."""

from dataclasses import replace

import numpy as np

from tests.cli_status import exit_status
from tests.model_fixtures import QUIET, make_dataset, make_frames
from world_model.data import iter_clips
from world_model.model import get_preset
from world_model.sim import ProceduralSimulator
from world_model.train.data import FrameSampler, object_pixel_weights


def test_object_weights_cover_exactly_the_simulators_boxes():
    cfg = get_preset("default")
    frame = make_frames(cfg, 1, num_objects=4, seed=5)[0]
    s, extra = cfg.sensors, cfg.vae.object_loss_weight
    assert extra > 0  # the default recipe weights objects
    sim = ProceduralSimulator()
    seen = 0
    for v in range(s.num_cameras):
        expected = np.ones((s.height, s.width), np.float32)
        for x0, y0, x1, y1 in sim.object_boxes_2d(frame, v).values():
            expected[y0:y1, x0:x1] = 1.0 + extra
            seen += 1
        np.testing.assert_array_equal(object_pixel_weights(frame, v, s.height, s.width, extra), expected)
    assert seen > 0
    assert (object_pixel_weights(frame, 0, s.height, s.width, 0.0) == 1).all()  # weight 0: plain L1


def test_frame_sampler_weights_cameras_not_the_lidar_map(tmp_path):
    cfg = get_preset("tiny")
    clips = list(iter_clips(make_dataset(tmp_path, cfg, lengths=(4, 3))))
    sampler = FrameSampler(clips, cfg)
    batch = sampler.sample(np.random.default_rng(0), 64)
    s = cfg.sensors
    assert batch.images.shape == (64, 3, s.height, s.width) and batch.weights.shape == (64, 1, s.height, s.width)
    lidar = batch.is_lidar.numpy()
    assert lidar.any() and (~lidar).any()
    assert (batch.weights[lidar] == 1).all()
    assert (batch.weights[~lidar] > 1).any()  # some camera draw shows an object
    plain = FrameSampler(clips, replace(cfg, vae=replace(cfg.vae, object_loss_weight=0.0)))
    assert (plain.sample(np.random.default_rng(0), 64).weights == 1).all()


def test_vae_object_weight_flag_reaches_the_vae_stage_and_later_stages_accept_that_vae(tmp_path, capsys):
    from m4world_env.cli import main as m4world
    from world_model.train import load_vae, stage_options, train_stage
    from world_model.train.__main__ import main as train

    data = make_dataset(tmp_path / "data", get_preset("tiny"), lengths=(4, 3))
    run = tmp_path / "run"
    common = ["--data", str(data), "--run", str(run), "--preset", "tiny", "--no-progress"]
    assert train(["--stage", "vae", *common, "--steps", "2", "--vae-object-weight", "0"]) == 0
    assert load_vae(run / "vae" / "model").cfg.vae.object_loss_weight == 0.0
    # The teacher (preset weight) takes that VAE: the weight is a training-only setting.
    train_stage("teacher", data, run, stage_options("teacher", preset="tiny", steps=1, batch_size=1), QUIET)
    for cli in (lambda a: m4world(["train", *a]), train):
        assert exit_status(cli, ["--stage", "vae", *common, "--vae-object-weight", "-1"]) == 2
        assert "argument --vae-object-weight: must be a finite number of at least 0" in capsys.readouterr().err

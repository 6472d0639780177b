"""``--stage reference`` end to end on tiny data: task mix, export, exact resume, survives a kill."""

from pathlib import Path

import numpy as np
import pytest
import torch

from tests.model_fixtures import QUIET, kill_after_checkpoint, make_dataset, perturbed, tiny_conditions
from world_model.model import MultiViewDiT, SensorVAE, get_preset
from world_model.model.reference import TASKS, ReferenceConfig, ReferenceGenerator, reference_channels
from world_model.train import load_latest, load_teacher, load_vae, stage_options, train_stage
from world_model.train.checkpoint import export_weights
from world_model.train.exports import EXPORT
from world_model.train.reference_stage import reference_batch

CFG = get_preset("tiny")


def make_run(run: Path) -> Path:
    """A run directory with exported (random, perturbed) VAE and teacher, as the earlier stages leave it."""
    torch.manual_seed(0)
    meta = {"model_config": CFG.to_dict()}
    export_weights(run / "vae" / EXPORT, perturbed(SensorVAE(CFG), scale=0.05).state_dict(), {"stage": "vae", **meta})
    export_weights(run / "teacher" / EXPORT, perturbed(MultiViewDiT(CFG)).state_dict(), {"stage": "teacher", **meta})
    return run


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    return make_dataset(tmp_path_factory.mktemp("data"), CFG, lengths=(4, 3))


def test_reference_batches_mix_tasks_with_the_documented_probabilities(dataset, tmp_path):
    from world_model.model import make_text_encoder
    from world_model.train.data import LatentWindows, load_clips

    clips = load_clips(dataset, CFG)
    lat = [torch.randn(c.num_frames, *CFG.latent_shape(1)[1:]) for c in clips]
    windows = LatentWindows(clips, lat, CFG, make_text_encoder(CFG.text), None)
    rcfg = ReferenceConfig()
    rng = np.random.default_rng(0)
    counts = dict.fromkeys(TASKS, 0)
    n = 0
    for _ in range(150):
        x0, cond, extra, tasks = reference_batch(windows, rng, 4, rcfg)
        assert extra.shape == (*x0.shape[:3], reference_channels(CFG), *x0.shape[4:])
        assert cond.num_frames == x0.shape[1]
        mask = extra[:, :, :, -1:]
        torch.testing.assert_close(extra[:, :, :, :-1], x0 * mask)  # observed regions carry x0
        for task in tasks:
            counts[task] += 1
            n += 1
    for task, p in zip(TASKS, rcfg.task_probs, strict=True):
        assert abs(counts[task] / n - p) < 4 * np.sqrt(p * (1 - p) / n), (task, counts)


def test_reference_stage_end_to_end_exports_and_resumes_exactly(dataset, tmp_path):
    run = make_run(tmp_path / "run")
    out = train_stage(
        "reference", dataset, run, stage_options("reference", preset="tiny", steps=2, ckpt_every=1), QUIET
    )
    assert out["step"] == 2 and sum(out["task_counts"].values()) == 2 * 4
    ck = load_latest(run / "reference" / "checkpoints")
    assert ck.meta["model_config"]["dit"]["in_channels_extra"] == reference_channels(CFG)
    again = train_stage(
        "reference", dataset, run, stage_options("reference", preset="tiny", steps=4, ckpt_every=1), QUIET
    )
    assert again["resumed_from"] == 2 and again["step"] == 4
    # Resume is exact: an uninterrupted run sees the same losses.
    straight = train_stage(
        "reference", dataset, make_run(tmp_path / "b"), stage_options("reference", preset="tiny", steps=4), QUIET
    )
    assert straight["losses"][2:] == again["losses"]
    model = load_teacher(run / "reference" / "model")
    assert model.cfg.dit.in_channels_extra == reference_channels(CFG)
    lat, obs = ReferenceGenerator(model, load_vae(run / "vae" / "model")).first_frame(
        tiny_conditions(CFG, 1), {"FRONT": np.zeros((CFG.sensors.height, CFG.sensors.width, 3), np.uint8)}, steps=1
    )
    assert torch.isfinite(lat).all() and len(obs) == 1


def test_reference_stage_needs_the_teacher(dataset, tmp_path):
    with pytest.raises(FileNotFoundError, match="run --stage teacher first"):
        train_stage("reference", dataset, tmp_path / "empty", stage_options("reference", preset="tiny", steps=1), QUIET)


def test_killed_reference_run_resumes_from_last_checkpoint(dataset, tmp_path):
    run = make_run(tmp_path / "run")
    args = ["--stage", "reference", "--data", str(dataset), "--run", str(run), "--preset", "tiny"]
    checkpoints = run / "reference" / "checkpoints"
    kill_after_checkpoint([*args, "--steps", "100000", "--ckpt-every", "2", "--no-progress"], checkpoints)
    ck = load_latest(run / "reference" / "checkpoints")
    assert ck is not None and ck.step >= 4
    out = train_stage(
        "reference", dataset, run, stage_options("reference", preset="tiny", steps=ck.step + 2, ckpt_every=2), QUIET
    )
    assert out["resumed_from"] == ck.step and out["step"] == ck.step + 2


def test_a_reference_model_cut_to_the_teachers_input_is_the_reference_model_with_nothing_observed():
    from world_model.model.reference import expand_teacher, teacher_from_reference

    reference = perturbed(expand_teacher(perturbed(MultiViewDiT(CFG))), seed=1, scale=0.05)
    teacher = teacher_from_reference(reference)
    assert teacher.cfg == CFG and not teacher.training
    gen = torch.Generator().manual_seed(0)
    x = torch.randn(2, 3, *CFG.latent_shape(1)[1:], generator=gen)
    nothing = torch.zeros(2, 3, CFG.sensors.num_views, reference_channels(CFG), *CFG.latent_hw)
    t, cond = torch.rand(2, generator=gen), tiny_conditions(CFG, 3, batch=2)
    with torch.no_grad():
        assert torch.equal(teacher(x, t, cond), reference(torch.cat([x, nothing], dim=3), t, cond))
        observed = torch.cat([x, torch.ones_like(nothing)], dim=3)  # the cut channels were in use
        assert not torch.allclose(teacher(x, t, cond), reference(observed, t, cond))
    with pytest.raises(ValueError, match="extra input channels, got 0"):
        teacher_from_reference(teacher)

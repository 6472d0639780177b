"""``--stage first_frame`` on tiny data: the pool's targets are the reference model's first frames,
training brings the one-step frames to them, the export resumes exactly and loads as the env's."""

from pathlib import Path

import pytest
import torch

from tests.model_fixtures import QUIET, make_dataset, perturbed
from world_model.model import MultiViewDiT, SensorVAE, get_preset
from world_model.model.reference import ReferenceGenerator, expand_teacher, reference_model_config
from world_model.streaming import StreamingConfig
from world_model.train import load_teacher, stage_options, train_stage
from world_model.train.checkpoint import export_weights
from world_model.train.exports import EXPORT, open_run_latents, run_vae
from world_model.train.first_frame_stage import POOL_FILE, one_step_x0, row_noise

CFG = get_preset("tiny")
STEPS, BATCH = 40, 4


def make_run(run: Path) -> Path:
    """A run with exported (random, perturbed) VAE, teacher and reference model."""
    torch.manual_seed(0)
    meta = {"model_config": CFG.to_dict()}
    export_weights(run / "vae" / EXPORT, perturbed(SensorVAE(CFG), scale=0.05).state_dict(), {"stage": "vae", **meta})
    teacher = perturbed(MultiViewDiT(CFG))
    export_weights(run / "teacher" / EXPORT, teacher.state_dict(), {"stage": "teacher", **meta})
    reference = perturbed(expand_teacher(teacher), seed=1, scale=0.05)
    ref_meta = {"stage": "reference", "model_config": reference_model_config(CFG).to_dict()}
    export_weights(run / "reference" / EXPORT, reference.state_dict(), ref_meta)
    return run


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    return make_dataset(tmp_path_factory.mktemp("data"), CFG, lengths=(4, 3))


def _options(steps: int):
    return stage_options("first_frame", preset="tiny", steps=steps, batch_size=BATCH, lr=3e-3, ckpt_every=10)


def test_first_frame_stage_distils_the_reference_sampler_and_resumes_exactly(dataset, tmp_path):
    run = make_run(tmp_path / "run")
    out = train_stage("first_frame", dataset, run, _options(STEPS // 2), QUIET)
    assert out["step"] == STEPS // 2 and out["pool_frames"] == 4 + 3  # the clips' frames, fewer than POOL_FRAMES
    pool = torch.load(run / "first_frame" / POOL_FILE, weights_only=True)

    # The pool's targets are the reference model's first frames at the streaming defaults, from each
    # frame's own noise (what env.reset() draws).
    vae, _ = run_vae(run, CFG, "first_frame")
    windows = open_run_latents(dataset, run, CFG, "first_frame")
    rows = [0, 5]
    _, cond = windows.windows(pool["clips"].numpy()[rows], pool["starts"].numpy()[rows], 1)
    reference = load_teacher(run / "reference" / EXPORT)
    streaming = StreamingConfig()
    expected = ReferenceGenerator(reference, vae).sample(
        cond,
        steps=streaming.first_frame_steps,
        seed=pool["seeds"][rows].tolist(),
        guidance=streaming.first_frame_guidance,
    )
    torch.testing.assert_close(pool["targets"][rows], expected)

    def error(model: MultiViewDiT) -> float:
        _, all_cond = windows.windows(pool["clips"].numpy(), pool["starts"].numpy(), 1)
        with torch.no_grad():
            x0 = one_step_x0(model.eval(), row_noise(pool["seeds"].tolist(), CFG), all_cond)
        return float((x0 - pool["targets"]).pow(2).mean())

    again = train_stage("first_frame", dataset, run, _options(STEPS), QUIET)
    assert again["resumed_from"] == STEPS // 2 and again["step"] == STEPS
    straight = train_stage("first_frame", dataset, make_run(tmp_path / "b"), _options(STEPS), QUIET)
    assert straight["losses"][STEPS // 2 :] == again["losses"]  # resume is exact, the pool kept
    trained = load_teacher(run / "first_frame" / EXPORT)
    assert trained.cfg == reference.cfg
    assert error(trained) < 0.5 * error(reference), (error(trained), error(reference))


def test_first_frame_stage_needs_the_reference_model(dataset, tmp_path):
    run = make_run(tmp_path / "run")
    for suffix in (".safetensors", ".json"):
        (run / "reference" / EXPORT).with_suffix(suffix).unlink()
    with pytest.raises(FileNotFoundError, match="run --stage reference"):
        train_stage("first_frame", dataset, run, _options(1), QUIET)

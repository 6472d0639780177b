"""Student stages tf -> ode -> dmd -> long end to end from the CLI on a tiny dataset, resume, errors."""

import shutil
from pathlib import Path

import pytest
import torch

from tests.cli_status import exit_status
from tests.model_fixtures import QUIET
from world_model.model import get_preset
from world_model.train import stage_options, train_stage
from world_model.train.exports import load_student
from world_model.train.rollouts import reflected_index

from .model_fixtures import make_dataset, one_streamed_chunk, tiny_conditions, train_cli


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A run with a (barely) trained VAE and teacher, the student stages' inputs."""
    root = tmp_path_factory.mktemp("student")
    data = make_dataset(root / "data", get_preset("tiny"), lengths=(4, 3))
    for stage in ("vae", "teacher"):
        train_stage(stage, data, root / "run", stage_options(stage, preset="tiny", steps=2, ckpt_every=2), QUIET)
    return data, root / "run"


def test_student_stages_end_to_end_from_the_cli_and_resume(run):
    data, rundir = run
    common = ["--data", str(data), "--run", str(rundir)]
    for stage in ("tf", "ode", "dmd", "long"):
        extra = ["--long-frames", "4"] if stage == "long" else []
        out = train_cli("--stage", stage, *common, "--steps", "2", "--ckpt-every", "1", "--batch-size", "1", *extra)
        assert out["step"] == 2 and out["resumed_from"] is None, out
        assert (rundir / stage / "model.safetensors").exists() and (rundir / stage / "model.json").exists()
        again = train_cli("--stage", stage, *common, "--steps", "3", "--ckpt-every", "1", "--batch-size", "1", *extra)
        assert again["resumed_from"] == 2 and again["step"] == 3
        assert all(torch.isfinite(torch.tensor(again["final_loss"])).reshape(-1))
    assert (rundir / "dmd" / "critic.safetensors").exists()

    # The exported student streams with the engine.
    student, scfg = load_student(rundir / "long" / "model")
    assert scfg.num_steps == 4
    out = one_streamed_chunk(student, scfg)
    assert out.shape == (2, *student.cfg.latent_shape(1)) and torch.isfinite(out).all()


def test_student_stage_needs_its_predecessor(run, tmp_path):
    data, _ = run
    with pytest.raises(FileNotFoundError, match="run --stage ode"):
        train_stage("dmd", data, tmp_path / "fresh", stage_options("dmd", preset="tiny", steps=1), QUIET)


def test_reflected_playback_keeps_frames_adjacent():
    seq = [reflected_index(i, 4) for i in range(10)]
    assert seq == [0, 1, 2, 3, 2, 1, 0, 1, 2, 3]
    assert all(abs(a - b) == 1 for a, b in zip(seq, seq[1:], strict=False))
    assert reflected_index(7, 1) == 0


def _run_through_ode(run, tmp_path) -> tuple[Path, Path]:
    """A private copy of the module's run (VAE, teacher) with 1-step tf and ode stages."""
    data, rundir = run
    mine = tmp_path / "run"
    for stage in ("vae", "teacher"):
        shutil.copytree(rundir / stage, mine / stage, ignore=shutil.ignore_patterns("checkpoints"))
    for stage in ("tf", "ode"):
        train_stage(stage, data, mine, stage_options(stage, preset="tiny", steps=1, batch_size=1), QUIET)
    return data, mine


def test_diverging_dmd_run_stops_clearly_and_keeps_the_last_good_checkpoint(run, tmp_path):
    from world_model.train import TrainingDivergedError, load_latest

    data, mine = _run_through_ode(run, tmp_path)
    train_stage("dmd", data, mine, stage_options("dmd", preset="tiny", steps=1, batch_size=1, ckpt_every=1), QUIET)
    with pytest.raises(TrainingDivergedError, match="loss is (nan|inf).*last good checkpoint"):
        train_stage(
            "dmd", data, mine, stage_options("dmd", preset="tiny", steps=4, batch_size=1, ckpt_every=1, lr=1e30), QUIET
        )
    assert load_latest(mine / "dmd" / "checkpoints").step == 1


@pytest.mark.parametrize("prob, expected", [(0.0, 0), (1.0, 2)])
def test_dmd_and_long_stages_add_the_supervised_denoising_term_at_its_probability(
    run, tmp_path, monkeypatch, prob, expected
):
    from world_model.student import StudentConfig
    from world_model.train import student_stages

    data, mine = _run_through_ode(run, tmp_path)
    calls = []
    real_loss = student_stages.teacher_forcing_loss

    def counted(model, x0, *args):
        calls.append(x0.shape[1])
        return real_loss(model, x0, *args)

    monkeypatch.setattr(student_stages, "teacher_forcing_loss", counted)
    scfg = StudentConfig(denoise_loss_prob=prob, long_frames=4)
    for stage in ("dmd", "long"):
        calls.clear()
        train_stage(stage, data, mine, stage_options(stage, preset="tiny", steps=2, batch_size=1, student=scfg), QUIET)
        assert len(calls) == expected, (stage, calls)


@pytest.mark.parametrize("skip", [0, 2])
def test_long_stage_advances_its_rollout_by_the_untrained_chunks_between_trained_clips(run, tmp_path, skip):
    from world_model.student import StudentConfig

    data, mine = _run_through_ode(run, tmp_path)
    train_stage("dmd", data, mine, stage_options("dmd", preset="tiny", steps=1, batch_size=1), QUIET)
    scfg = StudentConfig(long_skip_chunks=skip, long_frames=100)
    out = train_stage(
        "long", data, mine, stage_options("long", preset="tiny", steps=3, batch_size=1, student=scfg), QUIET
    )
    c = get_preset("tiny").clip.chunk_frames
    # Step 1 trains the fresh rollout's first clip; steps 2 and 3 each skip, then train a clip.
    assert out["rollout_frames"] == scfg.prefix_frames + (3 * scfg.long_clip_chunks + 2 * skip) * c


def test_long_stage_restarts_a_rollout_that_cannot_hold_the_skipped_and_trained_chunks(run, tmp_path):
    from world_model.student import StudentConfig

    data, mine = _run_through_ode(run, tmp_path)
    train_stage("dmd", data, mine, stage_options("dmd", preset="tiny", steps=1, batch_size=1), QUIET)
    c = get_preset("tiny").clip.chunk_frames
    scfg = StudentConfig(long_skip_chunks=1, long_clip_chunks=1, long_frames=1 + 2 * c)
    out = train_stage(
        "long", data, mine, stage_options("long", preset="tiny", steps=2, batch_size=1, student=scfg), QUIET
    )
    assert out["rollout_frames"] == scfg.prefix_frames + c  # step 2 would pass long_frames: a fresh rollout
    with pytest.raises(ValueError, match="long_skip_chunks"):
        StudentConfig(long_skip_chunks=-1)


def test_both_train_clis_refuse_bad_student_flags_by_name(tmp_path, capsys):
    from m4world_env.cli import main as m4world
    from world_model.train.__main__ import main as train

    args = ["--stage", "long", "--data", str(tmp_path / "data"), "--run", str(tmp_path / "run"), "--preset", "tiny"]
    assert exit_status(m4world, ["train", *args, "--long-skip-chunks", "-1"]) == 2
    assert "argument --long-skip-chunks: must be 0 or a positive integer, got '-1'" in capsys.readouterr().err
    assert exit_status(train, [*args, "--long-skip-chunks", "-1"]) == 2
    assert "argument --long-skip-chunks: must be 0 or a positive integer, got '-1'" in capsys.readouterr().err
    assert exit_status(m4world, ["train", *args, "--denoise-loss-prob", "1.5"]) == 2
    assert "argument --denoise-loss-prob: must be a number in [0, 1], got '1.5'" in capsys.readouterr().err
    assert not (tmp_path / "run").exists()  # refused before any stage starts


def test_m4world_train_passes_the_student_flags_to_the_stage(tmp_path, monkeypatch):
    from m4world_env.cli import main as m4world
    from world_model.student import StudentConfig
    from world_model.train import stages

    seen = []
    monkeypatch.setattr(
        stages, "train_stage", lambda *a: seen.append((a[3].student, a[4].dtype, a[3].denoising_steps)) or {}
    )
    args = ["train", "--stage", "long", "--data", str(tmp_path), "--run", str(tmp_path), "--preset", "tiny"]
    flags = ["--long-skip-chunks", "3", "--denoise-loss-prob", "0.5", "--dmd-guidance-scale", "1.5"]
    flags += ["--dtype", "float32", "--denoising-steps", "2"]
    assert m4world([*args, *flags]) == 0
    assert m4world(args) == 0
    want = StudentConfig(long_skip_chunks=3, denoise_loss_prob=0.5, dmd_guidance_scale=1.5)
    assert seen == [(want, "float32", 2), (StudentConfig(), "auto", None)]  # no flag: the stage's defaults


def test_dmd_real_score_guidance_scale_replaces_the_teachers_and_reaches_the_loss():
    from dataclasses import replace

    from world_model.model import MultiViewDiT
    from world_model.model.flow import interpolate, predict_x0
    from world_model.student import StudentConfig
    from world_model.student.losses import dmd_loss
    from world_model.student.training import dmd_generator_loss, real_score_guidance

    cfg = get_preset("tiny")
    cfg = replace(cfg, sampler=replace(cfg.sampler, camera_cfg_scale=3.0, lidar_apg_scale=3.0))
    torch.manual_seed(0)
    real, critic = MultiViewDiT(cfg).eval(), MultiViewDiT(cfg).eval()
    for p in [*real.parameters(), *critic.parameters()]:  # adaLN-zero would make every score zero
        torch.nn.init.normal_(p, std=0.05)
    assert real_score_guidance(real, StudentConfig()) == cfg.sampler  # None: the teacher's scales
    unguided = real_score_guidance(real, StudentConfig(dmd_guidance_scale=1.0))
    assert (unguided.camera_cfg_scale, unguided.lidar_apg_scale) == (1.0, 1.0)

    cond = tiny_conditions(cfg, 2, batch=2)
    video, noise, t = torch.randn(2, *cfg.latent_shape(2)), torch.randn(2, *cfg.latent_shape(2)), torch.rand(2)
    with torch.no_grad():  # scale 1: the real score is the plain conditional teacher
        xt = interpolate(video, noise, t)
        expected = dmd_loss(video, predict_x0(xt, critic(xt, t, cond), t), predict_x0(xt, real(xt, t, cond), t))
        got = dmd_generator_loss(real, critic, video, cond, t, noise, guidance=unguided)
        guided = dmd_generator_loss(real, critic, video, cond, t, noise)
    assert torch.allclose(got, expected, atol=1e-6) and not torch.allclose(guided, expected, atol=1e-6)
    with pytest.raises(ValueError, match="dmd_guidance_scale must be > 0"):
        StudentConfig(dmd_guidance_scale=0.0)


def test_both_train_clis_retain_the_heap_unless_default_heap(tmp_path, monkeypatch):
    import world_model.train.student_flags as student_flags
    from m4world_env.cli import main as m4world
    from world_model.train import __main__ as train_module
    from world_model.train import stages

    calls = []
    monkeypatch.setattr(student_flags, "retain_freed_memory", lambda: calls.append(1))
    monkeypatch.setattr(stages, "train_stage", lambda *a, **kw: {})
    args = ["--stage", "long", "--data", str(tmp_path), "--run", str(tmp_path), "--preset", "tiny"]
    for main in (lambda a: m4world(["train", *a]), train_module.main):
        calls.clear()
        assert main(args) == 0 and calls == [1]
        calls.clear()
        assert main([*args, "--default-heap"]) == 0 and calls == []


def test_ode_targets_of_a_batch_are_each_rows_own_under_guidance():
    """The guided ODE's unconditional forwards attend to their own row's history K/V, computed under
    dropped conditions: a batch of two gives what each row gives alone."""
    from dataclasses import replace

    from world_model.model import MultiViewDiT
    from world_model.student import StudentConfig
    from world_model.student.training import ode_targets

    cfg = get_preset("tiny").for_student()
    cfg = replace(cfg, sampler=replace(cfg.sampler, steps=4, camera_cfg_scale=3.0, lidar_apg_scale=3.0))
    torch.manual_seed(0)
    model = MultiViewDiT(cfg).eval()
    for p in model.parameters():  # adaLN-zero would make every velocity zero
        torch.nn.init.normal_(p, std=0.05)
    scfg, c = StudentConfig(), cfg.clip.chunk_frames
    f = scfg.prefix_frames + c
    cond = tiny_conditions(cfg, f + c, batch=2)
    gen = torch.Generator().manual_seed(1)
    history, noise = (
        torch.randn(2, *cfg.latent_shape(f), generator=gen),
        torch.randn(2, *cfg.latent_shape(c), generator=gen),
    )
    points, end = ode_targets(model, history, cond, noise, scfg)
    for row in range(2):
        alone = cond.apply(lambda _, v, row=row: v[row : row + 1])
        row_points, row_end = ode_targets(model, history[row : row + 1], alone, noise[row : row + 1], scfg)
        assert torch.allclose(end[row : row + 1], row_end, atol=1e-6), (row, (end[row] - row_end[0]).abs().max())
        assert torch.allclose(points[:, row : row + 1], row_points, atol=1e-6)


def test_steps_stage_teaches_the_long_student_fewer_steps_and_resumes_only_at_them(run, tmp_path):
    from world_model.student import StudentConfig

    data, mine = _run_through_ode(run, tmp_path)
    scfg = StudentConfig(long_frames=4)
    for stage in ("dmd", "long"):
        train_stage(stage, data, mine, stage_options(stage, preset="tiny", steps=1, batch_size=1, student=scfg), QUIET)

    def steps(total: int, denoising_steps: int | None) -> dict:
        options = stage_options(
            "steps",
            preset="tiny",
            steps=total,
            batch_size=1,
            ckpt_every=1,
            student=scfg,
            denoising_steps=denoising_steps,
        )
        return train_stage("steps", data, mine, options, QUIET)

    with pytest.raises(ValueError, match="fewer denoising steps than .*long/model's 4, not 4"):
        steps(1, 4)
    out = steps(2, None)  # half the long student's 4
    assert out["step"] == 2 and torch.isfinite(torch.tensor(out["final_loss"])).all()
    student, taught = load_student(mine / "steps" / "model")
    assert taught.num_steps == 2 and taught.streaming.refresh_steps == scfg.streaming.refresh_steps
    assert (mine / "steps" / "critic.safetensors").exists()
    with pytest.raises(ValueError, match="denoising_steps=2 up to step 2, not 1"):
        steps(3, 1)
    assert steps(3, 2)["resumed_from"] == 2

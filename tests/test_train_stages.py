"""Training stages end to end on a tiny synthetic dataset: export, resume, determinism, kill, NaN."""

import json
import math
import time
from dataclasses import replace

import numpy as np
import pytest
import torch
from safetensors.torch import load_file

from tests.model_fixtures import QUIET, kill_after_checkpoint, make_dataset
from world_model.bundle import CheckpointError, export_bundle
from world_model.model import get_preset, sample_latents
from world_model.model.conditions import Conditions
from world_model.model.config import with_layout
from world_model.model.dit import MultiViewDiT
from world_model.model.vae import SensorVAE
from world_model.student.config import StudentConfig
from world_model.train import (
    StageRuntime,
    TrainConfig,
    Trainer,
    TrainingDivergedError,
    load_latest,
    load_teacher,
    load_vae,
    stage_options,
    train_stage,
)
from world_model.train.checkpoint import export_weights, save_checkpoint
from world_model.train.data import cached_latents, encoder_digest, latent_cache_dir, load_clips
from world_model.train.trainer import LoopOptions
from world_model.train.vae_stage import LIDAR_LAG_SHARE, LIDAR_LATENT_LAG, latent_frames

QUIET_LOOP = LoopOptions(progress=False)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    return make_dataset(tmp_path_factory.mktemp("data"), get_preset("tiny"), lengths=(4, 3))


def test_vae_then_teacher_end_to_end_and_resume(dataset, tmp_path):
    run = tmp_path / "run"
    out = train_stage("vae", dataset, run, stage_options("vae", preset="tiny", steps=4, ckpt_every=2), QUIET)
    assert out["step"] == 4 and out["resumed_from"] is None
    assert {"camera_psnr_db", "lidar_range_mae_m", "lidar_return_accuracy"} <= set(out["metrics"])
    again = train_stage("vae", dataset, run, stage_options("vae", preset="tiny", steps=6, ckpt_every=2), QUIET)
    assert again["resumed_from"] == 4 and again["step"] == 6 and len(again["losses"]) == 2
    vae = load_vae(run / "vae" / "model")
    assert vae.latent_std.ne(1.0).any()  # latent normalization was fitted

    t1 = train_stage("teacher", dataset, run, stage_options("teacher", preset="tiny", steps=3, ckpt_every=1), QUIET)
    assert t1["step"] == 3 and all(torch.isfinite(torch.tensor(t1["losses"])))
    cache = sorted((run / "teacher" / "latents").glob("*.safetensors"))
    assert len(cache) == 2
    stamp = [p.stat().st_mtime_ns for p in cache]
    t2 = train_stage("teacher", dataset, run, stage_options("teacher", preset="tiny", steps=5, ckpt_every=1), QUIET)
    assert t2["resumed_from"] == 3 and t2["step"] == 5
    assert [p.stat().st_mtime_ns for p in cache] == stamp  # latents encoded once, then reused
    model = load_teacher(run / "teacher" / "model")
    # The exported teacher samples with its own conditions pipeline.
    from world_model.model import make_text_encoder
    from world_model.train.data import LatentWindows, load_clips

    clips = load_clips(dataset, model.cfg)
    lat = [torch.zeros(c.num_frames, *model.cfg.latent_shape(1)[1:]) for c in clips]
    _, arr = LatentWindows(clips, lat, model.cfg, make_text_encoder(model.cfg.text), None).window(0, 0, 2)
    out = sample_latents(model, Conditions.collate([arr]), torch.Generator().manual_seed(0))
    assert out.shape == (1, *model.cfg.latent_shape(2)) and torch.isfinite(out).all()


def test_decoder_stage_keeps_the_encoder_and_learns_to_draw_the_label_maps(tmp_path):
    cfg = with_layout(get_preset("tiny"), True)
    data = make_dataset(tmp_path / "data", cfg, lengths=(3,))
    run = tmp_path / "run"
    with pytest.raises(ValueError, match="--layout"):
        train_stage("decoder", data, run, stage_options("decoder", preset="tiny", steps=2), QUIET)
    train_stage("vae", data, run, stage_options("vae", preset="tiny", config=cfg, steps=3), QUIET)
    out = train_stage(
        "decoder", data, run, stage_options("decoder", preset="tiny", config=cfg, steps=4, ckpt_every=2), QUIET
    )
    assert out["step"] == 4 and {"camera_psnr_db", "lidar_range_mae_m"} <= set(out["metrics"])
    plain = load_vae(run / "vae" / "model")
    drawn = load_vae(run / "decoder" / "model")
    assert not plain.draws_labels and drawn.draws_labels and drawn.cfg.layout.decoder
    mine = drawn.state_dict()
    for key, value in plain.state_dict().items():  # the DiTs' latents stay the encoder's
        if not key.startswith("decoder."):
            assert torch.equal(mine[key], value), key
    assert any(mods.conv.weight.abs().sum() > 0 for mods in drawn.decoder.label_mods)  # it learned the maps
    assert any(mods.style.weight.abs().sum() > 0 for mods in drawn.decoder.label_mods)  # and the style


def _decoder_run(tmp_path):
    """A tiny layout run through its ``vae`` and ``decoder`` stages: (config, dataset, run)."""
    cfg = with_layout(get_preset("tiny"), True)
    data = make_dataset(tmp_path / "data", cfg, lengths=(5, 3))
    run = tmp_path / "run"
    train_stage("vae", data, run, stage_options("vae", preset="tiny", config=cfg, steps=2), QUIET)
    train_stage("decoder", data, run, stage_options("decoder", preset="tiny", config=cfg, steps=2), QUIET)
    return cfg, data, run


def _export_untrained_student(run, cfg) -> None:
    """An ``ode`` export of a freshly initialized student: what the rollout stages stream."""
    student_cfg = cfg.for_student()
    torch.manual_seed(0)
    meta = {"stage": "ode", "model_config": student_cfg.to_dict(), "student_config": StudentConfig().to_dict()}
    export_weights(run / "ode" / "model", MultiViewDiT(student_cfg).state_dict(), meta)


def test_rollout_decoder_stage_tunes_the_decoder_on_the_students_own_rollouts(tmp_path):
    cfg, data, run = _decoder_run(tmp_path)
    with pytest.raises(FileNotFoundError, match="--stage ode"):
        train_stage(
            "rollout_decoder", data, run, stage_options("rollout_decoder", preset="tiny", config=cfg, steps=2), QUIET
        )
    _export_untrained_student(run, cfg)

    out = train_stage(
        "rollout_decoder",
        data,
        run,
        stage_options("rollout_decoder", preset="tiny", config=cfg, steps=3, ckpt_every=1),
        QUIET,
    )
    assert out["step"] == 3 and out["rollout_clips"] == 2
    rollouts_file = run / "rollout_decoder" / "rollouts.pt"
    rollouts = torch.load(rollouts_file)
    plain = load_vae(run / "vae" / "model")
    clips = load_clips(data, cfg)
    assert [len(r) for r in rollouts] == [c.num_frames for c in clips]  # every frame of every clip
    for clip, rolled in zip(clips, rollouts, strict=True):
        encoded = cached_latents(clip, plain, latent_cache_dir(run), encoder_digest(plain)).to(rolled.dtype)
        assert torch.isfinite(rolled).all()
        assert not torch.equal(rolled[:1], encoded[:1])  # the first frame generated, as the env does
        assert not torch.equal(rolled[1:], encoded[1:])
    tuned, drawn = load_vae(run / "rollout_decoder" / "model"), load_vae(run / "decoder" / "model")
    assert tuned.cfg == drawn.cfg and tuned.draws_labels
    assert torch.equal(tuned.encoder.conv_in.weight, plain.encoder.conv_in.weight)  # the latents stay the encoder's
    assert not torch.equal(tuned.decoder.conv_out.weight, drawn.decoder.conv_out.weight)

    stamp = rollouts_file.stat().st_mtime_ns
    again = train_stage(
        "rollout_decoder",
        data,
        run,
        stage_options("rollout_decoder", preset="tiny", config=cfg, steps=4, ckpt_every=1),
        QUIET,
    )
    assert again["resumed_from"] == 3 and again["step"] == 4
    assert rollouts_file.stat().st_mtime_ns == stamp  # rolled out once, then reused
    bundle = export_bundle(run, tmp_path / "bundle")
    manifest = json.loads((bundle / "manifest.json").read_text())
    assert manifest["components"]["vae"]["stage"] == "rollout_decoder"
    assert manifest["model_config"]["layout"]["decoder"]


def test_the_lidar_view_is_decoded_from_a_lagged_latent_for_a_share_of_its_samples():
    cfg = get_preset("tiny")
    lidar = cfg.sensors.lidar_view
    lengths = [30, 5]
    picks = [(c, f, v) for c, n in enumerate(lengths) for f in range(n) for v in (0, lidar)] * 20
    frames = latent_frames(np.random.default_rng(0), picks, lengths, cfg)
    cams = [(f, g) for (_, f, v), g in zip(picks, frames, strict=True) if v != lidar]
    assert all(f == g for f, g in cams)  # a camera decodes its own frame
    lags = [(c, g - f) for (c, f, v), g in zip(picks, frames, strict=True) if v == lidar]
    assert all(abs(d) <= LIDAR_LATENT_LAG for _, d in lags)
    assert all(0 <= g < lengths[c] for (c, _, _), g in zip(picks, frames, strict=True))  # within its clip
    own = sum(d == 0 for _, d in lags) / len(lags)
    assert LIDAR_LAG_SHARE / 2 < 1 - own < LIDAR_LAG_SHARE + 0.05  # some lagged ones land on their own frame
    # as many draws whatever the views, so the training's random stream does not depend on them
    rng_a, rng_b = np.random.default_rng(1), np.random.default_rng(1)
    latent_frames(rng_a, picks, lengths, cfg)
    latent_frames(rng_b, [(c, f, 0) for c, f, _ in picks], lengths, cfg)
    assert rng_a.random() == rng_b.random()


def test_latent_cache_key_is_the_encoder_not_the_decoder():
    cfg = get_preset("tiny")
    torch.manual_seed(0)
    vae = SensorVAE(cfg)
    key = encoder_digest(vae)
    drawn = SensorVAE(with_layout(cfg, True))
    drawn.load_state_dict(vae.state_dict(), strict=False)
    with torch.no_grad():
        drawn.decoder.conv_out.weight.add_(1.0)
    assert encoder_digest(drawn) == key  # another decoder: the same latents
    with torch.no_grad():
        vae.latent_std.mul_(2.0)
    assert encoder_digest(vae) != key  # another normalization: other latents
    with torch.no_grad():
        vae.latent_std.div_(2.0)
        vae.encoder.conv_in.weight.add_(1e-3)
    assert encoder_digest(vae) != key


def test_resume_gives_the_same_state_as_uninterrupted(dataset, tmp_path):
    straight = train_stage(
        "vae", dataset, tmp_path / "a", stage_options("vae", preset="tiny", steps=4, ckpt_every=2), QUIET
    )
    train_stage("vae", dataset, tmp_path / "b", stage_options("vae", preset="tiny", steps=2, ckpt_every=2), QUIET)
    resumed = train_stage(
        "vae", dataset, tmp_path / "b", stage_options("vae", preset="tiny", steps=4, ckpt_every=2), QUIET
    )
    assert resumed["losses"] == straight["losses"][2:]
    a = load_file(str(tmp_path / "a" / "vae" / "checkpoints" / "step_00000004" / "model.safetensors"))
    b = load_file(str(tmp_path / "b" / "vae" / "checkpoints" / "step_00000004" / "model.safetensors"))
    assert all(torch.equal(a[k], b[k]) for k in a)


def test_killed_run_resumes_from_last_checkpoint(dataset, tmp_path):
    run = tmp_path / "run"
    args = ["--stage", "vae", "--data", str(dataset), "--run", str(run), "--preset", "tiny"]
    kill_after_checkpoint(
        [*args, "--steps", "100000", "--ckpt-every", "2", "--no-progress"], run / "vae" / "checkpoints"
    )
    ck = load_latest(run / "vae" / "checkpoints")
    assert ck is not None and ck.step >= 4
    out = train_stage("vae", dataset, run, stage_options("vae", preset="tiny", steps=ck.step + 2, ckpt_every=2), QUIET)
    assert out["resumed_from"] == ck.step and out["step"] == ck.step + 2


def test_nan_loss_stops_with_clear_error_and_keeps_last_checkpoint(tmp_path):
    model = torch.nn.Linear(2, 1)
    trainer = Trainer(tmp_path, model, TrainConfig(steps=10, batch_size=1, lr=1e-2, ckpt_every=1), {}, loop=QUIET_LOOP)

    def step(tr):
        loss = model(torch.ones(1, 2)).sum() ** 2
        return (loss * float("nan") if tr.step == 3 else loss), 1

    with pytest.raises(TrainingDivergedError, match="loss is nan at step 4"):
        trainer.run(step, "toy")
    assert load_latest(tmp_path / "checkpoints").step == 3


def test_progress_file_follows_the_run(tmp_path):
    model = torch.nn.Linear(2, 1)
    trainer = Trainer(tmp_path, model, TrainConfig(steps=4, batch_size=1, lr=1e-2, ckpt_every=2), {}, loop=QUIET_LOOP)
    trainer.run(lambda tr: (model(torch.ones(1, 2)).sum() ** 2, 1), "toy")
    report = json.loads((tmp_path / "progress.json").read_text())
    assert report["stage"] == "toy" and report["step"] == report["total_steps"] == 4
    assert report["eta_s"] == 0 and report["steps_per_s"] > 0 and math.isfinite(report["loss"])


def test_half_written_checkpoint_is_ignored(tmp_path):
    root = tmp_path / "ck"
    save_checkpoint(root, 1, {"model": {"w": torch.ones(2)}}, {"x": 1}, {"a": 1})
    (root / ".tmp-step_00000002-999").mkdir()  # a writer killed mid-save
    (root / ".tmp-step_00000002-999" / "model.safetensors").write_bytes(b"garbage")
    ck = load_latest(root)
    assert ck.step == 1 and torch.equal(ck.tensors["model"]["w"], torch.ones(2))
    save_checkpoint(root, 2, {"model": {"w": torch.zeros(2)}}, {"x": 2}, {"a": 2}, keep=1)
    assert sorted(p.name for p in root.iterdir()) == ["latest.json", "step_00000002"]


def test_stage_errors_are_actionable(dataset, tmp_path):
    with pytest.raises(FileNotFoundError, match="run --stage vae"):
        train_stage("teacher", dataset, tmp_path / "run", stage_options("teacher", preset="tiny", steps=1), QUIET)
    with pytest.raises(ValueError, match="unknown stage"):
        train_stage("student", dataset, tmp_path / "run", stage_options("student", preset="tiny", steps=1), QUIET)
    with pytest.raises(ValueError, match="expects"):
        train_stage("vae", dataset, tmp_path / "run2", stage_options("vae", preset="default", steps=1), QUIET)
    with pytest.raises(ValueError, match="--stage dmd takes StudentStageOptions, got StageOptions"):
        train_stage("dmd", dataset, tmp_path / "run3", stage_options("vae", preset="tiny", steps=1), QUIET)
    with pytest.raises(ValueError, match="--lora-rank is a setting of --stage lora, not of 'vae'"):
        stage_options("vae", preset="tiny", rank=4)
    assert not (tmp_path / "run3").exists()  # refused before anything is written


def test_vae_stage_resumes_after_a_dit_only_config_change(dataset, tmp_path):
    from dataclasses import replace

    tiny = get_preset("tiny")
    run = tmp_path / "run"
    train_stage("vae", dataset, run, stage_options("vae", config=tiny, steps=2, ckpt_every=1), QUIET)
    wider_dit = replace(tiny, dit=replace(tiny.dit, heads=1))  # the VAE does not depend on the DiT
    out = train_stage("vae", dataset, run, stage_options("vae", config=wider_dit, steps=3, ckpt_every=1), QUIET)
    assert out["resumed_from"] == 2 and out["step"] == 3
    other_vae = replace(tiny, vae=replace(tiny.vae, kl_weight=tiny.vae.kl_weight * 2))
    with pytest.raises(ValueError, match="different config"):
        train_stage("vae", dataset, run, stage_options("vae", config=other_vae, steps=4), QUIET)
    train_stage("teacher", dataset, run, stage_options("teacher", config=tiny, steps=1), QUIET)
    with pytest.raises(ValueError, match="different config"):  # the teacher depends on everything
        train_stage("teacher", dataset, run, stage_options("teacher", config=wider_dit, steps=2), QUIET)


def test_expensive_stages_have_their_own_default_step_counts():
    from world_model.train.stages import DEFAULT_STEPS, _train_config

    cfg = get_preset("default")
    teacher = _train_config("teacher", cfg, stage_options("teacher")).steps
    assert teacher == DEFAULT_STEPS["default"]
    assert _train_config("dmd", cfg, stage_options("dmd")).steps < teacher
    assert _train_config("dmd", cfg, stage_options("dmd", steps=7)).steps == 7  # explicit steps win


def test_latent_cache_is_keyed_by_vae_and_clip(dataset, tmp_path):
    from dataclasses import replace

    from world_model.data import iter_clips
    from world_model.model import SensorVAE
    from world_model.train.data import cached_latents

    clip = next(iter(iter_clips(dataset)))
    vae = SensorVAE(get_preset("tiny")).eval()
    calls = []
    encode = vae.encode_frames
    vae.encode_frames = lambda *a: calls.append(1) or encode(*a)
    first = cached_latents(clip, vae, tmp_path, "vae-a")
    assert torch.equal(cached_latents(clip, vae, tmp_path, "vae-a"), first) and len(calls) == 1  # reused
    cached_latents(clip, vae, tmp_path, "vae-b")  # another VAE: re-encoded
    other = replace(clip, meta={**clip.meta, "seed": -1})  # same name, another recording
    cached_latents(other, vae, tmp_path, "vae-b")
    assert len(calls) == 3


def test_train_dtype_reaches_the_stage_models_not_the_checkpoint(dataset, tmp_path):
    with pytest.raises(ValueError, match="float16"):
        train_stage(
            "teacher",
            dataset,
            tmp_path / "none",
            stage_options("teacher", preset="tiny", steps=1),
            StageRuntime(dtype="float16"),
        )
    assert not (tmp_path / "none").exists()  # refused before anything is written
    vae_run = tmp_path / "vae_run"
    train_stage("vae", dataset, vae_run, stage_options("vae", preset="tiny", steps=2), QUIET)
    losses = {}
    for dtype in ("float32", "bfloat16"):  # the tiny preset's config says float32
        run = tmp_path / dtype
        (run / "vae").mkdir(parents=True)
        for f in (vae_run / "vae").glob("model.*"):
            (run / "vae" / f.name).write_bytes(f.read_bytes())
        out = train_stage(
            "teacher",
            dataset,
            run,
            stage_options("teacher", preset="tiny", steps=2),
            StageRuntime(progress=False, dtype=dtype),
        )
        losses[dtype] = out["losses"]
        meta = json.loads((run / "teacher" / "model.json").read_text())
        assert meta["model_config"]["dit"]["autocast_bf16"] is False  # the preset's: dtype is a run-time choice
    assert losses["float32"] != losses["bfloat16"]  # bf16 autocast reached the teacher's forwards


def test_a_time_limit_stops_the_run_checkpointed_and_a_rerun_resumes_to_its_steps(tmp_path):
    model = torch.nn.Linear(2, 1)
    tcfg = TrainConfig(steps=50, batch_size=1, lr=1e-2, ckpt_every=100)

    def slow_step(tr):
        time.sleep(0.02)
        return model(torch.ones(1, 2)).sum() ** 2, 1

    loop = LoopOptions(progress=False, deadline=time.perf_counter() + 0.05)
    out = Trainer(tmp_path, model, tcfg, {}, loop=loop).run(slow_step, "toy")
    assert out["stopped_by_time_limit"] and 1 <= out["step"] < 50
    assert load_latest(tmp_path / "checkpoints").step == out["step"]  # saved where it stopped
    again = Trainer(tmp_path, model, tcfg, {}, loop=QUIET_LOOP).run(slow_step, "toy")
    assert again["resumed_from"] == out["step"] and again["step"] == 50
    assert not again["stopped_by_time_limit"]


def test_a_stage_time_limit_counts_its_setup_and_still_takes_one_step(dataset, tmp_path, monkeypatch):
    from world_model.train import stages

    spec = stages.REGISTRY["vae"]

    def slow_setup_then_train(run, **kw):
        time.sleep(0.3)  # a cache or rollouts built before the first step
        return spec.train(run, **kw)

    monkeypatch.setitem(stages.REGISTRY, "vae", replace(spec, train=slow_setup_then_train))
    out = train_stage(
        "vae",
        dataset,
        tmp_path / "run",
        stage_options("vae", preset="tiny", steps=50),
        StageRuntime(progress=False, time_limit_s=0.2),
    )
    assert out["stopped_by_time_limit"] and out["step"] == 1  # the setup used the time: one step, checkpointed
    assert load_latest(tmp_path / "run" / "vae" / "checkpoints").step == 1


def test_range_head_stage_trains_the_head_alone_and_the_bundle_finishes_the_lidar_with_it(tmp_path):
    cfg, data, run = _decoder_run(tmp_path)
    _export_untrained_student(run, cfg)

    out = train_stage(
        "range_head", data, run, stage_options("range_head", preset="tiny", config=cfg, steps=3, ckpt_every=1), QUIET
    )
    assert out["step"] == 3 and out["rollout_clips"] == 2
    assert {"stretched_object_median_m", "head_object_median_m"} <= set(out["metrics"])
    headed, drawn = load_vae(run / "range_head" / "model"), load_vae(run / "decoder" / "model")
    assert headed.cfg.layout.range_head and not drawn.cfg.layout.range_head
    head_free = {k: v for k, v in headed.state_dict().items() if not k.startswith("range_head.")}
    assert head_free.keys() == drawn.state_dict().keys()
    assert all(torch.equal(v, drawn.state_dict()[k]) for k, v in head_free.items())  # only the head trained
    assert headed.range_head.net[-1].weight.abs().sum() > 0  # it moved from its zero start

    again = train_stage(
        "range_head", data, run, stage_options("range_head", preset="tiny", config=cfg, steps=4, ckpt_every=1), QUIET
    )
    assert again["resumed_from"] == 3 and again["step"] == 4
    bundle = export_bundle(run, tmp_path / "bundle")
    manifest = json.loads((bundle / "manifest.json").read_text())
    assert manifest["components"]["vae"]["stage"] == "range_head"
    assert manifest["model_config"]["layout"]["decoder"] and manifest["model_config"]["layout"]["range_head"]
    # the decoder trained on: the head finishes the one it was trained on, not this one
    train_stage("decoder", data, run, stage_options("decoder", preset="tiny", config=cfg, steps=3), QUIET)
    with pytest.raises(CheckpointError, match="train --stage range_head again"):
        export_bundle(run, tmp_path / "stale")

"""A student shallower than its teacher (``dit.student_depth``): initialization, stages, bundle."""

import os
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import pytest
import torch

from world_model.bundle import export_bundle
from world_model.model import MultiViewDiT, get_preset
from world_model.model.config import with_student_settings
from world_model.model.reference import reference_model_config
from world_model.rollout.runtime import load_world_model
from world_model.student.init import nearest, student_from_teacher, teacher_blocks
from world_model.train import stage_options, train_stage
from world_model.train.exports import load_student

from .model_fixtures import QUIET, make_dataset, perturbed, tiny_conditions

SRC = Path(__file__).resolve().parents[1]


def _cfg(depth: int, student_depth: int | None):
    cfg = get_preset("tiny")
    return replace(cfg, dit=replace(cfg.dit, depth=depth, student_depth=student_depth))


def test_teacher_blocks_are_evenly_spaced_with_first_and_last():
    assert teacher_blocks(10, 6) == [0, 2, 4, 5, 7, 9]
    assert teacher_blocks(10, 10) == list(range(10))
    assert teacher_blocks(10, 2) == [0, 9]
    assert teacher_blocks(10, 1) == [9]
    assert nearest(2, (1, 3)) == 1 and nearest(7, (4, 9)) == 9
    with pytest.raises(ValueError, match="student depth"):
        teacher_blocks(4, 5)


def test_config_rejects_a_student_deeper_than_the_teacher():
    with pytest.raises(ValueError, match="student_depth"):
        _cfg(2, 3)
    cfg = _cfg(5, 3)
    assert cfg.for_student().dit.depth == 3 and cfg.for_student().for_student() == cfg.for_student()
    assert _cfg(2, None).for_student().dit.depth == 2


def test_full_depth_student_is_the_teacher():
    teacher = perturbed(MultiViewDiT(get_preset("tiny")).eval())
    student = student_from_teacher(teacher).eval()
    cond = tiny_conditions(teacher.cfg, 2)
    x = torch.randn(1, *teacher.cfg.latent_shape(2))
    t = torch.rand(1, 2)
    with torch.no_grad():
        assert torch.equal(student(x, t, student.tokenize(cond)), teacher(x, t, teacher.tokenize(cond)))


def test_shallow_student_copies_teacher_blocks_and_nearest_cross_view():
    # Teacher: 5 blocks, cross-view in blocks 1 and 3; student: 3 blocks = teacher 0, 2, 4, and its
    # cross-view block 1 (teacher block 2 has none) takes teacher block 1's, the nearest.
    teacher = perturbed(MultiViewDiT(_cfg(5, 3)))
    assert teacher.cfg.cross_view_blocks == (1, 3)
    student = student_from_teacher(teacher)
    assert student.cfg.dit.depth == 3 and student.cfg.cross_view_blocks == (1,)
    t_state, s_state = teacher.state_dict(), student.state_dict()
    for key, value in s_state.items():
        if not key.startswith("blocks."):
            assert torch.equal(value, t_state[key]), key
            continue
        i, name = key.split(".", 2)[1:]
        src = 1 if name.startswith(("cross_view.", "norm_view.")) else [0, 2, 4][int(i)]
        assert torch.equal(value, t_state[f"blocks.{src}.{name}"]), key
    with pytest.raises(ValueError, match="apart from the student settings"):
        student_from_teacher(teacher, replace(_cfg(5, 3), name="other"))


def test_with_student_settings_replaces_only_what_is_given():
    cfg = _cfg(5, None)
    assert with_student_settings(cfg) == cfg
    new = with_student_settings(cfg, student_depth=3, context_frames=6)
    assert (
        new.dit.student_depth == 3 and new.clip.context_frames == 6 and new.teacher_settings() == cfg.teacher_settings()
    )
    with pytest.raises(ValueError, match="context_frames"):
        with_student_settings(cfg, context_frames=0)
    with pytest.raises(ValueError, match="student_depth"):
        with_student_settings(cfg, student_depth=6)


def test_student_settings_do_not_touch_the_teacher():
    a = _cfg(5, 3)
    b = replace(a, clip=replace(a.clip, context_frames=7), dit=replace(a.dit, student_depth=2))
    assert a != b and a.teacher_settings() == b.teacher_settings()
    assert a.shared_settings() == b.for_student().shared_settings() == reference_model_config(a).shared_settings()
    student = student_from_teacher(MultiViewDiT(a), b)
    assert student.cfg == b.for_student() and student.cfg.dit.depth == 2


def test_shallow_student_through_every_stage_and_the_bundle(tmp_path):
    # The teacher was trained before the student's settings changed (depth and window).
    first = _cfg(2, None)
    cfg = replace(_cfg(2, 1), clip=replace(first.clip, context_frames=first.clip.context_frames + 1))
    data = make_dataset(tmp_path / "data", cfg, lengths=(4, 3))
    run = tmp_path / "run"
    for stage in ("vae", "teacher", "ode", "dmd", "long", "reference"):
        config = first if stage in ("vae", "teacher") else cfg
        train_stage(stage, data, run, stage_options(stage, steps=1, batch_size=1, ckpt_every=1, config=config), QUIET)
        if stage == "teacher":  # tf from the CLI: its flags set the student-only settings
            cmd = [sys.executable, "-m", "world_model.train", "--stage", "tf", "--data", str(data), "--run", str(run)]
            cmd += ["--preset", "tiny", "--steps", "1", "--batch-size", "1", "--no-progress", "--student-depth", "1"]
            cmd += ["--context-frames", str(cfg.clip.context_frames)]
            env = {**os.environ, "PYTHONPATH": str(SRC), "OMP_NUM_THREADS": "1"}
            subprocess.run(cmd, env=env, check=True, capture_output=True, timeout=300)
    student, _ = load_student(run / "long" / "model")
    assert student.cfg == cfg.for_student() and student.cfg.dit.depth == 1

    wm = load_world_model(export_bundle(run, tmp_path / "bundle"))
    assert len(wm.student.blocks) == 1 and len(wm.reference.blocks) == 2
    assert wm.reference.cfg.dit.in_channels_extra > 0

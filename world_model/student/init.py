"""The causal student's starting weights: the teacher's, with fewer blocks when the preset asks.

Every DiT forward of an env step is the student's, so the student may be shallower than
the teacher (``DitConfig.student_depth``). It starts from the teacher's embeddings, head and an
evenly spaced subset of its blocks (first and last always kept) — the usual layer-dropping
initialization of compressed diffusion models — and the ``tf`` stage then adapts it. Cross-view
attention sits at fixed block positions (every ``cross_view_every``-th block): a student block
that carries one takes its cross-view weights from the teacher's cross-view block nearest to the
teacher block it copies, so every student parameter starts from a trained teacher parameter.
With ``student_depth == depth`` the student is exactly the teacher.
"""

from __future__ import annotations

import torch

from world_model.model.config import ModelConfig
from world_model.model.dit import MultiViewDiT

CROSS_VIEW_PREFIXES = ("cross_view.", "norm_view.")  # a block's optional cross-view submodules


def teacher_blocks(teacher_depth: int, student_depth: int) -> list[int]:
    """Teacher block copied into each student block: evenly spaced, first and last included."""
    if not 1 <= student_depth <= teacher_depth:
        raise ValueError(f"student depth must be in [1, {teacher_depth}], got {student_depth}")
    if student_depth == 1:
        return [teacher_depth - 1]
    step = (teacher_depth - 1) / (student_depth - 1)
    return [round(i * step) for i in range(student_depth)]


def nearest(index: int, candidates: tuple[int, ...]) -> int:
    """The candidate closest to ``index`` (the earlier one on a tie)."""
    if not candidates:
        raise ValueError("the teacher has no cross-view block to copy from")
    return min(candidates, key=lambda c: (abs(c - index), c))


def student_from_teacher(teacher: MultiViewDiT, cfg: ModelConfig | None = None) -> MultiViewDiT:
    """A student of config ``cfg`` (default ``teacher.cfg.for_student()``) initialized from ``teacher``.

    ``cfg`` must share the teacher's settings (:meth:`ModelConfig.shared_settings`): only the DiT
    depth and the student-only settings (e.g. ``clip.context_frames``) may differ.
    """
    tcfg = teacher.cfg
    cfg = (cfg or tcfg).for_student()
    if cfg.shared_settings() != tcfg.shared_settings():
        raise ValueError("the student's config must equal the teacher's apart from the student settings")
    source = teacher.state_dict()
    picks = teacher_blocks(tcfg.dit.depth, cfg.dit.depth)
    student = MultiViewDiT(cfg)
    state: dict[str, torch.Tensor] = {}
    for key in student.state_dict():  # every student parameter is taken from one teacher parameter
        if not key.startswith("blocks."):
            state[key] = source[key]
            continue
        _, i, name = key.split(".", 2)
        j = picks[int(i)]
        if name.startswith(CROSS_VIEW_PREFIXES):
            j = nearest(j, tcfg.cross_view_blocks)
        state[key] = source[f"blocks.{j}.{name}"]
    student.load_state_dict(state)
    return student.to(next(teacher.parameters()).dtype)

"""The causal student's starting weights: the teacher's, with fewer blocks when the preset asks.

The env runs the student's 4 denoising forwards per step, so the student may be shallower than
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
    state: dict[str, torch.Tensor] = {k: v for k, v in source.items() if not k.startswith("blocks.")}
    for i, j in enumerate(picks):
        view_src = nearest(j, tcfg.cross_view_blocks) if i in cfg.cross_view_blocks else None
        for key, value in source.items():
            if not key.startswith(f"blocks.{j}."):
                continue
            name = key.removeprefix(f"blocks.{j}.")
            if not name.startswith(CROSS_VIEW_PREFIXES):
                state[f"blocks.{i}.{name}"] = value
        if view_src is not None:
            for key, value in source.items():
                name = key.removeprefix(f"blocks.{view_src}.")
                if key.startswith(f"blocks.{view_src}.") and name.startswith(CROSS_VIEW_PREFIXES):
                    state[f"blocks.{i}.{name}"] = value
    student = MultiViewDiT(cfg)
    student.load_state_dict(state)  # strict: every student parameter came from the teacher
    return student.to(next(teacher.parameters()).dtype)

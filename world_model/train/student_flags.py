"""The training CLI's model flags (the student's, the DiTs' precision, the allocator), used by
:mod:`world_model.train.cli`.

Import-light (no torch) so that building the ``m4world`` parser stays fast.
"""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

from world_model import cli_args
from world_model.precision import DTYPES
from world_model.train.heap import retain_freed_memory

if TYPE_CHECKING:
    from world_model.model.config import ModelConfig
    from world_model.student.config import StudentConfig


BASE_HELP = (  # --base of the training CLI: lora
    "lora: the model to adapt (default RUN/teacher/model): an exported DiT (e.g. RUN/long/model or "
    "RUN/reference/model), or a checkpoint bundle, whose student is adapted in the bundle's own VAE latents "
    "(e.g. the shipped world_model/checkpoints/default: no training run needed; "
    "BUNDLE/reference.safetensors for its reference model)"
)


def add_lora_flags(p: argparse.ArgumentParser | argparse._ArgumentGroup) -> None:
    """The LoRA stage's objective flags (``--stage lora``)."""
    p.add_argument(
        "--lora-box-weight",
        type=cli_args.non_negative_float,
        default=0.0,
        help="lora: extra flow-loss weight on the latent cells inside the rare object's projected boxes "
        "(default 0 = the plain mean; e.g. 9 weighs them 10x); a run resumes only with the same value",
    )
    p.add_argument(
        "--lora-rank",
        type=cli_args.positive_int,
        default=None,
        help="lora: rank of the adapter's low-rank updates (default: world_model.lora.LoraConfig's, 8); its scale "
        "stays 1 (alpha = rank); a run resumes only with the same value",
    )


def add_student_flags(p: argparse.ArgumentParser | argparse._ArgumentGroup, long_frames: bool = False) -> None:
    """Add the student flags (and ``--long-frames`` when asked) to ``p``; every default is None,
    meaning "the preset's" or "the stage's"."""
    p.add_argument(
        "--student-depth",
        type=cli_args.positive_int,
        default=None,
        help="blocks of the causal student (default: the preset's dit.student_depth, else the teacher's); "
        "starts from evenly spaced teacher blocks; give it to every student stage of the run",
    )
    p.add_argument(
        "--context-frames",
        type=cli_args.positive_int,
        default=None,
        help="the student's rolling window (default: the preset's)",
    )
    p.add_argument(
        "--dtype",
        choices=DTYPES,
        default="auto",
        help="the DiTs' autocast while training (default auto: bf16 when the preset asks for it and this CPU "
        "multiplies bf16 faster than float32, else float32; checkpoints do not record it)",
    )
    p.add_argument(
        "--default-heap",
        action="store_true",
        help="leave glibc's allocator as it is (default: keep freed memory in the heap, world_model.train.heap, "
        "which spares eager CPU training most of its page faults)",
    )
    p.add_argument(
        "--vae-object-weight",
        type=cli_args.non_negative_float,
        default=None,
        help="vae stage: extra L1 weight on camera pixels inside objects' boxes (default: the preset's "
        "vae.object_loss_weight; 0 = plain L1)",
    )
    p.add_argument(
        "--layout",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="pixel-aligned layout conditioning: the DiT also reads each view's rasterized road, lane "
        "lines and object boxes as input channels (default: the preset's layout.enabled); every "
        "stage of one run must agree",
    )
    if long_frames:
        p.add_argument(
            "--long-frames", type=cli_args.positive_int, default=None, help="long stage: frames per self-rollout (600)"
        )
    p.add_argument(
        "--long-skip-chunks",
        type=cli_args.non_negative_int,
        default=None,
        help="long stage: chunks a self-rollout advances untrained between trained clips (default 0: every "
        "clip is trained); lets a short tuning run reach a rollout's late frames",
    )
    p.add_argument(
        "--denoising-steps",
        type=cli_args.positive_int,
        default=None,
        help="student stages: the denoising steps the student streams at while trained (default: 4; the "
        "steps stage: half its predecessor's)",
    )
    p.add_argument(
        "--denoise-loss-prob",
        type=cli_args.probability,
        default=None,
        help="dmd and long stages: probability of adding the supervised denoising term on real latents "
        "to a step (default 0.1)",
    )
    p.add_argument(
        "--dmd-guidance-scale",
        type=cli_args.positive_float,
        default=None,
        help="dmd and long stages: guidance scale of the DMD real score, camera CFG and LiDAR APG alike "
        "(default: the teacher's sampler scales; 1 = unguided)",
    )


def student_config(args: argparse.Namespace) -> StudentConfig | None:
    """The :class:`StudentConfig` of the parsed flags: None when none is given (every stage keeps its
    defaults), else the defaults with the given fields replaced."""
    from world_model.student.config import StudentConfig

    names = (
        "long_frames",
        "long_skip_chunks",
        "denoise_loss_prob",
        "dmd_guidance_scale",
    )
    given = {name: getattr(args, name) for name in names if getattr(args, name, None) is not None}
    return StudentConfig(**given) if given else None


def stage_config(args: argparse.Namespace, preset: ModelConfig) -> ModelConfig:
    """``preset`` with the config flags applied: student depth, context window, VAE object weight,
    layout conditioning."""
    from world_model.model.config import with_layout, with_student_settings, with_vae_object_weight

    cfg = with_student_settings(preset, args.student_depth, args.context_frames)
    return with_layout(with_vae_object_weight(cfg, args.vae_object_weight), args.layout)


def apply_heap_flag(args: argparse.Namespace) -> None:
    """The process-wide allocator setting of ``--default-heap`` (training on CPU; see world_model.train.heap)."""
    if not args.default_heap:
        retain_freed_memory()

"""The one training command line: ``python -m world_model.train`` and ``m4world train`` build the
same parser (:func:`add_train_arguments`) and run the same entry (:func:`run_train`).

Import-light (no torch until a command runs) so that building the ``m4world`` parser stays fast.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from world_model import cli_args
from world_model.train.student_flags import BASE_HELP, add_lora_flags, add_student_flags

if TYPE_CHECKING:
    from world_model.model.config import ModelConfig

DESCRIPTION = "Train world-model stages into a run directory (resumable: rerun the same command)."
EPILOG = """\
stages: vae, decoder, teacher, tf, ode, dmd, long, steps, shallow, reference, first_frame, rollout_decoder,
range_head, camera_decoder, lora
(each writes RUN/<stage>/; lora RUN/lora/CASE/); first_frame teaches a copy of the reference model to
draw reset()'s first frame in one step; decoder (with --layout) fine-tunes the VAE's decoder to draw the
layout's label maps, rollout_decoder fine-tunes it again on the trained student's own rollouts,
range_head trains the VAE's range head (the LiDAR at the range map's resolution) on them; steps teaches
the long student to stream at fewer denoising steps (--denoising-steps; a faster env), shallow distils the
finished student into --student-depth blocks (a faster env again).
--all trains vae -> [decoder] -> teacher -> tf -> ode -> dmd -> long -> reference -> first_frame ->
[rollout_decoder -> range_head]
at the preset's steps, then writes
RUN/bundle. Multi-GPU: torchrun --nproc-per-node N -m world_model.train -- FLAGS (data parallel;
--batch-size is the global batch, a multiple of N; the "--" keeps torchrun from reading --run as its
--run-path). Rerunning the same command resumes from each stage's last checkpoint.
"""
# --all; the decoder stages with --layout
PIPELINE = (
    "vae",
    "decoder",
    "teacher",
    "tf",
    "ode",
    "dmd",
    "long",
    "reference",
    "first_frame",
    "rollout_decoder",
    "range_head",
    "camera_decoder",
)
DECODER_STAGES = ("decoder", "rollout_decoder", "range_head", "camera_decoder")


def add_train_arguments(p: argparse.ArgumentParser) -> None:
    """Every flag of the training command."""
    p.add_argument("--stage", default=None, help="the stage to train (see below)")
    p.add_argument("--all", action="store_true", help="train every stage of the chain, then write RUN/bundle")
    p.add_argument("--data", default="data/train", help="dataset directory (m4world record output)")
    p.add_argument("--run", default="runs/default", help="run directory; each stage writes RUN/<stage>/")
    p.add_argument("--preset", default="default", help="model preset: tiny, default or gpu")
    p.add_argument(
        "--geometry-only",
        action="store_true",
        help="the evaluation's baseline: object tokens without image/text descriptions (use its own --run; "
        "copy RUN/vae and RUN/teacher/latents of the full run into it to share the autoencoder)",
    )
    p.add_argument(
        "--steps", type=cli_args.positive_int, default=None, help="total optimizer steps of --stage (default: preset's)"
    )
    p.add_argument("--batch-size", type=cli_args.positive_int, default=None, help="global batch (default: the stage's)")
    p.add_argument("--lr", type=cli_args.positive_float, default=None)
    p.add_argument(
        "--ckpt-every",
        type=cli_args.positive_int,
        default=None,
        help="steps between checkpoints (default: the stage's)",
    )
    p.add_argument("--seed", type=cli_args.seed, default=0)
    p.add_argument("--no-progress", action="store_true")
    p.add_argument(
        "--device",
        default="auto",
        help="auto (a CUDA GPU when there is one, else the CPU), cpu, cuda or cuda:N; under torchrun each "
        "rank takes cuda:LOCAL_RANK",
    )
    p.add_argument("--compile", action="store_true", help="torch.compile the trained networks")
    model = p.add_argument_group("model and student stages (tf, ode, dmd, long)")
    add_student_flags(model, long_frames=True)
    lora = p.add_argument_group("--stage lora")
    lora.add_argument("--case", default=None, help="adapter name = rare object category (e.g. tree_truck)")
    lora.add_argument("--case-data", default=None, help="dataset of rare-case clips (default: from --data)")
    lora.add_argument("--case-clips", default=None, help="comma-separated rare clip names (overrides the category)")
    lora.add_argument("--base", default=None, help=BASE_HELP)
    add_lora_flags(lora)


def build_parser(prog: str = "python -m world_model.train") -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=prog, description=DESCRIPTION, epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    add_train_arguments(p)
    return p


def run_train(args: argparse.Namespace) -> int:
    """Train what ``args`` asks (one stage, or ``--all`` and a bundle); prints each stage's summary."""
    from world_model.model.config import get_preset
    from world_model.train import stages
    from world_model.train.device import close_place, init_place
    from world_model.train.run import StageRuntime
    from world_model.train.student_flags import apply_heap_flag, stage_config

    if args.all == (args.stage is not None):
        raise ValueError(f"give exactly one of --stage (one of {', '.join(stages.STAGES)}) or --all")
    cli_args.check_out(args.run, "folder", "--run")
    apply_heap_flag(args)
    config = stage_config(args, get_preset(args.preset, geometry_only=args.geometry_only))
    place = init_place(args.device)
    runtime = StageRuntime(progress=not args.no_progress, dtype=args.dtype, place=place, compile_model=args.compile)
    try:
        # Each stage resumes from its own last checkpoint, and a finished stage returns at once:
        # rerunning the same command after an interruption loses nothing.
        chain = [s for s in PIPELINE if s not in DECODER_STAGES or config.layout.decoder]
        for stage in chain if args.all else (args.stage,):
            options = stages.stage_options(stage, **chain_settings(args, config))
            summary = stages.train_stage(stage, args.data, args.run, options, runtime)
            summary.pop("losses", None)
            if place.is_main:
                print(json.dumps(summary, indent=1, default=float))
        if args.all and place.is_main:
            from world_model.bundle import export_bundle

            print(f"bundle: {export_bundle(args.run, Path(args.run) / 'bundle')}")
    finally:
        close_place(place)
    return 0


def chain_settings(args: argparse.Namespace, config: ModelConfig) -> dict[str, object]:
    """Every stage option the command line sets (:func:`world_model.train.stages.stage_options`
    keeps a stage's own): ``--all`` trains each stage at the preset's steps; without a student flag
    the student stages keep their default student config."""
    from world_model.train.student_flags import student_config

    student = student_config(args)
    settings = {
        "preset": args.preset,
        "config": config,
        "steps": None if args.all else args.steps,
        "batch_size": args.batch_size,
        "lr": args.lr,
        "ckpt_every": args.ckpt_every,
        "seed": args.seed,
        "case": args.case,
        "case_data": args.case_data,
        "case_clips": args.case_clips.split(",") if args.case_clips else None,
        "base": args.base,
        "box_weight": args.lora_box_weight,
        "rank": args.lora_rank,
        "denoising_steps": args.denoising_steps,
    }
    return settings if student is None else {**settings, "student": student}


def main(argv: list[str] | None = None) -> int:
    """``python -m world_model.train``: exit status 2 with one line on a user error."""
    from world_model.train.trainer import TrainingDivergedError

    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["--"]:  # torchrun ... -m world_model.train -- FLAGS: the "--" ends torchrun's options
        argv = argv[1:]
    args = build_parser().parse_args(argv)
    try:
        return run_train(args)
    except (FileNotFoundError, ValueError, KeyError, TrainingDivergedError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2

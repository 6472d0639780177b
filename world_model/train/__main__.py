"""CLI: train one stage of the world model.

``python -m world_model.train --stage STAGE --data DIR --run RUN --preset tiny|default [--steps N]``
with STAGE one of vae, teacher, tf, ode, dmd, long, compress, reference, lora (for long and compress:
``--long-frames N``, ``--long-skip-chunks K``).

``--stage compress [--base BUNDLE_OR_STUDENT] [--student-depth D] [--context-frames W]`` distills a
trained student (default RUN/long/model) into RUN/compress/ on its own rollouts.

``--stage lora --case NAME [--case-data DIR] [--base PATH] [--lora-box-weight W]`` trains one long-tail
adapter into RUN/lora/NAME/.

Rerunning the same command resumes from the stage's last checkpoint.
"""

from __future__ import annotations

import argparse
import json
import sys

from world_model.model.config import PRESETS, get_preset
from world_model.student_flags import (
    BASE_HELP,
    add_lora_flags,
    add_student_flags,
    apply_heap_flag,
    stage_config,
    student_config,
)
from world_model.train.stages import STAGES, train_stage
from world_model.train.trainer import TrainingDivergedError


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m world_model.train", description=__doc__.splitlines()[0])
    p.add_argument("--stage", required=True, choices=STAGES)
    p.add_argument("--data", required=True, help="dataset directory (m4world-clips format)")
    p.add_argument("--run", required=True, help="run directory; each stage writes RUN/<stage>/")
    p.add_argument("--preset", default="default", choices=sorted(PRESETS))
    p.add_argument("--steps", type=int, default=None, help="total optimizer steps (default: per preset)")
    p.add_argument("--batch-size", type=int, default=None)
    p.add_argument("--lr", type=float, default=None)
    p.add_argument("--ckpt-every", type=int, default=None)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--no-progress", action="store_true")
    p.add_argument("--case", default=None, help="lora: adapter name = rare object category (e.g. tree_truck)")
    p.add_argument("--case-data", default=None, help="lora: dataset of rare-case clips (default: from --data)")
    p.add_argument("--case-clips", default=None, help="lora: comma-separated rare clip names (overrides the category)")
    p.add_argument("--base", default=None, help=BASE_HELP)
    add_lora_flags(p)
    add_student_flags(p, long_frames=True)
    a = p.parse_args(argv)
    apply_heap_flag(a)
    try:
        out = train_stage(
            a.stage,
            a.data,
            a.run,
            preset=a.preset,
            config=stage_config(a, get_preset(a.preset)),
            steps=a.steps,
            batch_size=a.batch_size,
            lr=a.lr,
            ckpt_every=a.ckpt_every,
            seed=a.seed,
            progress=not a.no_progress,
            case=a.case,
            case_data=a.case_data,
            case_clips=a.case_clips.split(",") if a.case_clips else None,
            base=a.base,
            lora_box_weight=a.lora_box_weight,
            lora_rank=a.lora_rank,
            student=student_config(a),
            dtype=a.dtype,
        )
    except (FileNotFoundError, ValueError, TrainingDivergedError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    out.pop("losses", None)
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""First frames from controls alone (what ``env.reset()`` samples without a reference image),
judged against the evaluation set's true first frames, for a grid of sampler settings.

Each clip's first frame is generated ``--seeds`` times (different noise) by the checkpoint's
reference model — and, with ``--teacher``, by the bidirectional teacher as a plain text-to-scene
sampler — for every camera guidance scale in ``--cfg`` and step count in ``--steps``, and by the bundle's
one-step first-frame model where it has one (one unguided step, what a reset then draws). Every
generated frame is scored by the report's judge and metrics (weather, time of day, existence, ...,
PSNR, LiDAR MAE) next to the Oracle (the true frame). This separates what the first frame gets
wrong from what the causal student loses over a rollout (the report's student row).

    m4world bench first_frame --evalset data/evalset [--checkpoint BUNDLE]
        [--teacher RUN/teacher/model] [--cfg 1 3 5] [--steps 20 40] [--seeds 2] [--out F.json]
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from world_model.data import Clip, iter_clips
from world_model.eval.report import Generated, ReportConfig, RowFn, evaluate_rows, oracle_row
from world_model.model.conditions import Conditions
from world_model.model.config import SamplerConfig
from world_model.model.reference import ONE_STEP, ReferenceGenerator
from world_model.rollout.runtime import WorldModel, load_world_model

SEED_SEPARATOR = "#seed"


def first_frames(clips: list[Clip], seeds: int) -> list[Clip]:
    """Every clip cut to its first frame, ``seeds`` times (the seed rides in the clip's name)."""
    out = []
    for c in clips:
        cams, lidar, bev = (np.asarray(a[:1]) for a in (c.cameras, c.lidar, c.bev))
        for s in range(seeds):
            out.append(Clip(f"{c.name}{SEED_SEPARATOR}{s}", c.frames[:1], cams, lidar, bev, c.crops, c.meta))
    return out


def first_frame_row(wm: WorldModel, generator: ReferenceGenerator, sampler: SamplerConfig) -> RowFn:
    def row(clip: Clip) -> Generated:
        cond = Conditions.collate([wm.conditions.arrays(clip.frames, clip.frames[0], clip.crops, clip.crop_since)])
        seed = int(clip.name.rsplit(SEED_SEPARATOR, 1)[1])
        obs = wm.decode(generator.sample(cond, None, seed=seed, sampler=sampler), **cond.frames(0, 1).decoder_inputs())[
            0
        ]
        return Generated(cameras=np.stack([o.cameras for o in obs]), lidar=np.stack([o.lidar for o in obs]))

    return row


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(
        prog="m4world bench first_frame", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--evalset", required=True)
    ap.add_argument("--checkpoint", default=None, help="bundle (default: the shipped checkpoint)")
    ap.add_argument("--teacher", default=None, help="also sample with this teacher export (RUN/teacher/model)")
    ap.add_argument("--cfg", type=float, nargs="+", default=None, help="camera guidance scales (default: config's)")
    ap.add_argument("--steps", type=int, nargs="+", default=None, help="Euler steps (default: config's)")
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--max-clips", type=int, default=0)
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)

    wm = load_world_model(args.checkpoint, dtype="float32")
    clips = first_frames(list(iter_clips(args.evalset))[: args.max_clips or None], args.seeds)
    if not clips:
        raise SystemExit(f"no clips in {args.evalset}")
    generators = {"reference": wm.first_frames}
    if args.teacher:
        from world_model.train.exports import load_teacher

        generators["teacher"] = ReferenceGenerator(load_teacher(args.teacher), wm.vae)
    base = wm.cfg.sampler
    rows: dict[str, RowFn] = {"oracle": oracle_row}
    for name, gen in generators.items():
        for cfg in args.cfg or [base.camera_cfg_scale]:
            for steps in args.steps or [base.steps]:
                sampler = replace(base, camera_cfg_scale=cfg, steps=steps)
                rows[f"{name} cfg={cfg:g} steps={steps}"] = first_frame_row(wm, gen, sampler)
    if wm.one_step_frames is not None:
        rows["first_frame model, one step"] = first_frame_row(wm, wm.one_step_frames, ONE_STEP)
    t0 = time.perf_counter()
    report = evaluate_rows(rows, clips, config=ReportConfig(frame_stride=1, lidar_stride=1))
    result = {
        "evalset": args.evalset,
        "first_frames": len(clips),
        "seeds": args.seeds,
        "seconds": time.perf_counter() - t0,
        "rows": {
            name: {"table2": r.table2.to_json(), "psnr_db": r.table1.psnr_db, "lidar_mae_m": r.table1.lidar_range_mae_m}
            for name, r in report.rows.items()
        },
    }
    cols = ["weather", "time_of_day", "existence", "clarity", "visual_fidelity", "textual_fidelity"]
    print(f"{len(clips)} first frames ({args.seeds} seeds per clip)\n")
    print("| row | " + " | ".join(cols) + " | psnr_db | lidar_mae_m |")
    print("|---" * (len(cols) + 3) + "|")
    for k, r in result["rows"].items():
        vals = [r["table2"][c] for c in cols] + [r["psnr_db"], r["lidar_mae_m"]]
        print(f"| {k} | " + " | ".join("n/a" if x is None else f"{x:.3f}" for x in vals) + " |")
    if args.out:
        Path(args.out).write_text(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main()

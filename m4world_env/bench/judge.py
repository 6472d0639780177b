"""The judge's own accuracy on held-out ground truth, per question and per category, and its
throughput.

Questions with known answers are built from the evaluation set (``record_evalset``; seeds never
used to train the judge or the world model): positives ask about the true attribute / the same
object, negatives about a wrong one (see ``world_model.eval.questions``). Accuracy is balanced
accuracy; weather and time of day are also asked of the views under mild degradations that
change neither (``scene_accuracy_degraded``). Throughput: medians over repeats measured in one run.

    m4world bench judge --evalset data/evalset --out bench_judge.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time
from collections.abc import Callable
from dataclasses import replace

import numpy as np
import torch

from world_model.eval.judge import DEFAULT_JUDGE_DIR, load_judge
from world_model.eval.judge_data import MILD_DEGRADATIONS, CollectConfig, collect
from world_model.eval.questions import QUESTION_TYPES, build_questions, judge_accuracy


def _median_rate(fn: Callable[[], object], items: int, repeats: int) -> float:
    fn()  # warm-up
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return items / statistics.median(times)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="m4world bench judge", description=__doc__.split("\n\n")[0])
    p.add_argument("--evalset", required=True, help="directory of the recorded evaluation set")
    p.add_argument("--judge", default=str(DEFAULT_JUDGE_DIR), help="judge directory (default: shipped)")
    p.add_argument("--out", default=None, help="write the JSON figures here")
    p.add_argument("--max-clips", type=int, default=None)
    p.add_argument("--max-per-type", type=int, default=3000, help="source items per question type")
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--threads", type=int, default=2)
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)

    judge = load_judge(args.judge)
    t0 = time.perf_counter()
    data = collect(args.evalset, CollectConfig(max_clips=args.max_clips))
    questions = build_questions(data, seed=0, max_per_type=args.max_per_type)
    accuracy = judge_accuracy(judge, questions)
    eval_s = time.perf_counter() - t0
    scene = ("weather", "time_of_day")
    robustness = {
        name: judge_accuracy(
            judge, build_questions(replace(data, scene_frames=[fn(f) for f in data.scene_frames]), seed=0,
                                   max_per_type=args.max_per_type), scene)
        for name, fn in MILD_DEGRADATIONS.items()
    }  # fmt: skip

    crops = (data.crops * (1 + 512 // max(1, len(data.crops))))[:512]
    frames = np.stack((data.scene_frames * (1 + 32 // len(data.scene_frames)))[:32])
    crop_rate = _median_rate(lambda: judge.crop_outputs(crops), len(crops), args.repeats)
    frame_rate = _median_rate(lambda: judge.scene_outputs(frames), len(frames), args.repeats)

    result = {
        "evalset": args.evalset,
        "judge": args.judge,
        "clips": len(data.clip_names),
        "crops": len(data.crops),
        "scene_frames": len(data.scene_frames),
        "accuracy": accuracy,
        "scene_accuracy_degraded": robustness,
        "throughput": {"crops_per_s": crop_rate, "multiview_frames_per_s": frame_rate, "threads": args.threads},
        "evaluation_seconds": eval_s,
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count(), "torch": torch.__version__},
    }
    print(f"{'question':24s} {'bal.acc':>8s} {'yes|pos':>8s} {'no|neg':>8s} {'n':>11s}")
    for q in QUESTION_TYPES:
        a = accuracy[q]
        print(
            f"{q:24s} {a['balanced_accuracy']:8.3f} {a['tpr']:8.3f} {a['tnr']:8.3f} {a['n_pos']:>5d}+{a['n_neg']:<5d}"
        )
    print("existence per category: " + ", ".join(
        f"{c}={v['balanced_accuracy']:.2f}" for c, v in accuracy["existence"]["per_category"].items()
    ))  # fmt: skip
    for name, acc in robustness.items():
        worst = {q: min(v["balanced_accuracy"] for v in a["per_category"].values()) for q, a in acc.items()}
        print(f"views under {name}: " + ", ".join(
            f"{q} {a['balanced_accuracy']:.3f} (worst view {worst[q]:.3f})" for q, a in acc.items()
        ))  # fmt: skip
    print(f"throughput: {crop_rate:.0f} crops/s, {frame_rate:.1f} multi-view frames/s ({args.threads} threads)")
    if args.out:
        with open(args.out, "w") as f:
            json.dump(result, f, indent=1)
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

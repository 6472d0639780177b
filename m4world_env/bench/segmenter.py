"""How good and how fast is the segmenter of the scene IoU? Per-class IoU on recorded clips and CPU
milliseconds per multi-view frame.

For each ``--data`` dataset: the per-class IoU of the segmenter (default: the shipped one) on every
``--stride``-th frame of every clip, against the label maps of the clips' scene frames (cached under
``--out``). On the held-out clips at the training run's ``heldout_stride`` this is the held-out
figure of ``segmenter.json``; on the evaluation set it is the ceiling of the report's oracle row.
``ms_per_frame``: one (V, H, W, 3) frame of the first clip at a time, on ``--threads`` CPU threads,
median of ``--repeats`` passes over ``--frames`` frames.

    m4world bench segmenter --data data/segmenter/heldout data/evalset --out out/bench_segmenter
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from world_model.data import read_clip
from world_model.eval.segmenter import DEFAULT_SEGMENTER_DIR, SCENE_CLASSES, Segmenter, load_segmenter
from world_model.eval.segmenter_data import clip_refs, collect_views
from world_model.eval.train_segmenter import evaluate


def ms_per_frame(segmenter: Segmenter, frames: np.ndarray, repeats: int) -> float:
    """Median milliseconds to segment one multi-view frame (V, H, W, 3), frame by frame."""
    segmenter.predict(frames[0])  # warm-up
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        for f in frames:
            segmenter.predict(f)
        times.append((time.perf_counter() - start) / len(frames))
    return 1000.0 * float(np.median(times))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="m4world bench segmenter", description=__doc__.splitlines()[0])
    p.add_argument("--data", nargs="+", required=True, help="recorded datasets (held-out clips, the evaluation set)")
    p.add_argument("--segmenter", default=str(DEFAULT_SEGMENTER_DIR), help="a saved segmenter directory")
    p.add_argument("--stride", type=int, default=4, help="every n-th frame of each clip")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--frames", type=int, default=20, help="frames timed per pass")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--out", required=True, help="folder for bench_segmenter.json and the label cache")
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    seg = load_segmenter(args.segmenter)
    out = Path(args.out)
    result: dict = {"segmenter": Path(args.segmenter).name, "threads": args.threads, "stride": args.stride}
    result["datasets"] = {}
    for data in args.data:
        refs = clip_refs([data])
        views = collect_views(refs, out / "labels", args.stride)
        iou = dict(zip(SCENE_CLASSES, evaluate(seg, views).iou(), strict=True))
        result["datasets"][Path(data).name] = {"clips": len(refs), "views": len(views.images), "iou": iou}
        print(f"{data}: {len(refs)} clips, {len(views.images)} views (every {args.stride}th frame)")
        for c, v in iou.items():
            print(f"  IoU {c:>12}: {'-' if v is None else f'{v:.3f}'}")
    first = read_clip(refs[0].root, refs[0].name)
    frames = np.asarray(first.cameras[: args.frames])
    result["ms_per_frame"] = ms_per_frame(seg, frames, args.repeats)
    result["frame_shape"] = list(frames.shape[1:])
    print(f"{result['ms_per_frame']:.1f} ms per {frames.shape[1]}-view frame on {args.threads} thread(s)")
    out.mkdir(parents=True, exist_ok=True)
    (out / "bench_segmenter.json").write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

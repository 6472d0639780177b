"""How good and how fast is the segmenter of the scene IoU? Per-class IoU on recorded clips and CPU
milliseconds per multi-view frame.

For each ``--data`` dataset: the per-class IoU of the segmenter (default: the shipped one) on every
``--stride``-th frame of every clip, against the label maps of the clips' scene frames (cached under
``--out``). On the held-out clips at the training run's ``heldout_stride`` this is the held-out
figure of ``segmenter.json``; on the evaluation set it is the ceiling of the report's oracle row.
``front``: the report's FRONT readings (:func:`~world_model.eval.decisions.camera_decisions`: the
lead vehicle's bottom row, the lane markings at the bottom) taken by the segmenter on the recorded
views against the same readings of the label maps: the judge's own error on what a policy reads,
below which no row's can be told apart. ``lead_within_px``: the share of frames with a lead in the
label map whose segmented lead's bottom row is within :data:`LEAD_ROW_TOLERANCE_PX` of it.
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
from world_model.eval.decisions import P50, P95, DecisionSums, camera_decisions, front_view_index, percentile, share
from world_model.eval.segmenter import DEFAULT_SEGMENTER_DIR, SCENE_CLASSES, Segmenter, load_segmenter
from world_model.eval.segmenter_data import ClipRef, cached_scene_labels, clip_refs, collect_views
from world_model.eval.train_segmenter import evaluate

# The tolerance a policy reading the lead's bottom row can live with: one pixel row is a few
# metres of range at 20-40 m in the 64-row FRONT view.
LEAD_ROW_TOLERANCE_PX = 1.0


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


def front_readings(segmenter: Segmenter, refs: list[ClipRef], cache_dir: Path, stride: int) -> dict:
    """The FRONT readings of every ``stride``-th frame of the clips ``refs``: the segmenter's view of
    each recorded FRONT image against its label map's (module docstring)."""
    sums = DecisionSums()
    for ref in refs:
        clip = read_clip(ref.root, ref.name)
        front = front_view_index(clip.frames[0].rig.names)
        if front is None:
            continue
        labels = cached_scene_labels(clip, cache_dir)
        read = list(range(0, clip.num_frames, stride))
        predicted = segmenter.predict(np.asarray(clip.cameras[read, front]))
        for f, classes in zip(read, predicted, strict=True):
            frame = clip.frames[f]
            camera = frame.rig.cameras[front]
            sums += camera_decisions(np.asarray(labels[f, front]), classes, camera, frame.lidar.mount_height)
    lead, lanes = sums.lead, sums.lanes
    within = sum(e <= LEAD_ROW_TOLERANCE_PX for e in lead.bottom_row_errors_px)
    return {
        "leads": lead.leads,
        "lead_missed": share(lead.missed, lead.leads),
        "lead_bottom_row_p50_px": percentile(lead.bottom_row_errors_px, P50),
        "lead_bottom_row_p95_px": percentile(lead.bottom_row_errors_px, P95),
        "lead_within_px": share(within, lead.leads),
        "lead_phantom": share(lead.phantom, lead.no_lead),
        "markings": lanes.markings,
        "lane_error_p50_m": percentile(lanes.errors_m, P50),
        "lane_error_p95_m": percentile(lanes.errors_m, P95),
        "lane_missed": share(lanes.missed, lanes.markings),
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="m4world bench segmenter", description=__doc__.split("\n\n")[0])
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
        front = front_readings(seg, refs, out / "labels", args.stride)
        row = {"clips": len(refs), "views": len(views.images), "iou": iou, "front": front}
        result["datasets"][Path(data).name] = row
        print(f"{data}: {len(refs)} clips, {len(views.images)} views (every {args.stride}th frame)")
        for c, v in iou.items():
            print(f"  IoU {c:>12}: {'-' if v is None else f'{v:.3f}'}")
        for k, v in front.items():
            print(f"  FRONT {k:>22}: {'-' if v is None else f'{v:.3f}' if isinstance(v, float) else v}")
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

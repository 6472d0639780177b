"""Procedural simulator throughput: 6 cameras + LiDAR at 64x112 and 224x400, BEV separately.

A realistic highway sequence: 4 lanes, ~18 objects of every category; vehicles drift relative to
the ego while static objects (cones, barriers, pedestrians) stream past; the ego drives 2 m per
frame (20 m/s at 10 Hz), so road tiles are rasterized lazily during the run as they would be in an
episode. Reports medians over frames measured in one run.

    m4world bench render --out bench_render.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import statistics
import time
from collections.abc import Callable

import cv2
import numpy as np

from world_model import Box3D, SceneFrame, default_rig
from world_model.sim import ProceduralSimulator
from world_model.sim.demo import demo_frame, straight_road

EGO_STEP_M = 2.0  # per frame
FRAME_DT_S = 0.1
STATIC = ("cone", "barrier", "pedestrian")


def sequence(width: int, height: int, frames: int, objects: int, weather: str, time_of_day: str) -> list[SceneFrame]:
    rig = default_rig(width=width, height=height)
    road = straight_road(num_lanes=4, x0=-500.0, x1=5000.0)
    base = demo_frame(num_objects=objects, seed=0, weather=weather, time_of_day=time_of_day, rig=rig, road=road)
    rel_speed = np.random.default_rng(1).uniform(-3.0, 3.0, len(base.objects))  # m/s relative to the ego
    out = []
    for i in range(frames):
        ego_x = EGO_STEP_M * i
        objs = []
        for o, dv in zip(base.objects, rel_speed, strict=True):
            x, y, z = o.box.center
            x = x + (0.0 if o.category in STATIC else ego_x + dv * FRAME_DT_S * i)
            objs.append(dataclasses.replace(o, box=Box3D((x, y, z), o.box.size, o.box.yaw)))
        out.append(
            dataclasses.replace(
                base,
                time=FRAME_DT_S * i,
                frame_index=i,
                objects=tuple(objs),
                ego=dataclasses.replace(base.ego, x=ego_x),
            )
        )
    return out


def median_ms(fn: Callable[[SceneFrame], object], frames: list[SceneFrame], warmup: int) -> float:
    for f in frames[:warmup]:
        fn(f)
    times = []
    for f in frames:
        t0 = time.perf_counter()
        fn(f)
        times.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(times)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(
        prog="m4world bench render", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--out", required=True, help="where to write the JSON results")
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--warmup", type=int, default=10)
    ap.add_argument("--objects", type=int, default=18)
    ap.add_argument("--weather", default="sunny")
    ap.add_argument("--time-of-day", default="day")
    args = ap.parse_args(argv)

    rows = []
    for width, height in ((112, 64), (400, 224)):
        frames = sequence(width, height, args.frames, args.objects, args.weather, args.time_of_day)
        sim = ProceduralSimulator()
        full = median_ms(lambda f, s=sim: s.render(f, with_bev=False), frames, args.warmup)
        cams = median_ms(sim.render_cameras, frames, args.warmup)
        lidar = median_ms(sim.render_lidar, frames, args.warmup)
        bev = median_ms(sim.render_bev, frames, args.warmup)
        rows.append(
            {
                "resolution": f"{height}x{width}",
                "views": frames[0].rig.num_views,
                "cameras_plus_lidar_ms": full,
                "cameras_plus_lidar_fps": 1e3 / full,
                "cameras_ms": cams,
                "lidar_ms": lidar,
                "bev_ms": bev,
                "bev_fps": 1e3 / bev,
            }
        )
    result = {
        "benchmark": "bench_render",
        "frames": args.frames,
        "objects": args.objects,
        "weather": args.weather,
        "time_of_day": args.time_of_day,
        "statistic": "median over frames",
        "lidar": {"beams": frames[0].lidar.beams, "azimuth": frames[0].lidar.azimuth},
        "bev_shape": list(frames[0].bev.shape),
        "machine": {
            "cpus": os.cpu_count(),
            "cv2_threads": cv2.getNumThreads(),
            "python": platform.python_version(),
            "numpy": np.__version__,
            "opencv": cv2.__version__,
            "processor": platform.processor(),
        },
        "results": rows,
    }
    with open(args.out, "w") as fh:
        json.dump(result, fh, indent=2)
    print(f"{'resolution':>10} {'6 cams + LiDAR':>16} {'fps':>7} {'cams':>8} {'LiDAR':>8} {'BEV':>8}")
    for r in rows:
        print(
            f"{r['resolution']:>10} {r['cameras_plus_lidar_ms']:>13.2f} ms"
            f" {r['cameras_plus_lidar_fps']:>7.0f} {r['cameras_ms']:>5.2f} ms {r['lidar_ms']:>5.2f} ms"
            f" {r['bev_ms']:>5.2f} ms"
        )
    print(
        f"(median over {args.frames} frames, {args.objects} objects, {args.weather}/{args.time_of_day}; "
        f"JSON: {args.out})"
    )


if __name__ == "__main__":
    main()

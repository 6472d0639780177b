"""Time to rasterize one frame's layout (every view) at a preset's latent resolution.

    m4world bench layout --preset default --supersample 2 4 --out bench_layout.json

The frame is the demo highway (``world_model.sim.demo.demo_frame``, 18 objects of every
category); its BEV comes from the procedural simulator. Median over ``--repeats`` calls.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

from world_model.model.config import get_preset
from world_model.model.layout import layout_raster
from world_model.sim import ProceduralSimulator
from world_model.sim.demo import demo_frame


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(
        prog="m4world bench layout", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--preset", default="default")
    p.add_argument("--supersample", type=int, nargs="+", default=[2, 4])
    p.add_argument("--objects", type=int, default=18)
    p.add_argument("--repeats", type=int, default=50)
    p.add_argument("--out", type=Path, default=None)
    args = p.parse_args(argv)
    cfg = get_preset(args.preset)
    frame = demo_frame(num_objects=args.objects, seed=1, rig=cfg.sensors.rig())
    bev = ProceduralSimulator().render_bev(frame)
    results = {}
    for s in args.supersample:
        layout_raster(frame, bev, cfg.sensors.lidar, cfg.latent_hw, s)  # ray bundles are cached per rig
        times = []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            layout_raster(frame, bev, cfg.sensors.lidar, cfg.latent_hw, s)
            times.append(time.perf_counter() - t0)
        results[f"supersample_{s}"] = {"median_ms_per_frame": 1e3 * statistics.median(times)}
        print(f"{args.preset} supersample {s}: {results[f'supersample_{s}']['median_ms_per_frame']:.2f} ms per frame")
    if args.out:
        args.out.write_text(json.dumps({"args": vars(args) | {"out": str(args.out)}, "results": results}, indent=1))
    return results


if __name__ == "__main__":
    main()

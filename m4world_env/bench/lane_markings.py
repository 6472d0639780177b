"""What a lane finder reads on the world model vs the ground truth, on the same states: how bright
the lane markings low in FRONT are, and the road beside them.

    m4world bench lane_markings --out F.json [--scenarios highway_sunny_day ...] [--seeds 0 1 2] \
        [--steps 20] [--checkpoint BUNDLE]

For each scenario and seed, one episode: the built-in ``lane_keeping`` policy drives
``backend="procedural"`` (the ground truth) and its very actions are fed to ``backend="world_model"``
(cameras only), both reset with the seed, so the traffic is the same on both. After each step, on the
lower half of both FRONT views (where lane finders look), the mean luminance (the mean of R, G, B,
0-255) of the pixels the scene's label map calls markings, and of those it calls road; a frame with
fewer than ``MIN_MARKING_PIXELS`` marking pixels there is left out. The markings are where the scene
puts them on both backends (the decoder draws the label map); how they stand out from the road is the
model's. An episode stops when either env ends.

Per scenario (its seeds and steps pooled): the frames read, the markings' and the road's mean
luminance on each backend and their contrast (markings over road), with the world model's contrast
over the ground truth's. A markdown table is printed; the JSON holds the figures and the settings.
"""

from __future__ import annotations

import sys

import numpy as np

from m4world_env.agreement import FULL_SCENARIOS
from m4world_env.same_states import (
    model_env_kwargs,
    pooled_by_scenario,
    replay_main,
    replay_settings,
    replayed_steps,
)
from world_model.raster.classes import CLASS_PLANE, MARKING, ROAD
from world_model.sensors import DEFAULT_CAMERA_NAMES
from world_model.sim.labels import LabelRasterizer

DEFAULT_SCENARIOS = FULL_SCENARIOS  # the agreement report's: where policies are scored
FRONT = DEFAULT_CAMERA_NAMES.index("FRONT")
MIN_MARKING_PIXELS = 6  # fewer markings in the lower half: a frame with no lane line to read
Reading = tuple[float, float]  # (markings, road) mean luminance of one FRONT view


def front_reading(image: np.ndarray, classes: np.ndarray) -> Reading | None:
    """The mean luminance of the markings and of the road in the lower half of a view: ``image``
    (H, W, 3) uint8, ``classes`` (H, W) its label map's class ids; None with fewer than
    :data:`MIN_MARKING_PIXELS` markings or no road there."""
    if image.shape[:2] != classes.shape:
        raise ValueError(f"image {image.shape[:2]} and label map {classes.shape} differ in size")
    half = image.shape[0] // 2
    luminance, low = image[half:].astype(np.float64).mean(-1), classes[half:]
    markings, road = luminance[low == MARKING], luminance[low == ROAD]
    if markings.size < MIN_MARKING_PIXELS or road.size == 0:
        return None
    return float(markings.mean()), float(road.mean())


def episode(scenario: str, seed: int, steps: int, model: dict) -> list[tuple[Reading, Reading]]:
    """Up to ``steps`` policy steps of ``scenario``: after each, the ground truth's FRONT reading and
    the ``model`` env's (gym.make keywords, fed the same actions), where both have one."""
    rasterizer = LabelRasterizer()
    pairs = []
    for step in replayed_steps(scenario, seed, steps, model):
        frame = step.truth.scene_frame
        views = step.truth_obs["cameras"][FRONT], step.model_obs["cameras"][FRONT]
        sizes = {view.shape[:2] for view in views}  # the label map at each view's size, once where alike
        classes = {size: rasterizer.maps(frame, frame.rig, *size)[FRONT, CLASS_PLANE] for size in sizes}
        truth, model_reading = (front_reading(view, classes[view.shape[:2]]) for view in views)
        if truth is not None and model_reading is not None:
            pairs.append((truth, model_reading))
    return pairs


def figures(pairs: list[tuple[Reading, Reading]]) -> dict[str, float | int | None]:
    """The readings' means: markings and road on each backend, their contrast (markings over road)
    on each, and the world model's contrast over the ground truth's (None without a frame)."""
    if not pairs:
        return dict.fromkeys(("marking_truth", "marking_model", "road_truth", "road_model"), None) | {
            "frames": 0,
            "contrast_truth": None,
            "contrast_model": None,
            "contrast_ratio": None,
        }
    a = np.array(pairs, dtype=np.float64)  # (N, backend, markings | road)
    mean = a.mean(0)
    contrast_truth, contrast_model = mean[0, 0] / mean[0, 1], mean[1, 0] / mean[1, 1]
    return {
        "frames": len(pairs),
        "marking_truth": float(mean[0, 0]),
        "marking_model": float(mean[1, 0]),
        "road_truth": float(mean[0, 1]),
        "road_model": float(mean[1, 1]),
        "contrast_truth": float(contrast_truth),
        "contrast_model": float(contrast_model),
        "contrast_ratio": float(contrast_model / contrast_truth),
    }


def table(results: dict[str, dict]) -> str:
    """A markdown table of :func:`figures` per scenario."""
    head = ["scenario", "frames", "markings (truth / model)", "road (truth / model)", "contrast (truth / model)"]
    head.append("ratio")
    lines = ["| " + " | ".join(head) + " |", "|" + " --- |" * len(head)]
    for name, f in results.items():
        if not f["frames"]:
            lines.append(f"| {name} | 0 | - | - | - | - |")
            continue
        lines.append(
            f"| {name} | {f['frames']} | {f['marking_truth']:.0f} / {f['marking_model']:.0f} | "
            f"{f['road_truth']:.0f} / {f['road_model']:.0f} | {f['contrast_truth']:.2f} / {f['contrast_model']:.2f} | "
            f"{f['contrast_ratio']:.2f} |"
        )
    return "\n".join(lines)


def run(scenarios: list[str], seeds: list[int], steps: int, checkpoint: str | None) -> dict:
    """Every episode; the figures per scenario (seeds pooled), with the settings."""
    model = model_env_kwargs(("cameras",), checkpoint)  # the cameras alone: no LiDAR decoded
    pooled = pooled_by_scenario(scenarios, seeds, lambda scenario, s: episode(scenario, s, steps, model))
    results = {scenario: figures(pairs) for scenario, pairs in pooled.items()}
    return {
        **replay_settings(scenarios, seeds, steps, checkpoint),
        "min_marking_pixels": MIN_MARKING_PIXELS,
        "results": results,
    }


def main(argv: list[str] | None = None) -> int:
    return replay_main("m4world bench lane_markings", __doc__, (DEFAULT_SCENARIOS, (0, 1, 2), 20), run, table, argv)


if __name__ == "__main__":
    sys.exit(main())

"""One episode on both backends, side by side: what a policy saw on each and what it did.

Each frame holds the ground truth's sensor mosaic (cameras in ring layout, the LiDAR range image
below) on the left and the world model's on the right, and under them a line per backend with the
step, the policy's action (acceleration m/s^2, steering deg) and the ego's speed, and the episode's
end (collision, off road) when it comes. The episode on either side is the one ``m4world eval``
runs for that policy, scenario and seed; a side that ended first shows its last frame.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from m4world_env.zoo.base import SENSOR_KEYS

TEXT_HEIGHT_PX = 18  # one line of the caption under the mosaics
TEXT_MARGIN_PX = 6  # the caption's left margin
TEXT_BASELINE_PX = 13  # the first line's baseline, from the caption's top
TEXT_SCALE, END_TEXT_SCALE = 0.42, 0.5  # OpenCV font scales: ~9 px and ~11 px letters
END_TEXT_WIDTH_PX = 120  # room at the caption's right end for "COLLISION" / "OFF ROAD"
SCALE = 2  # integer upscaling: the views are 112 x 64
GAP_PX = 4  # white space between the two sides
VIDEO_QUALITY = 8  # imageio's 0-10 scale, as the demo's video
TEXT_COLOUR = (255, 255, 255)
FAIL_COLOUR = (255, 90, 90)


def _episode(
    policy: str, scenario: str, seed: int, steps: int, backend: str, checkpoint: str | None, dtype: str = "auto"
) -> list[dict]:
    """Every step of one episode: the observation and what the policy did after seeing it (``dtype``:
    the world model's ``config.model.dtype``)."""
    import gymnasium as gym

    import m4world_env  # noqa: F401  (registers M4World-v0)
    from m4world_env import zoo
    from m4world_env.evaluate import make_policy

    env = gym.make(
        "M4World-v0",
        scenario=scenario,
        backend=backend,
        checkpoint=checkpoint if backend == "world_model" else None,
        config={"observation_keys": list(SENSOR_KEYS), "model": {"dtype": dtype}},
    )
    geometry = None
    try:
        obs, info = env.reset(seed=seed)
        act = make_policy(policy, env)
        geometry = zoo.SensorGeometry.of_env(env)
        out, ended = [], ""
        for t in range(steps + 1):
            action = act(obs, info) if t < steps and not ended else None
            out.append({"obs": obs, "info": info, "action": action, "ended": ended, "step": t})
            if action is None:
                break
            obs, _r, terminated, truncated, info = env.step(action)
            if terminated or truncated:
                m = info["episode_metrics"]
                ended = "COLLISION" if m["collision"] else "OFF ROAD" if m["off_road"] else "END"
                out.append({"obs": obs, "info": info, "action": None, "ended": ended, "step": t + 1})
                break
    finally:
        env.close()
    for row in out:
        row["controls"] = None if row["action"] is None else geometry.controls(row["action"])
    return out


def _panel(row: dict, label: str, size: tuple[int, int] | None = None) -> np.ndarray:
    """The sensor mosaic of one step (scaled to ``size`` (w, h) when given: a checkpoint's views
    may be smaller than the ground truth's) with its caption."""
    import cv2

    from world_model.observation import Observation
    from world_model.sim import mosaic

    obs = row["obs"]
    img = mosaic(Observation(cameras=obs["cameras"], lidar=obs["lidar"]))
    size = size or (img.shape[1] * SCALE, img.shape[0] * SCALE)
    img = cv2.resize(img, size, interpolation=cv2.INTER_NEAREST)
    caption = np.zeros((TEXT_HEIGHT_PX * 2, img.shape[1], 3), dtype=np.uint8)
    pdms = row["info"]["episode_metrics"]["pdms"]
    if row["controls"] is not None:
        acc, steer = row["controls"]
        what = f"accel {acc:+.1f} m/s2  steer {math.degrees(steer):+.1f} deg"
    else:
        what = "-"
    lines = [f"{label}  step {row['step']}  speed {row['info']['speed']:.1f} m/s  PDMS so far {pdms:.2f}", what]
    font = cv2.FONT_HERSHEY_SIMPLEX
    for k, text in enumerate(lines):
        origin = (TEXT_MARGIN_PX, TEXT_BASELINE_PX + k * TEXT_HEIGHT_PX)
        cv2.putText(caption, text, origin, font, TEXT_SCALE, TEXT_COLOUR, 1)
    if row["ended"]:
        origin = (img.shape[1] - END_TEXT_WIDTH_PX, TEXT_BASELINE_PX)
        cv2.putText(caption, row["ended"], origin, font, END_TEXT_SCALE, FAIL_COLOUR, 1)
    return np.concatenate([img, caption], axis=0)


def side_by_side_video(
    policy: str, scenario: str, seed: int, steps: int, checkpoint: str | None, path: str | Path, dtype: str = "auto"
) -> Path:
    """Write the side-by-side video of ``policy`` on ``scenario`` / ``seed`` for up to ``steps``
    steps to ``path`` (mp4, written whole or not at all; ``dtype``: the world model's
    ``config.model.dtype``); returns the path."""
    import imageio.v2 as imageio

    from m4world_env.scenario import load_scenario

    path = Path(path)
    truth = _episode(policy, scenario, seed, steps, "procedural", None)
    model = _episode(policy, scenario, seed, steps, "world_model", checkpoint, dtype)
    fps = load_scenario(scenario).policy_frequency
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(f".{path.stem}.partial{path.suffix}")
    try:
        with imageio.get_writer(partial, fps=fps, codec="libx264", quality=VIDEO_QUALITY, macro_block_size=2) as writer:
            for t in range(max(len(truth), len(model))):
                left = _panel(truth[min(t, len(truth) - 1)], "ground truth")
                size = (left.shape[1], left.shape[0] - 2 * TEXT_HEIGHT_PX)
                right = _panel(model[min(t, len(model) - 1)], "world model", size)
                gap = np.full((left.shape[0], GAP_PX, 3), 255, dtype=np.uint8)
                frame = np.concatenate([left, gap, right], axis=1)
                writer.append_data(np.pad(frame, ((0, frame.shape[0] % 2), (0, frame.shape[1] % 2), (0, 0))))
        partial.replace(path)
    finally:
        partial.unlink(missing_ok=True)
    return path

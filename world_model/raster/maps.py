"""The decoder's maps of a scene: each camera's label map and the LiDAR view's nearness.

The VAE decoder draws the scene's layout from these at the views' full resolution, beside the
student's latents (``layout.decoder``; docs/layout.md): each camera's
class ids, the objects' paint and the ground's surface (:meth:`LabelRasterizer.maps
<world_model.sim.labels.LabelRasterizer.maps>`), and the range map the scene implies on the LiDAR
view (:func:`~world_model.model.layout.lidar_nearness`). Over the decoded cameras go the rain
streaks or snow flakes the weather puts in front of each lens (:func:`camera_precipitation`).
Frames that will not be decoded may be left out (``labeled``): their maps draw nothing.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence

import numpy as np

from world_model.model.config import ModelConfig
from world_model.model.layout import RANGE_LEVELS, lidar_nearness
from world_model.raster.classes import MAP_PLANES, blank_maps
from world_model.scene import SceneFrame
from world_model.sensors import LidarSpec
from world_model.sim.config import SimConfig
from world_model.sim.labels import LabelRasterizer
from world_model.sim.lidar import LidarRays, cast, lidar_rays
from world_model.sim.lighting import lighting_for
from world_model.sim.poses import object_poses
from world_model.sim.precipitation import Overlay, precipitation_rgb


class SceneRaster:
    """Draws the decoder's maps of frames for a model config. One kept across calls (a rollout's
    frames, every rollout of a vector env) reuses its rasterizer's ray geometry, road textures and
    meshes."""

    def __init__(self, cfg: ModelConfig, rasterizer: LabelRasterizer | None = None) -> None:
        self.cfg = cfg
        self.rasterizer = rasterizer or LabelRasterizer()
        self.overlays: dict[tuple[str, int, int], Overlay] = {}

    def labels(self, frames: Sequence[SceneFrame], labeled: Sequence[bool] | None = None) -> np.ndarray:
        """The frames' camera label maps (:func:`camera_labels`)."""
        return camera_labels(frames, self.cfg, self.rasterizer, labeled)

    def precipitation(
        self, frames: Sequence[SceneFrame], labeled: Sequence[bool] | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """The frames' rain or snow over each camera and its colour (:func:`camera_precipitation`)."""
        return camera_precipitation(frames, self.cfg, self.rasterizer.config, self.overlays, labeled)

    def nearness(self, frames: Sequence[SceneFrame], labeled: Sequence[bool] | None = None) -> np.ndarray:
        """The frames' LiDAR nearness maps (:func:`lidar_nearness_maps`)."""
        return lidar_nearness_maps(frames, self.cfg, labeled)

    def range_nearness(self, frames: Sequence[SceneFrame], labeled: Sequence[bool] | None = None) -> np.ndarray:
        """The frames' nearness maps at the range map's resolution (:func:`range_nearness_maps`)."""
        return range_nearness_maps(frames, self.cfg, labeled)


def _check_labeled(frames: Sequence[SceneFrame], labeled: Sequence[bool] | None) -> None:
    if labeled is not None and len(labeled) != len(frames):
        raise ValueError(f"labeled must flag each of the {len(frames)} frames, got {len(labeled)}")


def camera_labels(
    frames: Sequence[SceneFrame],
    cfg: ModelConfig,
    rasterizer: LabelRasterizer | None = None,
    labeled: Sequence[bool] | None = None,
) -> np.ndarray:
    """The ``labels`` condition: each camera's label map of every frame, (T, Vc, 3, H, W) uint8
    (class ids, paint, surface: :meth:`~world_model.sim.labels.LabelRasterizer.maps`), for a
    decoder that draws them (``layout.decoder``); (T, Vc, 3, 0, 0) without one. ``rasterizer``: one
    kept across calls reuses its ray geometry, road texture and meshes (default: a new one).
    ``labeled`` (T,): the frames that will be decoded (default: all); the others' classes are left
    :data:`~world_model.raster.classes.NO_LABEL`, which saves rendering maps nobody draws."""
    s = cfg.sensors
    if not cfg.layout.decoder:
        return np.zeros((len(frames), s.num_cameras, MAP_PLANES, 0, 0), np.uint8)
    _check_labeled(frames, labeled)
    raster = rasterizer or LabelRasterizer()
    out = blank_maps((len(frames), s.num_cameras), s.height, s.width)
    for t, frame in enumerate(frames):
        if labeled is None or labeled[t]:
            out[t] = raster.maps(frame, frame.rig, s.height, s.width)
    return out


def camera_precipitation(
    frames: Sequence[SceneFrame],
    cfg: ModelConfig,
    sim: SimConfig | None = None,
    overlays: dict[tuple[str, int, int], Overlay] | None = None,
    labeled: Sequence[bool] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """The ``precipitation`` and ``precipitation_rgb`` conditions: the alpha, (T, Vc, H, W) uint8,
    of the rain streaks or snow flakes the simulator blends over each camera of every frame (``sim``'s
    :mod:`~world_model.sim.precipitation`: a function of the weather, the scenario and the frame
    index, nothing the model could draw from its latents), 0 where the weather has none; and their
    colour in the frame's light, (T, 3) uint8. Blended over the decoded cameras, so the world model's
    rain and snow fall as the ground truth's. (T, Vc, 0, 0) and zeros without a label decoder
    (``layout.decoder``). ``overlays``: the layer pools by (kind, H, W), kept across calls (a pool
    is hundreds of antialiased streaks, drawn once). ``labeled`` as :func:`camera_labels`: the
    other frames get none."""
    s = cfg.sensors
    rgb = np.zeros((len(frames), 3), np.uint8)
    if not cfg.layout.decoder:
        return np.zeros((len(frames), s.num_cameras, 0, 0), np.uint8), rgb
    _check_labeled(frames, labeled)
    sim = sim or SimConfig()
    overlays = {} if overlays is None else overlays
    out = np.zeros((len(frames), s.num_cameras, s.height, s.width), np.uint8)
    for t, frame in enumerate(frames):
        lighting = lighting_for(frame.prompt)
        if lighting.precipitation == "none" or not (labeled is None or labeled[t]):
            continue
        key = (lighting.precipitation, s.height, s.width)
        if key not in overlays:
            overlays[key] = Overlay(lighting.precipitation, s.height, s.width, sim)
        out[t] = overlays[key].alpha(frame, s.num_cameras).reshape(s.num_cameras, s.height, s.width)
        rgb[t] = precipitation_rgb(lighting)
    return out, rgb


def lidar_nearness_maps(
    frames: Sequence[SceneFrame], cfg: ModelConfig, labeled: Sequence[bool] | None = None
) -> np.ndarray:
    """The ``lidar_nearness`` condition: the LiDAR view's nearness map of every frame, (T, H, W)
    uint8 (:func:`~world_model.model.layout.lidar_nearness`), for a decoder that draws it
    (``layout.decoder``); (T, 0, 0) without one. ``labeled`` as :func:`camera_labels`: the
    other frames' maps are left 0, nothing in range."""
    s = cfg.sensors
    if not cfg.layout.decoder:
        return np.zeros((len(frames), 0, 0), np.uint8)
    _check_labeled(frames, labeled)
    out = np.zeros((len(frames), s.height, s.width), np.uint8)
    for t, frame in enumerate(frames):
        if labeled is None or labeled[t]:
            out[t] = lidar_nearness(frame, s.lidar, (s.height, s.width))
    return out


def range_nearness_maps(
    frames: Sequence[SceneFrame], cfg: ModelConfig, labeled: Sequence[bool] | None = None
) -> np.ndarray:
    """The ``range_nearness`` condition: the range map the scene implies at the LiDAR's own
    resolution, every frame's, (T, beams, azimuth) uint16 in :func:`nearness_levels`' steps, for a VAE
    with a range head (``layout.range_head``); (T, 0, 0) without one. ``labeled`` as
    :func:`camera_labels`.

    Cast by the simulator's LiDAR (:mod:`world_model.sim.lidar`: its own beams, each box culled to
    the sector it can hit), a few milliseconds a frame where a ray per cell against every box takes
    tens."""
    lidar = cfg.sensors.lidar
    if not cfg.layout.range_head:
        return np.zeros((len(frames), 0, 0), np.uint16)
    _check_labeled(frames, labeled)
    rays = _lidar_rays(lidar)
    out = np.zeros((len(frames), lidar.beams, lidar.azimuth), np.uint16)
    for t, frame in enumerate(frames):
        if labeled is None or labeled[t]:
            ranges = cast(object_poses(frame, lidar.mount_height), lidar, rays, SimConfig().lidar_cull_margin_cols)
            out[t] = nearness_levels(ranges, lidar)
    return out


def nearness_levels(ranges: np.ndarray, lidar: LidarSpec) -> np.ndarray:
    """Range maps in metres (``lidar.no_return`` where nothing is in range) -> uint16 nearness,
    :data:`~world_model.model.layout.RANGE_LEVELS` steps of ``1 - range / max_range``, 0 for no return."""
    hit = (ranges != lidar.no_return) & (ranges < lidar.max_range)
    near = np.where(hit, 1.0 - ranges / lidar.max_range, 0.0)
    return np.rint(near * RANGE_LEVELS).astype(np.uint16)


@functools.lru_cache(maxsize=4)
def _lidar_rays(lidar: LidarSpec) -> LidarRays:
    return lidar_rays(lidar)

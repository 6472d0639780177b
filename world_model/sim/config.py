"""Configuration of the procedural sensor simulator: one dataclass, every default visible."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class SimConfig:
    """Knobs of :class:`~world_model.sim.ProceduralSimulator`.

    Appearance per weather / time of day lives in :mod:`world_model.sim.lighting`; this holds the
    geometric, raster and performance settings.
    """

    # -- ground texture (rasterized once per map, world-aligned) --
    texture_m_per_px: float = 0.1  # texel size
    texture_tile_px: int = 256  # tiles are rasterized on first sight (power of two)
    texture_max_tiles: int = 1024  # tiles kept per map (1024 x 64 KiB); one frame's tiles always fit
    texture_noise_cell_m: float = 1.5  # size of the low-frequency asphalt / grass patches
    texture_noise_levels: int = 8  # palette entries per surface used for that variation
    texture_seed: int = 1234
    lane_line_width_m: float = 0.15
    road_edge_width_m: float = 0.25
    dash_length_m: float = 3.0
    dash_gap_m: float = 6.0
    max_ground_distance_m: float = 400.0  # ground farther than this along a ray reads as horizon
    shading_levels: int = 256  # quantization steps per unit of road light and of fog

    # -- cameras --
    near_plane_m: float = 0.1  # polygons are clipped against z_cam >= near_plane_m
    min_face_area_px: float = 0.25  # faces projecting smaller than this are skipped
    impostor_max_px: float = 4.0  # objects whose projected box is smaller are drawn as one flat hull
    antialias: bool = True  # anti-aliased polygon edges (cv2.LINE_AA)
    subpixel_bits: int = 4  # fixed-point fraction bits passed to cv2 drawing calls

    # -- precipitation overlay (rain streaks / snow flakes) --
    precipitation_layers: int = 4  # pre-generated overlay layers per resolution; frames pick one
    precipitation_seed: int = 4321
    rain_streaks_per_kpx: float = 4.0  # streaks per 1000 pixels
    snow_flakes_per_kpx: float = 3.0

    # -- LiDAR --
    lidar_cull_margin_cols: int = 1  # extra azimuth columns around each object's sector

    # -- object crops (image descriptions) --
    crop_min_visible_px: int = 12  # fewer visible pixels than this: no crop
    crop_min_visible_fraction: float = 0.35  # visible / unoccluded silhouette pixels
    crop_margin: float = 0.1  # relative margin added around the projected box

    # -- caches (keyed by object identity of specs, road textures by the map's content) --
    cache_size: int = 8  # rigs, LiDAR specs, lightings and object sets kept
    texture_cache_size: int = 2  # roads (by map content) whose textures are kept (each up to texture_max_tiles)

    def __post_init__(self) -> None:
        positive = {
            "texture_m_per_px": self.texture_m_per_px,
            "texture_noise_cell_m": self.texture_noise_cell_m,
            "lane_line_width_m": self.lane_line_width_m,
            "road_edge_width_m": self.road_edge_width_m,
            "dash_length_m": self.dash_length_m,
            "max_ground_distance_m": self.max_ground_distance_m,
            "near_plane_m": self.near_plane_m,
            "shading_levels": self.shading_levels,
        }
        for name, value in positive.items():
            if not value > 0:
                raise ValueError(f"SimConfig.{name} must be > 0, got {value}")
        if self.dash_gap_m < 0:
            raise ValueError(f"SimConfig.dash_gap_m must be >= 0, got {self.dash_gap_m}")
        if not 1 <= self.texture_noise_levels <= 32:
            raise ValueError(f"SimConfig.texture_noise_levels must be in [1, 32], got {self.texture_noise_levels}")
        if (
            self.precipitation_layers < 1
            or self.cache_size < 1
            or self.texture_cache_size < 1
            or self.texture_max_tiles < 2
        ):
            raise ValueError("SimConfig: precipitation_layers and cache sizes must be >= 1, texture_max_tiles >= 2")
        if not 0 <= self.subpixel_bits <= 8:
            raise ValueError(f"SimConfig.subpixel_bits must be in [0, 8], got {self.subpixel_bits}")
        if not 0.0 <= self.crop_min_visible_fraction <= 1.0:
            raise ValueError("SimConfig.crop_min_visible_fraction must be in [0, 1]")

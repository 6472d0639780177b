"""Appearance of a scene under each weather and time of day, and the material palette.

A :class:`Lighting` is derived from a frame's :class:`~world_model.scene.ScenePrompt` by composing a
weather entry (sky, fog, light, road surface, precipitation) with a time-of-day entry (light level,
colour tint, sky override, lamps on). Colours are RGB in 0..255.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from world_model.scene import ScenePrompt

RGB = tuple[float, float, float]


@dataclass(frozen=True)
class WeatherLook:
    sky_zenith: RGB
    sky_horizon: RGB
    fog_color: RGB
    fog_distance_m: float  # e-folding distance of fog attenuation
    ambient: float  # light on every surface
    sun: float  # extra light on surfaces facing the sun
    road: RGB  # asphalt albedo
    offroad: RGB  # verge albedo
    marking: RGB  # painted lines
    precipitation: str = "none"  # "none", "rain" or "snow"
    precipitation_color: RGB = (255.0, 255.0, 255.0)


@dataclass(frozen=True)
class TimeLook:
    light_scale: float  # multiplies ambient and sun
    tint: RGB  # per-channel multiplier of all reflected light
    sky_zenith: RGB
    sky_horizon: RGB
    sky_mix: float  # 0 = the weather's sky, 1 = this sky
    sun_elevation_deg: float
    lamps: float  # 0 = lamps off; otherwise strength of headlights and emissive lamps


WEATHER_LOOKS: dict[str, WeatherLook] = {
    "sunny": WeatherLook(
        (70, 130, 220),
        (175, 205, 235),
        (200, 215, 230),
        900.0,
        0.55,
        0.6,
        (95, 95, 100),
        (85, 125, 60),
        (235, 235, 225),
    ),
    "cloudy": WeatherLook(
        (140, 148, 158),
        (190, 194, 200),
        (185, 188, 194),
        450.0,
        0.75,
        0.15,
        (100, 100, 104),
        (80, 110, 62),
        (225, 225, 220),
    ),
    "rain": WeatherLook(
        (95, 100, 110),
        (150, 155, 162),
        (140, 145, 152),
        160.0,
        0.6,
        0.05,
        (60, 62, 68),
        (60, 90, 50),
        (200, 200, 195),
        "rain",
        (205, 210, 220),
    ),
    "fog": WeatherLook(
        (190, 192, 195),
        (200, 202, 205),
        (196, 198, 201),
        30.0,
        0.75,
        0.05,
        (100, 100, 104),
        (95, 115, 85),
        (225, 225, 220),
    ),
    "snow": WeatherLook(
        (175, 180, 190),
        (215, 218, 224),
        (215, 218, 224),
        140.0,
        0.8,
        0.1,
        (135, 135, 140),
        (228, 230, 236),
        (215, 215, 210),
        "snow",
        (252, 252, 255),
    ),
}

TIME_LOOKS: dict[str, TimeLook] = {
    "day": TimeLook(1.0, (1.0, 1.0, 1.0), (0, 0, 0), (0, 0, 0), 0.0, 50.0, 0.0),
    "dusk": TimeLook(0.55, (1.08, 0.85, 0.7), (60, 60, 115), (240, 135, 80), 0.7, 6.0, 0.6),
    "night": TimeLook(0.12, (0.8, 0.85, 1.1), (4, 6, 18), (18, 22, 40), 0.95, 30.0, 1.0),
}

# Sun azimuth in the world frame; any fixed choice works, this one lights cars' left-front faces.
SUN_AZIMUTH_DEG = 35.0
# The sky is fogged as if it were this far away.
SKY_DISTANCE_M = 2000.0
# Elevation (radians) over which the sky goes from its horizon to its zenith colour.
SKY_GRADIENT_SPAN_RAD = math.radians(35.0)
# Ego headlights: added light on road and objects ahead, as a Gaussian cone with distance falloff.
HEADLIGHT_GAIN = 1.6
HEADLIGHT_HALF_ANGLE_RAD = math.radians(22.0)
HEADLIGHT_RANGE_M = 35.0


@dataclass(frozen=True)
class Lighting:
    """Everything the renderers need to know about light, sky, fog and precipitation."""

    sky_zenith: np.ndarray  # (3,)
    sky_horizon: np.ndarray  # (3,)
    fog_color: np.ndarray  # (3,)
    fog_distance_m: float
    ambient: float
    sun: float
    sun_direction: np.ndarray  # (3,) unit vector towards the sun, world frame
    tint: np.ndarray  # (3,)
    road: np.ndarray  # (3,)
    offroad: np.ndarray  # (3,)
    marking: np.ndarray  # (3,)
    precipitation: str
    precipitation_color: np.ndarray  # (3,)
    lamps: float

    def fog_factor(self, distance: np.ndarray | float) -> np.ndarray:
        """Fraction of fog colour seen through ``distance`` metres of air (0 = clear)."""
        return 1.0 - np.exp(-np.asarray(distance, dtype=np.float64) / self.fog_distance_m)

    def headlight(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Extra light from the ego's headlights at ego-frame ground points (x, y)."""
        if self.lamps <= 0:
            return np.zeros(np.broadcast(x, y).shape)
        dist = np.hypot(x, y)
        angle = np.arctan2(y, x)
        cone = np.exp(-0.5 * (angle / HEADLIGHT_HALF_ANGLE_RAD) ** 2) * (x > 0)
        falloff = 1.0 / (1.0 + (dist / HEADLIGHT_RANGE_M) ** 2)
        return self.lamps * HEADLIGHT_GAIN * cone * falloff


def _mix(a: RGB, b: RGB, t: float) -> np.ndarray:
    return (1.0 - t) * np.asarray(a, dtype=np.float64) + t * np.asarray(b, dtype=np.float64)


def lighting_for(prompt: ScenePrompt) -> Lighting:
    """Compose the weather and time-of-day looks of ``prompt``."""
    w, t = WEATHER_LOOKS[prompt.weather], TIME_LOOKS[prompt.time_of_day]
    elev, az = math.radians(t.sun_elevation_deg), math.radians(SUN_AZIMUTH_DEG)
    sun_dir = np.array([math.cos(elev) * math.cos(az), math.cos(elev) * math.sin(az), math.sin(elev)])
    horizon = _mix(w.sky_horizon, t.sky_horizon, t.sky_mix)
    return Lighting(
        sky_zenith=_mix(w.sky_zenith, t.sky_zenith, t.sky_mix),
        sky_horizon=horizon,
        fog_color=_mix(w.fog_color, t.sky_horizon, t.sky_mix),
        fog_distance_m=w.fog_distance_m,
        ambient=w.ambient * t.light_scale,
        sun=w.sun * t.light_scale,
        sun_direction=sun_dir,
        tint=np.asarray(t.tint, dtype=np.float64),
        road=np.asarray(w.road, dtype=np.float64),
        offroad=np.asarray(w.offroad, dtype=np.float64),
        marking=np.asarray(w.marking, dtype=np.float64),
        precipitation=w.precipitation,
        precipitation_color=np.asarray(w.precipitation_color, dtype=np.float64) * max(t.light_scale, 0.35),
        lamps=t.lamps,
    )


# -- materials of object parts ------------------------------------------------------------------

# Roles whose albedo derives from the object's own colour.
BODY, BODY_LIGHT, BODY_DARK = "body", "body_light", "body_dark"
# Fixed albedos of every other material.
MATERIAL_ALBEDO: dict[str, RGB] = {
    "glass": (38, 52, 68),
    "wheel": (22, 22, 24),
    "trim": (48, 48, 52),
    "headlight": (215, 215, 200),
    "taillight": (150, 25, 25),
    "skin": (205, 160, 125),
    "hair": (45, 30, 20),
    "legs": (40, 50, 82),
    "foliage": (34, 92, 34),
    "foliage_light": (72, 132, 46),
    "trunk": (105, 72, 42),
    "stripe": (240, 240, 240),
    "sign": (235, 145, 30),
}
# Lamps glow with these colours when the lamps are on (night, dusk).
EMISSIVE_COLOR: dict[str, RGB] = {
    "headlight": (255, 248, 220),
    "taillight": (255, 40, 30),
    "sign": (255, 170, 60),
}
ROLES: tuple[str, ...] = (BODY, BODY_LIGHT, BODY_DARK, *MATERIAL_ALBEDO)
ROLE_INDEX: dict[str, int] = {r: i for i, r in enumerate(ROLES)}


def role_albedos(color: tuple[int, int, int]) -> np.ndarray:
    """(len(ROLES), 3) albedo of every role for an object of base colour ``color``."""
    base = np.asarray(color, dtype=np.float64)
    body_light = _mix(tuple(base), (255.0, 255.0, 255.0), 0.35)
    body_dark = 0.6 * base
    fixed = [np.asarray(MATERIAL_ALBEDO[r], dtype=np.float64) for r in ROLES[3:]]
    return np.stack([base, body_light, body_dark, *fixed])


def emissive_table() -> tuple[np.ndarray, np.ndarray]:
    """(is_emissive (len(ROLES),) bool, emissive colour (len(ROLES), 3))."""
    flags = np.array([r in EMISSIVE_COLOR for r in ROLES])
    colors = np.array([EMISSIVE_COLOR.get(r, (0.0, 0.0, 0.0)) for r in ROLES], dtype=np.float64)
    return flags, colors

"""The zoo's modular and perturbed members (the learned ones live beside their weights,
:mod:`m4world_env.zoo.learned`). A member's settings are part of its version: change one and the
version goes up, so a harness's citation ``name@vN`` always means the same driver."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from m4world_env.zoo.base import Builder, SensorGeometry, SensorPolicy, ZooMember
from m4world_env.zoo.modular import GapKeeping, LaneCentring, ModularDriver
from m4world_env.zoo.perturbed import Perturbed

BASE_GAP, BASE_LANE = GapKeeping(), LaneCentring()
# The beams near the horizon: they meet a car from ~8.5 m on and pass over its roof nearer (the
# LiDAR is 1.84 m up, a car 1.6 m tall).
HORIZON_BEAMS_DEG = (-2.0, 2.0)
FORWARD_SECTOR_DEG = (-30.0, 30.0)  # what a blinded forward LiDAR loses

# name: (gap keeping, lane centring, description)
MODULAR: dict[str, tuple[GapKeeping, LaneCentring, str]] = {
    "gap_keeper": (
        BASE_GAP,
        BASE_LANE,
        "IDM on the LiDAR gap (beams -15..+2 deg, T 1.5 s, 25 m/s), FRONT lane centring",
    ),
    "gap_keeper_horizon": (
        replace(BASE_GAP, beams_deg=HORIZON_BEAMS_DEG),
        BASE_LANE,
        "gap keeping on the horizon beams only (-2..+2 deg)",
    ),
    "gap_keeper_close": (replace(BASE_GAP, time_headway=0.8, min_gap=2.0), BASE_LANE, "short headway: T 0.8 s, s0 2 m"),
    "gap_keeper_far": (replace(BASE_GAP, time_headway=2.5, min_gap=8.0), BASE_LANE, "long headway: T 2.5 s, s0 8 m"),
    "gap_keeper_fast": (replace(BASE_GAP, cruise_speed=32.0), BASE_LANE, "cruise at 32 m/s"),
    "gap_keeper_slow": (replace(BASE_GAP, cruise_speed=15.0), BASE_LANE, "cruise at 15 m/s"),
    "gap_keeper_eager": (
        replace(BASE_GAP, max_accel=3.0, accel_change=2.0),
        BASE_LANE,
        "strong, jerky acceleration: a_max 3 m/s^2, no smoothing to speak of",
    ),
    "gap_keeper_gentle": (replace(BASE_GAP, max_accel=0.6), BASE_LANE, "weak acceleration: a_max 0.6 m/s^2"),
    "gap_keeper_narrow": (replace(BASE_GAP, half_width_m=0.5), BASE_LANE, "a corridor 1 m wide: late to see cut-ins"),
    "gap_keeper_wide": (
        replace(BASE_GAP, half_width_m=2.6),
        BASE_LANE,
        "a corridor 5.2 m wide: brakes for the next lanes",
    ),
    "gap_keeper_straight": (BASE_GAP, replace(BASE_LANE, gain=0.0), "gap keeping, the wheel held straight"),
    "gap_keeper_soft_steer": (BASE_GAP, replace(BASE_LANE, gain=0.3), "weak lane centring: gain 0.3"),
    "gap_keeper_hard_steer": (
        BASE_GAP,
        replace(BASE_LANE, gain=4.0, smoothing=1.0, lookahead_s=0.3),
        "aggressive lane centring: gain 4, short look-ahead, no smoothing",
    ),
    "gap_keeper_faint_lines": (
        BASE_GAP,
        replace(BASE_LANE, min_contrast=45.0),
        "lane centring that needs high-contrast markings (45 grey levels)",
    ),
    "cruise_lane_keeper": (
        replace(BASE_GAP, enabled=False),
        BASE_LANE,
        "FRONT lane centring at 25 m/s, blind to what is ahead",
    ),
}

# name: (base modular member, perturbation keywords of Perturbed, description)
PERTURBED: dict[str, tuple[str, dict, str]] = {
    "gap_keeper_lidar_noise": ("gap_keeper", {"lidar_noise_m": 1.5}, "gap_keeper with 1.5 m range noise"),
    "gap_keeper_lidar_dropout": ("gap_keeper", {"lidar_dropout": 0.5}, "gap_keeper losing half its LiDAR returns"),
    "gap_keeper_camera_noise": ("gap_keeper", {"camera_noise": 40.0}, "gap_keeper with pixel noise (std 40)"),
    "gap_keeper_delay_2": ("gap_keeper", {"delay_steps": 2}, "gap_keeper acting 0.4 s late (2 steps)"),
    "gap_keeper_delay_5": ("gap_keeper", {"delay_steps": 5}, "gap_keeper acting 1 s late (5 steps)"),
    "gap_keeper_blind_front_camera": (
        "gap_keeper",
        {"blind_views": ("FRONT",)},
        "gap_keeper with its FRONT camera black",
    ),
    "gap_keeper_blind_front_lidar": (
        "gap_keeper",
        {"blind_lidar_deg": FORWARD_SECTOR_DEG},
        "gap_keeper with no LiDAR returns within 30 deg of straight ahead",
    ),
}


# Each member's own seed, fixed with its name: adding or moving a member changes no other's noise.
SEEDS: dict[str, int] = {
    "gap_keeper": 100,
    "gap_keeper_horizon": 101,
    "gap_keeper_close": 102,
    "gap_keeper_far": 103,
    "gap_keeper_fast": 104,
    "gap_keeper_slow": 105,
    "gap_keeper_eager": 106,
    "gap_keeper_gentle": 107,
    "gap_keeper_narrow": 108,
    "gap_keeper_wide": 109,
    "gap_keeper_straight": 110,
    "gap_keeper_soft_steer": 111,
    "gap_keeper_hard_steer": 112,
    "gap_keeper_faint_lines": 113,
    "cruise_lane_keeper": 114,
    "gap_keeper_lidar_noise": 200,
    "gap_keeper_lidar_dropout": 201,
    "gap_keeper_camera_noise": 202,
    "gap_keeper_delay_2": 203,
    "gap_keeper_delay_5": 204,
    "gap_keeper_blind_front_camera": 205,
    "gap_keeper_blind_front_lidar": 206,
}


def _modular_builder(gap: GapKeeping, lane: LaneCentring) -> Builder:
    def build(geometry: SensorGeometry, seeds: np.random.SeedSequence) -> SensorPolicy:
        return ModularDriver(geometry, gap, lane)

    return build


def _perturbed_builder(base: str, perturbation: dict) -> Builder:
    gap, lane, _ = MODULAR[base]

    def build(geometry: SensorGeometry, seeds: np.random.SeedSequence) -> SensorPolicy:
        return Perturbed(ModularDriver(geometry, gap, lane), np.random.default_rng(seeds), **perturbation)

    return build


def rule_members() -> list[ZooMember]:
    """The modular and perturbed members, version 1, each with its own seed."""
    members = [
        ZooMember(name, "modular", 1, SEEDS[name], description, _modular_builder(gap, lane))
        for name, (gap, lane, description) in MODULAR.items()
    ]
    members += [
        ZooMember(name, "perturbed", 1, SEEDS[name], description, _perturbed_builder(base, perturbation))
        for name, (base, perturbation, description) in PERTURBED.items()
    ]
    return members

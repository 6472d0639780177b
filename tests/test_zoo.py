"""The zoo of policies that see: its members, their perception on hand-made sensors, and that none
reads the traffic state."""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping

import gymnasium as gym
import numpy as np
import pytest

import m4world_env  # noqa: F401  (registers M4World-v0)
from m4world_env import zoo
from m4world_env.evaluate import EvalRequest, evaluate, make_policy
from m4world_env.zoo.base import EGO_STATUS_KEYS, SENSOR_KEYS, SensorGeometry
from m4world_env.zoo.modular import GapKeeping, LaneCentring, ModularDriver
from m4world_env.zoo.perception import (
    LANE_WIDTH_M,
    Markings,
    beam_band,
    forward_gap,
    lane_markings,
    marking_peaks,
)
from m4world_env.zoo.perturbed import Perturbed
from world_model.sensors import LidarSpec, default_rig, road_points

SPEC = LidarSpec()
RIG = default_rig()
FRONT = RIG.cameras[RIG.names.index("FRONT")]


def geometry() -> SensorGeometry:
    return SensorGeometry(RIG, SPEC, (-5.0, 5.0), (-math.pi / 4, math.pi / 4), 0.2)


def flat_ground() -> np.ndarray:
    """The range map of an empty flat road: each downward beam meets the road, the rest see nothing."""
    el = SPEC.elevations()
    ranges = np.where(el < 0, SPEC.mount_height / np.sin(-np.minimum(el, -1e-9)), 0.0)
    ranges = np.where(ranges <= SPEC.max_range, ranges, 0.0)
    return np.repeat(ranges[:, None], SPEC.azimuth, axis=1).astype(np.float32)


def with_wall(ranges: np.ndarray, distance: float, half_width: float, top: float) -> np.ndarray:
    """``ranges`` with a vertical face at ``distance`` m ahead, ``half_width`` m to each side and
    ``top`` m above the road, where it is nearer than what the ray already hits."""
    out = ranges.copy()
    rays = SPEC.ray_directions()
    r = distance / np.maximum(rays[..., 0], 1e-9)
    y, z = r * rays[..., 1], SPEC.mount_height + r * rays[..., 2]
    hit = (rays[..., 0] > 0) & (np.abs(y) <= half_width) & (z >= 0) & (z <= top)
    hit &= (out == 0) | (r < out)
    out[hit] = r[hit]
    return out


# -- the members --


def test_the_zoo_has_at_least_24_named_versioned_seeded_members_of_three_families():
    members = zoo.members()
    assert len(members) >= 24
    assert {m.family for m in members.values()} == set(zoo.FAMILIES)
    assert len({m.seed for m in members.values()}) == len(members)
    for name, m in members.items():
        assert m.name == name and m.version >= 1 and m.description
        assert zoo.member(m.citation) is m
    with pytest.raises(ValueError, match="version 1"):
        zoo.member("gap_keeper@v9")
    with pytest.raises(ValueError, match="unknown zoo policy"):
        zoo.member("no_such_driver")


class TrafficGuard(Mapping):
    """An env's ``info`` that lets a policy read only the ego's own status: reading anything else
    (a traffic field, the episode's metrics, the bridge) fails the test."""

    def __init__(self, info: Mapping) -> None:
        self._info = info

    def __getitem__(self, key: str):
        if key not in EGO_STATUS_KEYS:
            raise AssertionError(f"a zoo policy read info[{key!r}]")
        return self._info[key]

    def __iter__(self) -> Iterator[str]:
        raise AssertionError("a zoo policy iterated over info")

    def __len__(self) -> int:
        raise AssertionError("a zoo policy asked info's size")

    def get(self, key, default=None):
        return self[key]


@pytest.mark.parametrize("name", list(zoo.members()))
def test_no_member_reads_the_traffic_state(name):
    """Each member drives from the cameras, the LiDAR and the ego's speed alone: its inputs are an
    observation without "state", an info that refuses every other key, and a geometry that holds no
    traffic; the same sensors and speed under a different traffic state give the same action."""
    env = gym.make("M4World-v0", scenario="merge_cut_in", config={"observation_keys": list(SENSOR_KEYS)})
    obs, info = env.reset(seed=1)
    geo = SensorGeometry.of_env(env)
    assert not any(hasattr(v, "bridge") or hasattr(v, "road") for v in vars(geo).values())
    policy, twin = zoo.member(name).build(geo, 7), zoo.member(name).build(geo, 7)
    for _ in range(4):
        action = policy(obs, TrafficGuard(info))
        other = {**info, "lane_index": 99, "crashed": True, "on_road": False, "bridge": object()}
        assert np.array_equal(twin(obs, TrafficGuard(other)), action)
        assert action.shape == (2,) and action.dtype == np.float32 and np.all(np.abs(action) <= 1)
        obs, _, terminated, truncated, info = env.step(action)
        if terminated or truncated:
            break


def test_m4world_eval_runs_every_member():
    """``--policy NAME`` builds every member per episode, and replays an episode from its seed."""
    for name in zoo.members():
        report = evaluate(EvalRequest(name, ["highway_sunny_day"], episodes=1, seed=4, max_steps=2), progress=False)
        assert report["episodes"][0]["steps"] == 2
        assert report["policy"] == name
    again = evaluate(
        EvalRequest("gap_keeper@v1", ["highway_sunny_day"], episodes=1, seed=4, max_steps=2), progress=False
    )
    first = evaluate(EvalRequest("gap_keeper", ["highway_sunny_day"], episodes=1, seed=4, max_steps=2), progress=False)
    assert again["episodes"] == first["episodes"]


def test_a_member_that_sees_nothing_ahead_crashes_where_one_that_sees_keeps_its_distance():
    """On the rainy highway, seed 1, a car ahead is slower: the gap keeper brakes for it; the same
    driver with its forward LiDAR sector blinded drives into it."""
    kwargs = {"episodes": 1, "seed": 1, "max_steps": 30}
    sees = evaluate(EvalRequest("gap_keeper", ["highway_dense_rain_dusk"], **kwargs), progress=False)["episodes"][0]
    blind = evaluate(
        EvalRequest("gap_keeper_blind_front_lidar", ["highway_dense_rain_dusk"], **kwargs), progress=False
    )["episodes"][0]
    assert sees["collision"] == 0.0 and blind["collision"] == 1.0
    assert sees["pdms"] > 0.4 > blind["pdms"]


def test_zoo_policies_refuse_discrete_actions():
    env = gym.make("M4World-v0", scenario="highway_sunny_day", config={"action_type": "discrete_meta"})
    env.reset(seed=0)
    with pytest.raises(ValueError, match="continuous"):
        make_policy("gap_keeper", env)


# -- geometry --


def test_actions_map_physical_controls_to_the_action_space_and_back():
    geo = geometry()
    assert np.allclose(geo.action(0.0, 0.0), [0.0, 0.0])
    assert np.allclose(geo.action(2.5, -math.pi / 8), [0.5, -0.5])
    assert np.allclose(geo.action(50.0, 9.0), [1.0, 1.0])  # clipped
    assert np.allclose(geo.action(math.nan, math.inf), [0.0, 0.0])  # a misread coasts straight
    acc, steer = geo.controls(np.array([0.5, -0.5], dtype=np.float32))
    assert acc == pytest.approx(2.5) and steer == pytest.approx(-math.pi / 8)


# -- LiDAR perception --


def test_beam_band_selects_the_beams_by_elevation():
    el = np.rad2deg(SPEC.elevations())
    band = beam_band(SPEC, -2.0, 2.0)
    assert np.all((el[band] >= -2) & (el[band] <= 2)) and band.sum() == 3  # 1.29 deg apart: 0.97, -0.32, -1.61


def test_forward_gap_sees_a_wall_ahead_and_not_the_road():
    ground = flat_ground()
    all_beams = beam_band(SPEC, -90, 90)
    assert forward_gap(ground, SPEC, half_width_m=1.3, beams=all_beams) == math.inf
    wall = with_wall(ground, 10.0, half_width=1.0, top=1.5)
    assert forward_gap(wall, SPEC, half_width_m=1.3, beams=all_beams) == pytest.approx(10.0, abs=0.01)
    # The horizon beams pass over a car's roof 10 m ahead (the LiDAR is 1.84 m up; the lowest of
    # them, -1.61 deg, is 1.56 m up there) but meet a truck's back.
    horizon = beam_band(SPEC, -2, 2)
    assert forward_gap(wall, SPEC, half_width_m=1.3, beams=horizon) == math.inf
    truck = with_wall(ground, 10.0, half_width=1.0, top=3.0)
    assert forward_gap(truck, SPEC, half_width_m=1.3, beams=horizon) == pytest.approx(10.0, abs=0.01)
    # Beside the corridor (5 m to the left), it is not in the way.
    side = with_wall(ground, 10.0, half_width=0.5, top=1.5)
    side = np.roll(side, -int(round(math.atan2(5.0, 10.0) / (2 * math.pi) * SPEC.azimuth)), axis=1)
    assert forward_gap(side, SPEC, half_width_m=1.3, beams=all_beams) == math.inf
    # A low kerb 0.3 m high is ground, by the obstacle height threshold.
    kerb = with_wall(ground, 10.0, half_width=1.0, top=0.3)
    assert forward_gap(kerb, SPEC, half_width_m=1.3, beams=all_beams) == math.inf


# -- camera perception --


def paint_lines(lateral_m: list[float], road: int = 90, paint: int = 230) -> np.ndarray:
    """A FRONT image of a grey road with white lines at ``lateral_m`` (+ left), 0.2 m wide, drawn
    by projecting road points through the camera."""
    img = np.full((FRONT.height, FRONT.width, 3), road, dtype=np.uint8)
    rows, cols = np.mgrid[FRONT.height // 2 + 1 : FRONT.height, 0 : FRONT.width]
    xy = road_points(FRONT, SPEC.mount_height, cols.ravel() + 0.5, rows.ravel() + 0.5)
    for y in lateral_m:
        on = np.abs(xy[:, 1] - y) < 0.1 + 0.5 * np.abs(xy[:, 0]) / FRONT.K[0, 0]  # at least one pixel wide
        img[rows.ravel()[on], cols.ravel()[on]] = paint
    return img


def test_marking_peaks_keep_narrow_bright_runs_only():
    lum = np.full((1, 20), 100.0)
    lum[0, 3:5] = 200  # a line, 2 px
    lum[0, 10:17] = 200  # a light car, 7 px
    peaks = marking_peaks(lum, min_contrast=30, max_width_px=4)
    assert np.flatnonzero(peaks[0]).tolist() == [3, 4]


def test_lane_markings_find_both_sides_and_the_centre():
    seen = lane_markings(
        paint_lines([2.0, -2.0, 6.0]), FRONT, SPEC.mount_height, band_rows=20, min_contrast=30, max_width_px=6
    )
    assert seen.left_m == pytest.approx(2.0, abs=0.2) and seen.right_m == pytest.approx(-2.0, abs=0.2)
    assert seen.centre_m == pytest.approx(0.0, abs=0.15) and abs(seen.heading) < 0.05
    off = lane_markings(
        paint_lines([1.2, -2.8]), FRONT, SPEC.mount_height, band_rows=20, min_contrast=30, max_width_px=6
    )
    assert off.centre_m == pytest.approx(-0.8, abs=0.15)  # the lane's centre is 0.8 m to the right
    nothing = lane_markings(paint_lines([]), FRONT, SPEC.mount_height, band_rows=20, min_contrast=30, max_width_px=6)
    assert math.isnan(nothing.centre_m)


def test_one_marking_puts_the_centre_half_a_lane_away():
    assert Markings(1.5, math.nan, 0.0).centre_m == pytest.approx(1.5 - LANE_WIDTH_M / 2)
    assert Markings(math.nan, -2.5, 0.0).centre_m == pytest.approx(-2.5 + LANE_WIDTH_M / 2)


def test_the_modular_driver_steers_toward_the_lane_centre_and_brakes_for_a_wall():
    geo = geometry()
    driver = ModularDriver(geo, GapKeeping(), LaneCentring(smoothing=1.0))
    cams = np.repeat(paint_lines([1.2, -2.8])[None], RIG.num_views, axis=0)
    action = driver({"cameras": cams, "lidar": flat_ground()}, {"speed": 20.0})
    acc, steer = geo.controls(action)
    assert steer > 0  # the centre is to the right: + turns right
    assert 0 < acc <= GapKeeping().accel_change + 1e-6  # free road, below cruise speed: rate-limited speed-up
    braking = ModularDriver(geo, GapKeeping(), LaneCentring())
    wall = with_wall(flat_ground(), 9.0, half_width=1.0, top=1.5)
    acc, _ = geo.controls(braking({"cameras": cams, "lidar": wall}, {"speed": 20.0}))
    assert acc == pytest.approx(-GapKeeping().max_brake, abs=1e-5)


# -- perturbations --


class Fixed(ModularDriver):
    """A driver that returns its step count as the acceleration (to see the delay)."""

    def __init__(self) -> None:
        super().__init__(geometry(), GapKeeping(), LaneCentring())
        self.calls, self.seen = 0, None

    def drive(self, obs, status):
        self.calls += 1
        self.seen = obs
        return np.array([self.calls / 10, 0.0], dtype=np.float32)


def test_a_delay_coasts_first_then_replays_the_commands_in_order():
    inner = Fixed()
    late = Perturbed(inner, np.random.default_rng(0), delay_steps=2)
    obs = {"cameras": np.zeros((6, 64, 112, 3), np.uint8), "lidar": flat_ground()}
    got = [late(obs, {"speed": 10.0})[0] for _ in range(4)]
    assert got == pytest.approx([0.0, 0.0, 0.1, 0.2])


def test_blinded_and_noisy_sensors_change_only_what_they_name():
    inner = Fixed()
    pert = Perturbed(
        inner, np.random.default_rng(0), blind_views=("FRONT",), blind_lidar_deg=(-30, 30), lidar_dropout=0.0
    )
    cams = np.full((6, 64, 112, 3), 120, np.uint8)
    lidar = flat_ground()
    pert({"cameras": cams, "lidar": lidar}, {"speed": 10.0})
    seen = inner.seen
    assert seen["cameras"][RIG.names.index("FRONT")].max() == 0 and seen["cameras"][0].min() == 120
    az = np.rad2deg(SPEC.azimuths())
    assert (seen["lidar"][:, np.abs(az) < 29] == 0).all() and (
        seen["lidar"][:, np.abs(az) > 31] == lidar[:, np.abs(az) > 31]
    ).all()
    assert cams.min() == 120 and lidar.max() > 0  # the env's arrays are untouched
    drop = Perturbed(Fixed(), np.random.default_rng(0), lidar_dropout=0.5)
    drop({"cameras": cams, "lidar": lidar}, {"speed": 10.0})
    lost = (drop.inner.seen["lidar"] == 0) & (lidar > 0)
    assert 0.45 < lost.sum() / (lidar > 0).sum() < 0.55

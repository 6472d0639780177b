"""A faster highway-env road: the same vehicles and rules, with the hot loops vectorized.

highway-env's ``Road`` spends its time in three O(N^2) Python loops (issues #36, #121, #223):
every IDM vehicle scans every other vehicle to find its neighbours, every vehicle tests every
other one for collisions, and every vehicle projects itself on every lane to find its lane. Here
the same quantities are computed with numpy, once per simulation step, and the answers are
identical to highway-env's (same formulas, same tie-breaking):

* :meth:`FastRoad.neighbour_vehicles` projects all objects on the queried lane at once, caching
  the projection while positions do not change (the "act" phase);
* :meth:`FastRoad.step` defers each vehicle's lane lookup and does it for all vehicles in one
  :meth:`FastNetwork.closest_lane_indices` call, and only runs highway-env's exact polygon test on
  pairs that pass the same bounding-circle test highway-env uses.
"""

from __future__ import annotations

import bisect

import numpy as np
from highway_env.road.lane import AbstractLane, CircularLane, SineLane, StraightLane
from highway_env.road.road import LaneIndex, Road, RoadNetwork
from highway_env.vehicle.behavior import IDMVehicle
from highway_env.vehicle.controller import MDPVehicle
from highway_env.vehicle.kinematics import Vehicle
from highway_env.vehicle.objects import Landmark, Obstacle

from m4world_env.traffic.fastmath import FastControlMixin, FastIDMMixin
from m4world_env.traffic.polyline import PolylineLane

# highway-env's AbstractLane.on_lane margin used by Road.neighbour_vehicles.
NEIGHBOUR_LANE_MARGIN = 1.0


def _wrap(a: np.ndarray) -> np.ndarray:
    return (a + np.pi) % (2 * np.pi) - np.pi


def lane_coordinates(lane: AbstractLane, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vectorized ``lane.local_coordinates``. points: (N, 2) -> (s, lateral), each (N,)."""
    if isinstance(lane, StraightLane):  # SineLane included
        d = points - lane.start
        s = d @ lane.direction
        r = d @ lane.direction_lateral
        if isinstance(lane, SineLane):
            r = r - lane.amplitude * np.sin(lane.pulsation * s + lane.phase)
        return s, r
    if isinstance(lane, CircularLane):
        d = points - lane.center
        phi = np.arctan2(d[:, 1], d[:, 0])
        phi = lane.start_phase + _wrap(phi - lane.start_phase)
        rr = np.hypot(d[:, 0], d[:, 1])
        return lane.direction * (phi - lane.start_phase) * lane.radius, lane.direction * (lane.radius - rr)
    if isinstance(lane, PolylineLane):
        return lane.polyline.project(points)
    coords = np.array([lane.local_coordinates(p) for p in points]).reshape(-1, 2)
    return coords[:, 0], coords[:, 1]


def lane_headings(lane: AbstractLane, s: np.ndarray) -> np.ndarray:
    """Vectorized ``lane.heading_at``. s: (N,) -> (N,)."""
    if isinstance(lane, SineLane):
        return lane.heading + np.arctan(lane.amplitude * lane.pulsation * np.cos(lane.pulsation * s + lane.phase))
    if isinstance(lane, StraightLane):
        return np.full_like(s, lane.heading)
    if isinstance(lane, CircularLane):
        return lane.direction * s / lane.radius + lane.start_phase + np.pi / 2 * lane.direction
    if isinstance(lane, PolylineLane):
        return lane.polyline.heading(s)
    return np.array([lane.heading_at(x) for x in s])


class FastNetwork(RoadNetwork):
    """A RoadNetwork whose closest-lane search handles many positions and lanes at once."""

    _tables: tuple | None = None

    def _lane_tables(self) -> tuple:
        """Lane parameters stacked per lane family, in RoadNetwork's lane order (so that argmin
        ties resolve as in highway-env). Rebuilt if lanes were added."""
        idx = [(f, t, i) for f, tos in self.graph.items() for t, lanes in tos.items() for i in range(len(lanes))]
        if self._tables is not None and self._tables[0] == idx:
            return self._tables
        lanes = [self.graph[f][t][i] for f, t, i in idx]
        straight = [k for k, ln in enumerate(lanes) if isinstance(ln, StraightLane)]
        circular = [k for k, ln in enumerate(lanes) if isinstance(ln, CircularLane)]
        other = [k for k in range(len(lanes)) if k not in set(straight) | set(circular)]
        st = [lanes[k] for k in straight]
        sine = [(ln.amplitude, ln.pulsation, ln.phase) if isinstance(ln, SineLane) else (0.0, 0.0, 0.0) for ln in st]
        st_arr = {
            "start": np.array([ln.start for ln in st]).reshape(-1, 2),
            "dir": np.array([ln.direction for ln in st]).reshape(-1, 2),
            "lat": np.array([ln.direction_lateral for ln in st]).reshape(-1, 2),
            "heading": np.array([ln.heading for ln in st]),
            "sine": np.array(sine).reshape(-1, 3),
        }
        ci = [lanes[k] for k in circular]
        ci_arr = {
            "center": np.array([ln.center for ln in ci]).reshape(-1, 2),
            "radius": np.array([ln.radius for ln in ci]),
            "phase": np.array([ln.start_phase for ln in ci]),
            "dir": np.array([ln.direction for ln in ci], dtype=np.float64),
        }
        lengths = np.array([ln.length for ln in lanes])
        self._tables = (idx, lanes, lengths, (straight, st_arr), (circular, ci_arr), other)
        return self._tables

    def closest_lane_indices(self, positions: np.ndarray, headings: np.ndarray | None) -> list[LaneIndex]:
        """``get_closest_lane_index`` for (N, 2) positions and (N,) headings (or None)."""
        idx, lanes, lengths, (straight, st), (circular, ci), other = self._lane_tables()
        n = len(positions)
        s_all, r_all, h_all = np.empty((len(lanes), n)), np.empty((len(lanes), n)), np.empty((len(lanes), n))
        if straight:
            d = positions[None, :, :] - st["start"][:, None, :]
            s = np.einsum("lnk,lk->ln", d, st["dir"])
            amp, puls, phase = (st["sine"][:, j : j + 1] for j in range(3))
            s_all[straight] = s
            r_all[straight] = np.einsum("lnk,lk->ln", d, st["lat"]) - amp * np.sin(puls * s + phase)
            h_all[straight] = st["heading"][:, None] + np.arctan(amp * puls * np.cos(puls * s + phase))
        if circular:
            d = positions[None, :, :] - ci["center"][:, None, :]
            sp, rad, dr = ci["phase"][:, None], ci["radius"][:, None], ci["dir"][:, None]
            phi = sp + _wrap(np.arctan2(d[..., 1], d[..., 0]) - sp)
            s = dr * (phi - sp) * rad
            s_all[circular] = s
            r_all[circular] = dr * (rad - np.hypot(d[..., 0], d[..., 1]))
            h_all[circular] = dr * s / rad + sp + np.pi / 2 * dr
        for k in other:
            s_all[k], r_all[k] = lane_coordinates(lanes[k], positions)
            h_all[k] = lane_headings(lanes[k], s_all[k])
        length = lengths[:, None]
        cost = np.abs(r_all) + np.maximum(s_all - length, 0) + np.maximum(-s_all, 0)
        if headings is not None:
            cost += np.abs(_wrap(headings[None, :] - h_all))
        return [idx[k] for k in np.argmin(cost, axis=0)]

    def get_closest_lane_index(self, position: np.ndarray, heading: float | None = None) -> LaneIndex:
        h = None if heading is None else np.array([heading], dtype=np.float64)
        return self.closest_lane_indices(np.asarray(position, dtype=np.float64)[None, :], h)[0]


class _DeferredLaneUpdate:
    """Skips the per-vehicle lane search while the road updates all lanes in one batch."""

    road: FastRoad

    def on_state_update(self) -> None:
        if not getattr(self.road, "defer_lane_updates", False):
            super().on_state_update()  # type: ignore[misc]


class TrafficVehicle(_DeferredLaneUpdate, FastIDMMixin, IDMVehicle):
    """An IDM/MOBIL vehicle (highway-env's), with its lane found in batch."""


class EgoVehicle(_DeferredLaneUpdate, FastControlMixin, Vehicle):
    """Ego under continuous [acceleration, steering] control."""


class EgoMetaVehicle(_DeferredLaneUpdate, FastControlMixin, MDPVehicle):
    """Ego under DiscreteMetaAction control (MDPVehicle's target speeds and lane changes)."""


class FastRoad(Road):
    """highway-env's Road with vectorized neighbour search, lane updates and collision pre-check."""

    def __init__(self, network: FastNetwork, np_random: np.random.Generator) -> None:
        super().__init__(network=network, np_random=np_random)
        self.defer_lane_updates = False
        self._snapshot: tuple[list, np.ndarray, dict[int, int], dict] | None = None

    def invalidate(self) -> None:
        """Forget cached positions (call after moving, adding or removing anything)."""
        self._snapshot = None

    def _entities(self) -> tuple[list, np.ndarray, dict[int, int], dict]:
        snap = self._snapshot
        if snap is None or len(snap[0]) != len(self.vehicles) + len(self.objects):
            ents = [*self.vehicles, *self.objects]
            pos = np.array([e.position for e in ents], dtype=np.float64).reshape(-1, 2)
            snap = (ents, pos, {id(e): k for k, e in enumerate(ents)}, {})
            self._snapshot = snap
        return snap

    def _lane_table(self, lane: AbstractLane) -> tuple[np.ndarray, list[float], list[int]]:
        """Every entity's longitudinal coordinate on ``lane``, and the on-lane ones sorted by it."""
        ents, pos, _, per_lane = self._entities()
        table = per_lane.get(id(lane))
        if table is None:
            s_all, r_all = lane_coordinates(lane, pos)
            on = (np.abs(r_all) <= lane.width_at(0) / 2 + NEIGHBOUR_LANE_MARGIN) & (
                (s_all >= -lane.VEHICLE_LENGTH) & (s_all < lane.length + lane.VEHICLE_LENGTH)
            )
            ks = [int(k) for k in np.flatnonzero(on) if not isinstance(ents[k], Landmark)]
            ks.sort(key=lambda k: (s_all[k], k))
            table = (s_all, [float(s_all[k]) for k in ks], ks)
            per_lane[id(lane)] = table
        return table

    def neighbour_vehicles(self, vehicle: Vehicle, lane_index: LaneIndex = None) -> tuple:
        """Preceding and following object of ``vehicle`` on ``lane_index``: highway-env's answer
        (front = nearest at s' >= s, last of equals; rear = nearest at s' < s, first of equals)."""
        lane_index = lane_index or vehicle.lane_index
        if not lane_index or vehicle is None:
            return None, None
        ents, _, where, _ = self._entities()
        if not ents:
            return None, None
        lane = self.network.get_lane(lane_index)
        s_all, s_sorted, ks = self._lane_table(lane)
        k_self = where.get(id(vehicle), -1)
        s = float(s_all[k_self]) if k_self >= 0 else lane.local_coordinates(vehicle.position)[0]
        i = bisect.bisect_left(s_sorted, s)
        v_front = v_rear = None
        j = i
        while j < len(ks) and ks[j] == k_self:
            j += 1
        if j < len(ks):
            best = j
            while best + 1 < len(ks) and s_sorted[best + 1] == s_sorted[j]:
                best += 1
            if ks[best] == k_self:
                best -= 1
            v_front = ents[ks[best]]
        j = i - 1
        while j >= 0 and ks[j] == k_self:
            j -= 1
        if j >= 0:
            first = j
            while first - 1 >= 0 and s_sorted[first - 1] == s_sorted[j] and ks[first - 1] != k_self:
                first -= 1
            v_rear = ents[ks[first]]
        return v_front, v_rear

    def act(self) -> None:
        self.invalidate()
        super().act()

    def step(self, dt: float) -> None:
        """Move vehicles and scripted objects by ``dt``, update lanes, resolve collisions."""
        self.defer_lane_updates = True
        try:
            for v in self.vehicles:
                v.step(dt)
        finally:
            self.defer_lane_updates = False
        for o in self.objects:
            if hasattr(o, "advance"):
                o.advance(dt)
        self.invalidate()
        self._update_lanes()
        self._collisions(dt)

    def _update_lanes(self) -> None:
        if not self.vehicles:
            return
        pos = np.array([v.position for v in self.vehicles], dtype=np.float64)
        head = np.array([v.heading for v in self.vehicles], dtype=np.float64)
        for v, idx in zip(self.vehicles, self.network.closest_lane_indices(pos, head), strict=True):
            v.lane_index = idx
            v.lane = self.network.get_lane(idx)

    def _collisions(self, dt: float) -> None:
        vs, obs = self.vehicles, self.objects
        if not vs:
            return
        ents = [*vs, *obs]
        nv = len(vs)
        # One pass over the entities (position, heading, speed, diagonal, half length and width).
        state = np.array(
            [(*e.position, e.heading, e.speed, e.diagonal, e.LENGTH / 2, e.WIDTH / 2) for e in ents], dtype=np.float64
        )
        pos, head, speed, diag = state[:, :2], state[:, 2], state[:, 3], state[:, 4]
        d = pos[:nv, None, :] - pos[None, :, :]
        dist = np.sqrt(np.add.reduce(d * d, axis=-1))  # = np.linalg.norm(d, axis=-1), bit for bit
        # highway-env's bounding-circle pre-check, seen from the vehicle that checks.
        close = dist <= (diag[:nv, None] + diag[None, :]) / 2 + speed[:nv, None] * dt
        close &= np.arange(len(ents))[None, :] > np.arange(nv)[:, None]
        ii, jj = np.nonzero(close)
        if not len(ii):
            return
        # Exact, conservative rectangle test of every close pair at once: pairs surely apart after
        # the step skip highway-env's per-pair polygon test, which keeps the last word otherwise.
        # Displacement = highway-env's velocity (speed * (cos, sin) of the heading) * dt.
        disp = (speed * dt)[:, None] * np.stack([np.cos(head), np.sin(head)], axis=1)
        for i, j in zip(*[ix[~swept_apart(pos, head, state[:, 5:7], disp, ii, jj)] for ix in (ii, jj)], strict=True):
            vs[i].handle_collisions(ents[j], dt)


SEPARATION_MARGIN_M = 1e-6  # float slack: a pair closer than this is left to highway-env's test


def swept_apart(
    pos: np.ndarray, head: np.ndarray, half: np.ndarray, disp: np.ndarray, ii: np.ndarray, jj: np.ndarray
) -> np.ndarray:
    """(P,) True where rectangles ii and jj cannot touch during the step (separating-axis test).

    pos (N, 2) centres, head (N,) headings, half (N, 2) half length/width, disp (N, 2) displacement
    over the step. Mirrors ``highway_env.utils.are_polygons_intersecting``: on each of the four
    edge normals, a's interval is extended by the relative displacement; a pair is apart when
    some axis separates the intervals by more than :data:`SEPARATION_MARGIN_M` (then highway-env
    reports neither ``intersecting`` nor ``will_intersect``, so skipping it changes nothing).
    """
    cos, sin = np.cos(head), np.sin(head)
    k2 = np.concatenate([ii, jj])
    c2, s2 = cos[k2], sin[k2]
    # (P, 4, 2) unit normals: each rectangle's two edge directions, a's then b's.
    p = len(ii)
    ax_x = np.concatenate([c2[:p, None], c2[p:, None], -s2[:p, None], -s2[p:, None]], axis=1)
    ax_y = np.concatenate([s2[:p, None], s2[p:, None], c2[:p, None], c2[p:, None]], axis=1)

    def interval(k: np.ndarray, c: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        centre = ax_x * pos[k, 0:1] + ax_y * pos[k, 1:2]
        along = np.abs(ax_x * c[:, None] + ax_y * s[:, None])
        across = np.abs(-ax_x * s[:, None] + ax_y * c[:, None])
        radius = half[k, 0:1] * along + half[k, 1:2] * across
        return centre - radius, centre + radius

    min_a, max_a = interval(ii, c2[:p], s2[:p])
    min_b, max_b = interval(jj, c2[p:], s2[p:])
    rel = disp[ii] - disp[jj]
    shift = ax_x * rel[:, 0:1] + ax_y * rel[:, 1:2]
    min_a, max_a = min_a + np.minimum(shift, 0.0), max_a + np.maximum(shift, 0.0)
    gap = np.where(min_a < min_b, min_b - max_a, min_a - max_b)
    return (gap > SEPARATION_MARGIN_M).any(axis=1)


def size_object(obj: Vehicle | Obstacle, length: float, width: float) -> None:
    """Give one highway-env object its own footprint (their sizes are class constants)."""
    obj.LENGTH, obj.WIDTH = float(length), float(width)
    obj.diagonal = float(np.hypot(length, width))

"""Polylines as lanes and routes: projection onto a piecewise-linear curve, and a highway-env lane on it.

:class:`Polyline` is frame-agnostic numpy (used in our frame for the logged route, in highway-env's
for lanes). Its local coordinates follow highway-env's ``StraightLane``: ``s`` is the arc length of
the nearest point, ``lateral`` the offset along the segment's left normal ``(-dy, dx)``; before the
first and past the last vertex the end segments extend straight on.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from highway_env.road.lane import AbstractLane, LineType, PolyLaneFixedWidth

MIN_SEGMENT_M = 1e-3  # vertices closer than this to the previous one are dropped


@dataclass(frozen=True, eq=False)
class Polyline:
    """A piecewise-linear curve. ``points`` (N, 2) with N >= 2 distinct vertices."""

    points: np.ndarray

    @classmethod
    def from_points(cls, points: Sequence[Sequence[float]] | np.ndarray) -> Polyline:
        """Drops repeated vertices; raises ValueError when fewer than two distinct ones remain."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        if len(p) == 0:
            raise ValueError("a polyline needs at least two distinct points, got none")
        keep = [0]
        for i in range(1, len(p)):
            if np.hypot(*(p[i] - p[keep[-1]])) > MIN_SEGMENT_M:
                keep.append(i)
        if len(keep) < 2:
            raise ValueError(f"a polyline needs at least two distinct points, got {len(p)} at one place")
        return cls(p[keep])

    @cached_property
    def segments(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Segment starts (M, 2), unit directions (M, 2), lengths (M,)."""
        d = np.diff(self.points, axis=0)
        lengths = np.hypot(d[:, 0], d[:, 1])
        return self.points[:-1], d / lengths[:, None], lengths

    @cached_property
    def cumulative(self) -> np.ndarray:
        """(N,) arc length at each vertex."""
        return np.concatenate([[0.0], np.cumsum(self.segments[2])])

    @property
    def length(self) -> float:
        return float(self.cumulative[-1])

    def project(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(K, 2) points -> (s, lateral), each (K,): the nearest segment's coordinates."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        starts, dirs, lengths = self.segments
        rel = xy[:, None, :] - starts[None, :, :]  # (K, M, 2)
        along = np.einsum("kmi,mi->km", rel, dirs)
        across = rel[..., 1] * dirs[None, :, 0] - rel[..., 0] * dirs[None, :, 1]
        lo = np.zeros_like(lengths)
        hi = lengths.copy()
        lo[0], hi[-1] = -np.inf, np.inf  # the end segments extend straight on
        clipped = np.clip(along, lo, hi)
        dist2 = (along - clipped) ** 2 + across**2
        k = np.argmin(dist2, axis=1)  # ties: the earlier segment
        rows = np.arange(len(xy))
        return self.cumulative[k] + clipped[rows, k], across[rows, k]

    def position(self, s: float, lateral: float = 0.0) -> np.ndarray:
        """(2,) point at arc length ``s`` (extended past the ends), ``lateral`` to the left."""
        starts, dirs, _ = self.segments
        k = self._segment(s)
        d = dirs[k]
        return starts[k] + (s - self.cumulative[k]) * d + lateral * np.array([-d[1], d[0]])

    def heading(self, s: np.ndarray | float) -> np.ndarray:
        """Heading (radians) of the segment at arc length ``s``."""
        _, dirs, _ = self.segments
        d = dirs[self._segment(s)]
        return np.arctan2(d[..., 1], d[..., 0])

    def _segment(self, s: np.ndarray | float) -> np.ndarray:
        cum = self.cumulative
        return np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(cum) - 2)

    def offset(self, lateral: float) -> Polyline:
        """The curve shifted ``lateral`` along the left normal (vertex normals: mean of the two
        adjacent segments', so a corner is cut, not folded, for offsets well under its radius)."""
        _, dirs, _ = self.segments
        normals = np.stack([-dirs[:, 1], dirs[:, 0]], axis=1)
        at_vertex = np.concatenate([normals[:1], normals[:-1] + normals[1:], normals[-1:]])
        at_vertex /= np.maximum(np.hypot(at_vertex[:, 0], at_vertex[:, 1]), 1e-9)[:, None]
        return Polyline.from_points(self.points + lateral * at_vertex)


class PolylineLane(PolyLaneFixedWidth):
    """highway-env's fixed-width polyline lane with exact, vectorized nearest-segment coordinates.

    ``PolyLaneFixedWidth`` projects by scanning its 1 m samples from the end for the first one
    behind the point, which is slow and, on a curve, can pick a sample on the far side of a bend;
    here every coordinate comes from :class:`Polyline`. Points are in highway-env's frame.
    """

    def __init__(
        self,
        points: Sequence[Sequence[float]] | np.ndarray,
        width: float = AbstractLane.DEFAULT_WIDTH,
        line_types: tuple[LineType, LineType] | None = None,
        speed_limit: float = 20.0,
    ) -> None:
        self.polyline = Polyline.from_points(points)
        super().__init__(
            [tuple(p) for p in self.polyline.points], width=width, line_types=line_types, speed_limit=speed_limit
        )
        self.length = self.polyline.length

    def position(self, longitudinal: float, lateral: float) -> np.ndarray:
        return self.polyline.position(longitudinal, lateral)

    def local_coordinates(self, position: np.ndarray) -> tuple[float, float]:
        s, r = self.polyline.project(np.asarray(position, dtype=np.float64)[None, :])
        return float(s[0]), float(r[0])

    def heading_at(self, longitudinal: float) -> float:
        return float(self.polyline.heading(longitudinal))


def points_in_polygons(points: np.ndarray, polygons: Sequence[np.ndarray]) -> np.ndarray:
    """(K,) bool: each of the (K, 2) ``points`` lies inside at least one polygon (even-odd rule)."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    inside = np.zeros(len(points), dtype=bool)
    x, y = points[:, 0:1], points[:, 1:2]
    for poly in polygons:
        a = np.asarray(poly, dtype=np.float64).reshape(-1, 2)
        b = np.roll(a, -1, axis=0)
        crosses = (a[None, :, 1] > y) != (b[None, :, 1] > y)
        dy = np.where(b[:, 1] == a[:, 1], 1e-300, b[:, 1] - a[:, 1])
        x_cross = a[None, :, 0] + (y - a[None, :, 1]) * (b[None, :, 0] - a[None, :, 0]) / dy[None, :]
        inside |= (np.count_nonzero(crosses & (x < x_cross), axis=1) % 2) == 1
    return inside

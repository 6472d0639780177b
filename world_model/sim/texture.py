"""A world-aligned label texture of the road, rasterized lazily in tiles.

Labels: off-road and road surfaces, each in a few low-frequency variations (so that motion over
the road is visible), painted lane markings and road-edge lines. A palette turns labels into
albedo per weather. Maps can be many kilometres long (highway-env roads are 10 km), so the texture
is split into square tiles that are rasterized the first time a camera pixel lands on them; tiles
without any road geometry all share one off-road tile. The off-road noise is periodic with the tile
size, so tiles join seamlessly.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from world_model.scene import MapGeometry
from world_model.sim.config import SimConfig
from world_model.sim.lighting import Lighting

# Palette brightness spread of the surface variations (fraction of the albedo).
SURFACE_VARIATION = 0.12
FILL, MARKING, EDGE = 0, 1, 2  # primitive kinds


def labels_layout(levels: int) -> tuple[int, int, int, int]:
    """(first off-road label, first road label, marking label, road-edge label)."""
    return 0, levels, 2 * levels, 2 * levels + 1


def surface_variation(levels: int) -> np.ndarray:
    """(levels,) float64 in [-1, 1]: where each surface variation level sits between the darkest
    and the brightest patch (the palette scales the surface's albedo by 1 + SURFACE_VARIATION x this)."""
    return (np.arange(levels) / max(levels - 1, 1) - 0.5) * 2


def palette(lighting: Lighting, levels: int) -> np.ndarray:
    """(256, 3) float32 albedo of every label under ``lighting``."""
    off0, road0, marking, edge = labels_layout(levels)
    pal = np.zeros((256, 3), dtype=np.float32)
    ramp = 1.0 + SURFACE_VARIATION * surface_variation(levels)
    pal[off0 : off0 + levels] = ramp[:, None] * lighting.offroad
    pal[road0 : road0 + levels] = ramp[:, None] * lighting.road
    pal[marking] = lighting.marking
    pal[edge] = lighting.marking
    return pal


def dash_segments(points: np.ndarray, dash: float, gap: float) -> list[np.ndarray]:
    """Split a polyline (N, 2) into dashes of length ``dash`` separated by ``gap`` (arc length)."""
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(seg)])
    total = arc[-1]
    if gap <= 0 or total <= 0:
        return [points]
    out = []
    for s0 in np.arange(0.0, total, dash + gap):
        s1 = min(s0 + dash, total)
        s = np.concatenate([[s0], arc[(arc > s0) & (arc < s1)], [s1]])
        out.append(np.stack([np.interp(s, arc, points[:, 0]), np.interp(s, arc, points[:, 1])], axis=1))
    return out


def periodic_noise(tile: int, cells: int, levels: int, seed: int) -> np.ndarray:
    """(tile, tile) uint8 in [0, levels): bilinear value noise with ``cells`` cells per period."""
    rng = np.random.default_rng(seed)
    coarse = np.tile(rng.random((cells, cells), dtype=np.float32), (3, 3))
    smooth = cv2.resize(coarse, (3 * tile, 3 * tile), interpolation=cv2.INTER_LINEAR)
    smooth = smooth[tile : 2 * tile, tile : 2 * tile]
    return np.minimum((smooth * levels).astype(np.uint8), levels - 1)


class MapTexture:
    """Label lookup at world points; texel (row, col) of the whole texture covers world
    ``x in x0 + res * [col, col + 1)``, ``y in y0 + res * [row, row + 1)``."""

    def __init__(self, m: MapGeometry, config: SimConfig) -> None:
        tile = config.texture_tile_px
        if tile < 16 or tile & (tile - 1):
            raise ValueError(f"SimConfig.texture_tile_px must be a power of two >= 16, got {tile}")
        self.res = config.texture_m_per_px
        self.tile = tile
        self.bits = tile.bit_length() - 1
        self.max_tiles = config.texture_max_tiles
        self.shift = config.subpixel_bits
        levels = config.texture_noise_levels
        _, self.road0, self.marking, self.edge = labels_layout(levels)
        cells = max(1, round(tile * self.res / config.texture_noise_cell_m))
        self.noise = periodic_noise(tile, cells, levels, config.texture_seed)

        self.prims: list[tuple[int, np.ndarray, int]] = []  # (kind, world points (N, 2), thickness px)
        for poly in m.drivable_area:
            self.prims.append((FILL, np.asarray(poly, dtype=np.float64).reshape(-1, 2), 0))
        line_px = max(1, round(config.lane_line_width_m / self.res))
        for ln in m.lane_lines:
            if ln.kind == "none" or len(ln.points) < 2:
                continue
            segs = (
                [ln.points] if ln.kind == "solid" else dash_segments(ln.points, config.dash_length_m, config.dash_gap_m)
            )
            self.prims += [(MARKING, np.asarray(s, dtype=np.float64), line_px) for s in segs]
        edge_px = max(1, round(config.road_edge_width_m / self.res))
        self.prims += [(EDGE, np.asarray(e, dtype=np.float64), edge_px) for e in m.road_edges if len(e) >= 2]
        self.prims = [p for p in self.prims if len(p[1])]
        if self.prims:
            pad = np.array([p[2] * self.res for p in self.prims])[:, None]
            self.boxes = np.concatenate(
                [
                    np.stack([p[1].min(0) for p in self.prims]) - pad,
                    np.stack([p[1].max(0) for p in self.prims]) + pad,
                ],
                axis=1,
            )  # (P, 4): xmin, ymin, xmax, ymax
            lo, hi = self.boxes[:, :2].min(0), self.boxes[:, 2:].max(0)
        else:
            self.boxes = np.zeros((0, 4))
            lo = hi = np.zeros(2)
        tile_m = tile * self.res
        # One geometry-free tile of margin on every side: lookups beyond the grid clamp into it.
        self.x0 = (math.floor(lo[0] / tile_m) - 1) * tile_m
        self.y0 = (math.floor(lo[1] / tile_m) - 1) * tile_m
        self.ntx = int(math.floor(hi[0] / tile_m)) + 2 - int(math.floor(lo[0] / tile_m)) + 1
        self.nty = int(math.floor(hi[1] / tile_m)) + 2 - int(math.floor(lo[1] / tile_m)) + 1
        self._reset_tiles()

    def _reset_tiles(self) -> None:
        self.page = np.full(self.ntx * self.nty, -1, dtype=np.int32)  # tile -> atlas slot, -1 = not yet drawn
        self.atlas = np.empty((min(64, self.max_tiles), self.tile, self.tile), dtype=np.uint8)
        self.atlas[0] = self.noise  # slot 0: the shared off-road tile
        self.used = 1

    @property
    def tiles_drawn(self) -> int:
        """Atlas slots in use (the shared off-road tile included)."""
        return self.used

    def lookup(self, wx: np.ndarray, wy: np.ndarray) -> np.ndarray:
        """Labels (uint8) at world points ``wx``, ``wy`` (same shape)."""
        col = np.floor((np.asarray(wx, dtype=np.float64) - self.x0) / self.res).astype(np.int32)
        row = np.floor((np.asarray(wy, dtype=np.float64) - self.y0) / self.res).astype(np.int32)
        return self._at_texels(col.reshape(-1), row.reshape(-1)).reshape(col.shape)

    def lookup_ego(self, points: np.ndarray, x: float, y: float, yaw: float) -> np.ndarray:
        """Labels (G,) at ego-frame points ``points`` (G, 1, 2) float32 of an ego at world (x, y, yaw)."""
        c, s, inv = math.cos(yaw) / self.res, math.sin(yaw) / self.res, 1.0 / self.res
        to_texels = np.array([[c, -s, (x - self.x0) * inv], [s, c, (y - self.y0) * inv]])
        cols, rows = cv2.split(cv2.transform(points, to_texels))
        # Truncation equals floor inside the grid; outside it only the off-road tile is read.
        return self._at_texels(cols.astype(np.int32).reshape(-1), rows.astype(np.int32).reshape(-1))

    def _at_texels(self, col: np.ndarray, row: np.ndarray) -> np.ndarray:
        """Labels at integer texel coordinates (int32, modified in place)."""
        tiles = row >> self.bits
        np.clip(tiles, 0, self.nty - 1, out=tiles)
        tiles *= self.ntx
        tx = col >> self.bits
        np.clip(tx, 0, self.ntx - 1, out=tx)
        tiles += tx
        slot = np.take(self.page, tiles)
        if len(slot) and slot.min() < 0:
            self._ensure(np.unique(tiles))
            slot = np.take(self.page, tiles)
        mask = self.tile - 1
        slot <<= 2 * self.bits
        row &= mask
        row <<= self.bits
        slot += row
        col &= mask
        slot += col
        return np.take(self.atlas.reshape(-1), slot)

    def _tile_hits(self, tiles: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """World corners (x0, y0) of ``tiles`` and which primitives overlap each, (T, P) bool."""
        tile_m = self.tile * self.res
        tx0 = self.x0 + (tiles % self.ntx) * tile_m
        ty0 = self.y0 + (tiles // self.ntx) * tile_m
        hits = (
            (self.boxes[None, :, 0] < tx0[:, None] + tile_m)
            & (self.boxes[None, :, 2] > tx0[:, None])
            & (self.boxes[None, :, 1] < ty0[:, None] + tile_m)
            & (self.boxes[None, :, 3] > ty0[:, None])
        )
        return tx0, ty0, hits

    def _ensure(self, needed: np.ndarray) -> None:
        """Draw the tiles among ``needed`` (unique tile ids of one lookup) not drawn yet."""
        missing = needed[self.page[needed] < 0]
        tx0, ty0, hits = self._tile_hits(missing)
        if self.used + int(hits.any(1).sum()) > self.max_tiles:
            # Bounded memory: start over with just this lookup's tiles (which always fit, even
            # beyond max_tiles, so one frame never reads a tile evicted while it was drawn).
            self._reset_tiles()
            missing = needed
            tx0, ty0, hits = self._tile_hits(missing)
        empty = ~hits.any(1)
        self.page[missing[empty]] = 0
        todo = np.nonzero(~empty)[0]
        need = self.used + len(todo)
        if need > len(self.atlas):
            size = max(need, min(2 * len(self.atlas), self.max_tiles))
            grown = np.empty((size,) + self.atlas.shape[1:], np.uint8)
            grown[: self.used] = self.atlas[: self.used]
            self.atlas = grown
        for i in todo:
            self.atlas[self.used] = self._rasterize(tx0[i], ty0[i], np.nonzero(hits[i])[0])
            self.page[missing[i]] = self.used
            self.used += 1

    def _rasterize(self, x0: float, y0: float, prims: np.ndarray) -> np.ndarray:
        scale = (1 << self.shift) / self.res
        origin = np.array([x0, y0])

        def px(p: np.ndarray) -> np.ndarray:
            return np.round((p - origin) * scale - 0.5 * (1 << self.shift)).astype(np.int32)

        masks = np.zeros((3, self.tile, self.tile), dtype=np.uint8)
        for i in prims:
            kind, pts, thickness = self.prims[i]
            if kind == FILL:
                cv2.fillPoly(masks[FILL], [px(pts)], 1, cv2.LINE_8, self.shift)
            else:
                cv2.polylines(masks[kind], [px(pts)], False, 1, thickness, cv2.LINE_8, self.shift)
        labels = self.noise + np.uint8(self.road0) * masks[FILL]
        labels[masks[MARKING] > 0] = self.marking
        labels[masks[EDGE] > 0] = self.edge
        return labels

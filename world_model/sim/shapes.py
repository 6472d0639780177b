"""Category templates: one :class:`~world_model.sim.mesh.Mesh` per (category, box size).

Every template fills its object's 3D box (length l along x, width w along y, height h) in the
local frame whose origin is the box centre, so the ground is at z = -h/2. Proportions are
fractions of the box so that a scenario's custom sizes still look right. Parts keep disjoint
bounding boxes (see :mod:`world_model.sim.mesh`); the colour-carrying role is "body".
"""

from __future__ import annotations

import math
from collections.abc import Callable
from functools import lru_cache
from typing import NamedTuple

import numpy as np

from world_model.scene import CATEGORIES
from world_model.sim.mesh import Mesh, MeshBuilder

WHEEL_SIDES = 8
Y_AXIS = np.array([0.0, 1.0, 0.0])


def _wheels(mb: MeshBuilder, xs: tuple[float, ...], w: float, h: float, radius: float, tread: float) -> None:
    """Pairs of wheels at longitudinal positions ``xs``, flush with the box sides."""
    for x in xs:
        for side in (1.0, -1.0):
            mb.prism(
                (x, side * (w / 2 - tread / 2), -h / 2 + radius),
                radius,
                tread / 2,
                Y_AXIS,
                "wheel",
                sides=WHEEL_SIDES,
                cap_role="trim",
            )


def _lamps(mb: MeshBuilder, front: int | None, back: int | None, v0: float, v1: float) -> None:
    for u0, u1 in ((0.04, 0.22), (0.78, 0.96)):
        if front is not None:
            mb.decal(front, u0, u1, v0, v1, "headlight")
        if back is not None:
            mb.decal(back, u0, u1, v0, v1, "taillight")


def car(l: float, w: float, h: float) -> Mesh:
    mb = MeshBuilder()
    r, tread, z0 = 0.19 * h, 0.13 * w, -h / 2
    belt = z0 + 0.6 * h  # top of the lower body
    _wheels(mb, (0.31 * l, -0.31 * l), w, h, r, tread)
    inner = mb.box((-l / 2, -w / 2 + tread, z0 + 0.45 * r), (l / 2, w / 2 - tread, belt), "body")
    for side in (1.0, -1.0):
        ys = sorted((side * (w / 2 - tread), side * w / 2))
        mb.box((-l / 2, ys[0], z0 + 2 * r), (l / 2, ys[1], belt), "body")
    _lamps(mb, inner["front"], inner["back"], 0.12, 0.4)
    yb, yt = w / 2 - 0.03 * w, w / 2 - 0.12 * w
    cabin = np.array(
        [
            [0.22 * l, yb, h / 2],
            [0.22 * l, -yb, h / 2],
            [0.22 * l, -yb, belt],
            [0.22 * l, yb, belt],
            [-0.33 * l, yb, h / 2],
            [-0.33 * l, -yb, h / 2],
            [-0.33 * l, -yb, belt],
            [-0.33 * l, yb, belt],
        ]
    )
    # Slope the windshield and rear window: pull the roof's front and back edges inwards.
    cabin[[0, 1], 0] = 0.04 * l
    cabin[[4, 5], 0] = -0.26 * l
    cabin[[0, 4], 1] = yt
    cabin[[1, 5], 1] = -yt
    cab = mb.hexa(cabin, "body")
    mb.decal(cab["front"], 0.06, 0.94, 0.08, 0.9, "glass")
    mb.decal(cab["back"], 0.1, 0.9, 0.12, 0.85, "glass")
    mb.side_decals(cab, 0.1, 0.47, 0.12, 0.85, "glass")
    mb.side_decals(cab, 0.52, 0.88, 0.12, 0.85, "glass")
    return mb.build()


def van(l: float, w: float, h: float) -> Mesh:
    mb = MeshBuilder()
    r, tread, z0 = 0.16 * h, 0.12 * w, -h / 2
    belt = z0 + 0.45 * h
    _wheels(mb, (0.32 * l, -0.3 * l), w, h, r, tread)
    inner = mb.box((-l / 2, -w / 2 + tread, z0 + 0.4 * r), (l / 2, w / 2 - tread, belt), "body")
    for side in (1.0, -1.0):
        ys = sorted((side * (w / 2 - tread), side * w / 2))
        mb.box((-l / 2, ys[0], z0 + 2 * r), (l / 2, ys[1], belt), "body")
    _lamps(mb, inner["front"], inner["back"], 0.15, 0.45)
    upper = np.array(
        [
            [0.3 * l, w / 2, h / 2],
            [0.3 * l, -w / 2, h / 2],
            [0.5 * l, -w / 2, belt],
            [0.5 * l, w / 2, belt],
            [-l / 2, w / 2, h / 2],
            [-l / 2, -w / 2, h / 2],
            [-l / 2, -w / 2, belt],
            [-l / 2, w / 2, belt],
        ]
    )
    up = mb.hexa(upper, "body")
    mb.decal(up["front"], 0.05, 0.95, 0.06, 0.8, "glass")
    mb.side_decals(up, 0.72, 0.95, 0.1, 0.6, "glass")
    mb.decal(up["back"], 0.06, 0.46, 0.1, 0.5, "glass")
    mb.decal(up["back"], 0.54, 0.94, 0.1, 0.5, "glass")
    return mb.build()


def bus(l: float, w: float, h: float) -> Mesh:
    mb = MeshBuilder()
    r, tread, z0 = 0.15 * h, 0.12 * w, -h / 2
    _wheels(mb, (0.3 * l, -0.28 * l), w, h, r, tread)
    mb.box((-l / 2, -w / 2 + tread, z0 + 0.4 * r), (l / 2, w / 2 - tread, z0 + 2 * r), "trim")
    body = mb.box((-l / 2, -w / 2, z0 + 2 * r), (l / 2, w / 2, h / 2), "body")
    mb.decal(body["front"], 0.05, 0.95, 0.14, 0.6, "glass")
    mb.decal(body["front"], 0.15, 0.85, 0.03, 0.11, "sign")
    mb.decal(body["back"], 0.1, 0.9, 0.1, 0.42, "glass")
    panes = max(3, round(l / 1.4))
    for i in range(panes):
        u0 = 0.04 + 0.92 * i / panes
        mb.side_decals(body, u0, u0 + 0.92 / panes - 0.02, 0.1, 0.48, "glass")
    mb.side_decals(body, 0.0, 1.0, 0.86, 0.97, "body_dark")
    _lamps(mb, body["front"], body["back"], 0.8, 0.92)
    return mb.build()


class _TruckFront(NamedTuple):
    """What a truck's wheels, chassis and cab look like (metres, in the truck's box frame)."""

    wheel_radius: float
    tread: float  # wheel width, inside the box sides
    cab_len: float
    cab_top: float  # z of the cab's roof
    axles: tuple[float, ...]  # x of each pair of wheels


def _cab_and_chassis(mb: MeshBuilder, l: float, w: float, h: float, front: _TruckFront) -> float:
    """Truck front: wheels, a chassis between them, a cab with windows; returns the chassis top z."""
    z0 = -h / 2
    r, tread, cab_len = front.wheel_radius, front.tread, front.cab_len
    _wheels(mb, front.axles, w, h, r, tread)
    chassis_top = z0 + 2 * r
    mb.box((-l / 2, -w / 2 + tread, z0 + 0.5 * r), (l / 2, w / 2 - tread, chassis_top), "trim")
    cab = mb.box((l / 2 - cab_len, -w / 2, chassis_top), (l / 2, w / 2, front.cab_top), "body")
    mb.decal(cab["front"], 0.07, 0.93, 0.08, 0.5, "glass")
    mb.side_decals(cab, 0.5, 0.94, 0.1, 0.45, "glass")
    _lamps(mb, cab["front"], None, 0.78, 0.92)
    return chassis_top


def truck(l: float, w: float, h: float) -> Mesh:
    mb = MeshBuilder()
    cab_len = 0.22 * l
    front = _TruckFront(0.14 * h, 0.14 * w, cab_len, -h / 2 + 0.8 * h, (0.37 * l, -0.28 * l, -0.4 * l))
    top = _cab_and_chassis(mb, l, w, h, front)
    cargo = mb.box((-l / 2, -w / 2, top), (l / 2 - cab_len - 0.02 * l, w / 2, h / 2), "body")
    mb.side_decals(cargo, 0.0, 1.0, 0.86, 0.92, "body_dark")
    _lamps(mb, None, cargo["back"], 0.88, 0.97)
    return mb.build()


def tree_truck(l: float, w: float, h: float) -> Mesh:
    mb = MeshBuilder()
    cab_len = 0.2 * l
    front = _TruckFront(0.12 * h, 0.14 * w, cab_len, -h / 2 + 0.72 * h, (0.38 * l, -0.25 * l, -0.38 * l))
    top = _cab_and_chassis(mb, l, w, h, front)
    bed_x1 = l / 2 - cab_len - 0.02 * l
    bed = mb.box((-l / 2, -w / 2, top), (bed_x1, w / 2, top + 0.06 * h), "trim")
    _lamps(mb, None, bed["back"], 0.2, 0.8)
    # A layer of trunks, then the foliage load as a grid of blobs in two greens.
    trunk_top = top + 0.18 * h
    mb.box((-l / 2, -0.4 * w, top + 0.06 * h), (bed_x1 - 0.05 * l, 0.4 * w, trunk_top), "trunk")
    nx, gap = 4, 0.01 * l
    span = bed_x1 - (-l / 2)
    for i in range(nx):
        x0 = -l / 2 + i * span / nx
        for j, (y0, y1) in enumerate(((-w / 2, 0.0), (0.0, w / 2))):
            role = "foliage" if (i + j) % 2 == 0 else "foliage_light"
            z1 = h / 2 - (0.06 * h if (i + j) % 2 else 0.0)
            mb.box((x0, y0, trunk_top), (x0 + span / nx - gap, y1, z1), role)
    return mb.build()


def cement_mixer(l: float, w: float, h: float) -> Mesh:
    mb = MeshBuilder()
    cab_len = 0.22 * l
    front = _TruckFront(0.13 * h, 0.14 * w, cab_len, -h / 2 + 0.78 * h, (0.36 * l, -0.22 * l, -0.36 * l))
    top = _cab_and_chassis(mb, l, w, h, front)
    # The drum: an octagonal prism, rear end raised, kept inside the space behind the cab.
    tilt = math.radians(6.0)
    length = 0.68 * l
    room = (h / 2 - top) - 0.04 * h
    radius = min(0.45 * w, (room / 2 - 0.5 * length * math.sin(tilt)) / math.cos(tilt))
    axis = np.array([math.cos(tilt), 0.0, -math.sin(tilt)])
    cx = l / 2 - cab_len - 0.04 * l - 0.5 * length * math.cos(tilt) - radius * math.sin(tilt)
    cz = top + 0.02 * h + room / 2
    mb.prism(
        (cx, 0.0, cz),
        radius,
        length / 2,
        axis,
        "body",
        sides=8,
        side_roles=("body", "body", "stripe", "body"),
        cap_role="body_dark",
    )
    return mb.build()


def motorcycle(l: float, w: float, h: float) -> Mesh:
    mb = MeshBuilder()
    r, z0 = 0.21 * h, -h / 2
    for x in (l / 2 - r, -l / 2 + r):
        mb.prism((x, 0.0, z0 + r), r, 0.07 * w, Y_AXIS, "wheel", sides=WHEEL_SIDES, cap_role="trim")
    seat_z = z0 + 0.5 * h
    body = mb.box((-l / 2 + 2 * r, -0.2 * w, z0 + 0.2 * h), (l / 2 - 2 * r, 0.2 * w, seat_z), "body")
    mb.decal(body["front"], 0.3, 0.7, 0.1, 0.4, "headlight")
    mb.decal(body["back"], 0.3, 0.7, 0.1, 0.35, "taillight")
    for side in (1.0, -1.0):  # the rider's legs beside the tank
        ys = sorted((side * 0.2 * w, side * 0.34 * w))
        mb.box((-0.2 * l, ys[0], z0 + 0.22 * h), (0.1 * l, ys[1], seat_z), "legs")
    mb.box((-0.2 * l, -0.25 * w, seat_z), (0.05 * l, 0.25 * w, z0 + 0.83 * h), "trim")  # jacket
    mb.box((-0.07 * l, -0.15 * w, z0 + 0.83 * h), (0.07 * l, 0.15 * w, h / 2), "body")  # helmet
    return mb.build()


def cyclist(l: float, w: float, h: float) -> Mesh:
    mb = MeshBuilder()
    r, z0 = 0.2 * h, -h / 2
    for x in (l / 2 - r, -l / 2 + r):
        mb.prism((x, 0.0, z0 + r), r, 0.04 * w, Y_AXIS, "wheel", sides=WHEEL_SIDES, cap_role="wheel")
    hip = z0 + 0.53 * h
    mb.box((-l / 2 + 2 * r, -0.04 * w, z0 + 0.6 * r), (l / 2 - 2 * r, 0.04 * w, z0 + 1.6 * r), "trim")
    for side in (1.0, -1.0):
        ys = sorted((side * 0.06 * w, side * 0.24 * w))
        mb.box((-0.12 * l, ys[0], z0 + 0.6 * r), (0.06 * l, ys[1], hip), "legs")
        ys = sorted((side * 0.2 * w, side * 0.3 * w))
        mb.box((0.09 * l, ys[0], z0 + 0.6 * h), (0.24 * l, ys[1], z0 + 0.67 * h), "body")  # arm
    mb.box((-0.15 * l, -0.3 * w, hip), (0.09 * l, 0.3 * w, z0 + 0.85 * h), "body")
    mb.box((-0.06 * l, -0.17 * w, z0 + 0.85 * h), (0.06 * l, 0.17 * w, z0 + 0.93 * h), "skin")
    mb.box((-0.07 * l, -0.19 * w, z0 + 0.93 * h), (0.07 * l, 0.19 * w, h / 2), "stripe")  # helmet
    return mb.build()


def pedestrian(l: float, w: float, h: float) -> Mesh:
    mb = MeshBuilder()
    z0 = -h / 2
    hip, shoulder = z0 + 0.48 * h, z0 + 0.82 * h
    for side in (1.0, -1.0):
        ys = sorted((side * 0.03 * w, side * 0.24 * w))
        mb.box((-0.14 * l, ys[0], z0), (0.14 * l, ys[1], hip), "legs")
        ys = sorted((side * 0.32 * w, side * 0.44 * w))
        mb.box((-0.1 * l, ys[0], hip + 0.04 * h), (0.1 * l, ys[1], shoulder - 0.01 * h), "body")  # arm
    mb.box((-0.2 * l, -0.32 * w, hip), (0.2 * l, 0.32 * w, shoulder), "body")
    head = mb.box((-0.16 * l, -0.16 * w, shoulder), (0.16 * l, 0.16 * w, z0 + 0.96 * h), "skin")
    mb.decal(head["back"], 0.0, 1.0, 0.0, 0.5, "hair")
    mb.box((-0.17 * l, -0.17 * w, z0 + 0.96 * h), (0.17 * l, 0.17 * w, h / 2), "hair")
    return mb.build()


def cone(l: float, w: float, h: float) -> Mesh:
    mb = MeshBuilder()
    z0, rad = -h / 2, 0.5 * min(l, w)
    mb.box((-l / 2, -w / 2, z0), (l / 2, w / 2, z0 + 0.06 * h), "trim")
    mb.frustum(z0 + 0.06 * h, z0 + 0.45 * h, 0.85 * rad, 0.6 * rad, "body")
    mb.frustum(z0 + 0.45 * h, z0 + 0.68 * h, 0.6 * rad, 0.42 * rad, "stripe")
    mb.frustum(z0 + 0.68 * h, h / 2, 0.42 * rad, 0.12 * rad, "body")
    return mb.build()


def barrier(l: float, w: float, h: float) -> Mesh:
    mb = MeshBuilder()
    z0 = -h / 2
    panel = mb.box((-0.3 * l, -w / 2, z0 + 0.25 * h), (0.3 * l, w / 2, h / 2), "body")
    stripes = 5
    for i in range(stripes):
        u0 = (i + 0.25) / stripes
        for face in ("front", "back"):
            mb.decal(panel[face], u0, u0 + 0.5 / stripes, 0.0, 1.0, "stripe")
    for side in (1.0, -1.0):
        ys = sorted((side * 0.3 * w, side * 0.45 * w))
        mb.box((-l / 2, ys[0], z0), (l / 2, ys[1], z0 + 0.25 * h), "trim")
    return mb.build()


TEMPLATES: dict[str, Callable[[float, float, float], Mesh]] = {
    "car": car,
    "truck": truck,
    "bus": bus,
    "van": van,
    "motorcycle": motorcycle,
    "cyclist": cyclist,
    "pedestrian": pedestrian,
    "cone": cone,
    "barrier": barrier,
    "tree_truck": tree_truck,
    "cement_mixer": cement_mixer,
}
assert set(TEMPLATES) == set(CATEGORIES), "every category needs a template"


@lru_cache(maxsize=256)
def category_mesh(category: str, size: tuple[float, float, float]) -> Mesh:
    """The template of ``category`` scaled to ``size`` = (length, width, height), cached."""
    if category not in TEMPLATES:
        raise ValueError(f"unknown object category {category!r}; expected one of {CATEGORIES}")
    l, w, h = (float(s) for s in size)
    if min(l, w, h) <= 0:
        raise ValueError(f"object size must be positive, got {size} for a {category}")
    return TEMPLATES[category](l, w, h)

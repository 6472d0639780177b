"""Small convex-part meshes for the painter's-algorithm object renderer.

An object is a handful of convex *parts* (boxes, prisms, frustums) in the object's local frame
(x forward, y left, z up, origin at the 3D box centre). Every part's faces are convex polygons.
*Decals* (windows, lamps, stripes) are quads lying on a part's face; they are drawn right after
that face and only when it faces the camera, so they never need depth sorting of their own.

Templates keep the axis-aligned bounding boxes of their parts pairwise disjoint (touching is
fine): the renderer orders the parts of one object by their separating planes, which is exact for
disjoint boxes seen from a point.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from world_model.geometry import BOX_CORNER_SIGNS, BOX_FACES
from world_model.sim.lighting import ROLE_INDEX

MAX_FACE_VERTS = 8  # octagonal caps are the largest faces


@dataclass(frozen=True)
class Mesh:
    """Faces are padded to ``MAX_FACE_VERTS`` by repeating their last vertex (shapes in comments)."""

    vertices: np.ndarray  # (Nv, 3) local frame, metres
    faces: np.ndarray  # (F, MAX_FACE_VERTS) int32 vertex indices, padded
    face_sizes: np.ndarray  # (F,) int32 number of real vertices
    normals: np.ndarray  # (F, 3) outward unit normals
    centroids: np.ndarray  # (F, 3)
    roles: np.ndarray  # (F,) int32 index into lighting.ROLES
    parents: np.ndarray  # (F,) int32 -1 for a part's own face, else the face a decal lies on
    parts: np.ndarray  # (F,) int32 part index
    part_lo: np.ndarray  # (P, 3) part bounding boxes
    part_hi: np.ndarray  # (P, 3)

    @property
    def num_faces(self) -> int:
        return len(self.faces)

    @property
    def num_parts(self) -> int:
        return len(self.part_lo)


def _newell_normal(points: np.ndarray) -> np.ndarray:
    nxt = np.roll(points, -1, axis=0)
    n = np.array(
        [
            np.sum((points[:, 1] - nxt[:, 1]) * (points[:, 2] + nxt[:, 2])),
            np.sum((points[:, 2] - nxt[:, 2]) * (points[:, 0] + nxt[:, 0])),
            np.sum((points[:, 0] - nxt[:, 0]) * (points[:, 1] + nxt[:, 1])),
        ]
    )
    return n / max(np.linalg.norm(n), 1e-12)


class MeshBuilder:
    """Accumulates parts and decals, then :meth:`build` freezes them into a :class:`Mesh`.

    Part methods return a dict face-name -> face index used to attach decals.
    """

    def __init__(self) -> None:
        self._verts: list[np.ndarray] = []
        self._nverts = 0
        self._faces: list[list[int]] = []
        self._normals: list[np.ndarray] = []
        self._roles: list[int] = []
        self._parents: list[int] = []
        self._parts: list[int] = []
        self._part_boxes: list[tuple[np.ndarray, np.ndarray]] = []

    def _add_part(self, verts: np.ndarray, faces: dict[str, list[int]], roles: dict[str, str]) -> dict[str, int]:
        part = len(self._part_boxes)
        centre = verts.mean(axis=0)
        out = {}
        for name, idx in faces.items():
            pts = verts[idx]
            n = _newell_normal(pts)
            if np.dot(pts.mean(axis=0) - centre, n) < 0:  # orient outwards
                n = -n
            out[name] = len(self._faces)
            self._faces.append([self._nverts + i for i in idx])
            self._normals.append(n)
            self._roles.append(ROLE_INDEX[roles[name]])
            self._parents.append(-1)
            self._parts.append(part)
        self._verts.append(verts)
        self._nverts += len(verts)
        self._part_boxes.append((verts.min(axis=0), verts.max(axis=0)))
        return out

    def hexa(self, corners: np.ndarray, role: str, face_roles: dict[str, str] | None = None) -> dict[str, int]:
        """A convex hexahedron from 8 corners in the box corner order of :mod:`world_model.geometry`."""
        roles = {name: (face_roles or {}).get(name, role) for name in BOX_FACES}
        return self._add_part(np.asarray(corners, dtype=np.float64), {k: list(v) for k, v in BOX_FACES.items()}, roles)

    def box(
        self,
        lo: tuple[float, float, float],
        hi: tuple[float, float, float],
        role: str,
        face_roles: dict[str, str] | None = None,
    ) -> dict[str, int]:
        """Axis-aligned box between corners ``lo`` and ``hi``."""
        lo_a, hi_a = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
        if np.any(hi_a <= lo_a):
            raise ValueError(f"box needs hi > lo on every axis, got lo={lo}, hi={hi}")
        centre, half = 0.5 * (lo_a + hi_a), 0.5 * (hi_a - lo_a)
        return self.hexa(centre + BOX_CORNER_SIGNS * half, role, face_roles)

    def prism(
        self,
        center: tuple[float, float, float],
        radius: float,
        half_length: float,
        axis: np.ndarray,
        role: str,
        sides: int = 8,
        side_roles: tuple[str, ...] | None = None,
        cap_role: str | None = None,
    ) -> dict[str, int]:
        """A regular ``sides``-gon prism (wheel, drum) around the unit ``axis`` through ``center``.

        ``radius`` is the inradius: the flat sides touch the circle, so a wheel stands on the road.

        ``side_roles`` cycles over the side faces (stripes); faces are named "cap+", "cap-", "side<i>".
        """
        axis = np.asarray(axis, dtype=np.float64)
        axis = axis / np.linalg.norm(axis)
        helper = np.array([0.0, 0.0, 1.0]) if abs(axis[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
        e1 = np.cross(axis, helper)
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(axis, e1)
        ang = 2 * np.pi * (np.arange(sides) + 0.5) / sides
        ring = radius / np.cos(np.pi / sides) * (np.cos(ang)[:, None] * e1 + np.sin(ang)[:, None] * e2)
        c = np.asarray(center, dtype=np.float64)
        verts = np.concatenate([c + ring + half_length * axis, c + ring - half_length * axis])
        faces = {"cap+": list(range(sides)), "cap-": list(range(2 * sides - 1, sides - 1, -1))}
        roles = {"cap+": cap_role or role, "cap-": cap_role or role}
        for i in range(sides):
            j = (i + 1) % sides
            faces[f"side{i}"] = [i, j, sides + j, sides + i]
            roles[f"side{i}"] = side_roles[i % len(side_roles)] if side_roles else role
        return self._add_part(verts, faces, roles)

    def frustum(self, z0: float, z1: float, r0: float, r1: float, role: str, sides: int = 8) -> dict[str, int]:
        """A vertical ``sides``-gon frustum (cone segment) on the local z axis from z0 (inradius r0) to z1."""
        ang = 2 * np.pi * (np.arange(sides) + 0.5) / sides
        ring = np.stack([np.cos(ang), np.sin(ang), np.zeros(sides)], axis=1) / np.cos(np.pi / sides)
        verts = np.concatenate([ring * r1 + [0, 0, z1], ring * r0 + [0, 0, z0]])
        faces = {"top": list(range(sides)), "bottom": list(range(2 * sides - 1, sides - 1, -1))}
        for i in range(sides):
            j = (i + 1) % sides
            faces[f"side{i}"] = [i, j, sides + j, sides + i]
        return self._add_part(verts, faces, dict.fromkeys(faces, role))

    def decal(self, face: int, u0: float, u1: float, v0: float, v1: float, role: str) -> int:
        """A quad on ``face`` (a 4-vertex face) at bilinear coordinates u in [u0, u1], v in [v0, v1].

        For faces of :meth:`box` / :meth:`hexa`, v runs top to bottom on side faces; u runs back to
        front on "left", front to back on "right", left to right on "front", right to left on "back".
        """
        idx = self._faces[face]
        if len(idx) != 4:
            raise ValueError("decals need a quadrilateral parent face")
        allv = np.concatenate(self._verts)
        a, b, c, d = allv[idx]

        def at(u: float, v: float) -> np.ndarray:
            return (1 - u) * (1 - v) * a + u * (1 - v) * b + u * v * c + (1 - u) * v * d

        quad = np.stack([at(u0, v0), at(u1, v0), at(u1, v1), at(u0, v1)])
        out = len(self._faces)
        self._faces.append(list(range(self._nverts, self._nverts + 4)))
        self._verts.append(quad)
        self._nverts += 4
        self._normals.append(self._normals[face])
        self._roles.append(ROLE_INDEX[role])
        self._parents.append(face)
        self._parts.append(self._parts[face])
        return out

    def side_decals(self, faces: dict[str, int], x0: float, x1: float, v0: float, v1: float, role: str) -> None:
        """The same decal on the "left" and "right" faces, ``x0..x1`` measured back (0) to front (1)."""
        self.decal(faces["left"], x0, x1, v0, v1, role)
        self.decal(faces["right"], 1 - x1, 1 - x0, v0, v1, role)

    def build(self) -> Mesh:
        if not self._faces:
            raise ValueError("a mesh needs at least one part")
        verts = np.concatenate(self._verts)
        sizes = np.array([len(f) for f in self._faces], dtype=np.int32)
        if sizes.max() > MAX_FACE_VERTS:
            raise ValueError(f"faces have at most {MAX_FACE_VERTS} vertices")
        faces = np.array([f + [f[-1]] * (MAX_FACE_VERTS - len(f)) for f in self._faces], dtype=np.int32)
        centroids = np.stack([verts[f].mean(axis=0) for f in self._faces])
        lo = np.stack([b[0] for b in self._part_boxes])
        hi = np.stack([b[1] for b in self._part_boxes])
        return Mesh(
            vertices=verts,
            faces=faces,
            face_sizes=sizes,
            normals=np.stack(self._normals),
            centroids=centroids,
            roles=np.array(self._roles, dtype=np.int32),
            parents=np.array(self._parents, dtype=np.int32),
            parts=np.array(self._parts, dtype=np.int32),
            part_lo=lo,
            part_hi=hi,
        )

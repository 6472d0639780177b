"""All objects of a frame as one concatenated mesh, cached per object set.

Also precomputes, per object, the separating plane between every pair of its parts (view
independent), which the painter uses to order parts from any viewpoint.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from world_model.scene import SceneFrame
from world_model.sim.lighting import emissive_table, role_albedos
from world_model.sim.mesh import MAX_FACE_VERTS, Mesh
from world_model.sim.shapes import category_mesh

# Two parts whose boxes overlap by more than this (m) are ordered by centre distance instead.
SEPARATION_TOLERANCE_M = 1e-6


def object_key(frame: SceneFrame) -> tuple:
    """What the cached scene mesh depends on: category, size and colour of each object, in order."""
    return tuple((o.category, tuple(o.box.size), tuple(o.color)) for o in frame.objects)


@dataclass(frozen=True)
class SceneMesh:
    """All objects' meshes concatenated (local frames); shapes: Nv vertices, F faces, N objects, P parts."""

    vertices: np.ndarray  # (Nv, 3)
    vert_obj: np.ndarray  # (Nv,)
    faces: np.ndarray  # (F, MAX_FACE_VERTS) global vertex indices
    face_sizes: np.ndarray  # (F,)
    normals: np.ndarray  # (F, 3)
    centroids: np.ndarray  # (F, 3)
    parents: np.ndarray  # (F,) global parent face or -1
    face_obj: np.ndarray  # (F,)
    face_part: np.ndarray  # (F,) part index within its object
    face_start: np.ndarray  # (N + 1,) first face of each object
    albedo: np.ndarray  # (F, 3)
    emissive: np.ndarray  # (F,) bool
    emissive_color: np.ndarray  # (F, 3)
    object_albedo: np.ndarray  # (N, 3) area-weighted mean albedo of each object's faces (impostors)
    part_centre: np.ndarray  # (N, P, 3) padded
    part_valid: np.ndarray  # (N, P) bool
    sep_axis: np.ndarray  # (N, P, P) axis of the best separating plane between parts i and j
    sep_value: np.ndarray  # (N, P, P) its coordinate
    i_low: np.ndarray  # (N, P, P) part i lies on the low side of that plane
    separable: np.ndarray  # (N, P, P) bool


def _mean_albedo(m: Mesh, albedo: np.ndarray) -> np.ndarray:
    """Area-weighted mean albedo of a mesh's faces, (3,)."""
    v = m.vertices[m.faces]  # (F, 8, 3); padding repeats a vertex and adds no area
    cross = np.cross(v - v[:, :1], np.roll(v, -1, axis=1) - v[:, :1]).sum(axis=1)
    area = 0.5 * np.linalg.norm(cross, axis=1)
    return (albedo * area[:, None]).sum(0) / max(area.sum(), 1e-12)


def build_scene_mesh(frame: SceneFrame) -> SceneMesh:
    meshes = [category_mesh(o.category, tuple(o.box.size)) for o in frame.objects]
    n = len(meshes)
    pmax = max((m.num_parts for m in meshes), default=1)
    roles_flag, roles_emit = emissive_table()
    verts, vobj, faces, sizes, normals, cents, parents, fobj, fpart, alb, emit, ecol, obj_alb = ([] for _ in range(13))
    starts = [0]
    part_lo = np.zeros((n, pmax, 3))
    part_hi = np.zeros((n, pmax, 3))
    valid = np.zeros((n, pmax), dtype=bool)
    v_off = f_off = 0
    for i, (o, m) in enumerate(zip(frame.objects, meshes, strict=True)):
        verts.append(m.vertices)
        vobj.append(np.full(len(m.vertices), i))
        faces.append(m.faces + v_off)
        sizes.append(m.face_sizes)
        normals.append(m.normals)
        cents.append(m.centroids)
        parents.append(np.where(m.parents >= 0, m.parents + f_off, -1))
        fobj.append(np.full(m.num_faces, i))
        fpart.append(m.parts)
        alb.append(role_albedos(o.color)[m.roles])
        emit.append(roles_flag[m.roles])
        ecol.append(roles_emit[m.roles])
        obj_alb.append(_mean_albedo(m, alb[-1]))
        part_lo[i, : m.num_parts] = m.part_lo
        part_hi[i, : m.num_parts] = m.part_hi
        valid[i, : m.num_parts] = True
        v_off += len(m.vertices)
        f_off += m.num_faces
        starts.append(f_off)

    # Separating planes between every pair of parts of an object (view independent).
    lo_i, hi_i = part_lo[:, :, None, :], part_hi[:, :, None, :]
    lo_j, hi_j = part_lo[:, None, :, :], part_hi[:, None, :, :]
    below, above = lo_j - hi_i, lo_i - hi_j  # i under j / i over j, per axis
    gap = np.maximum(below, above)
    axis = np.argmax(gap, axis=-1)
    take = axis[..., None]
    i_low = np.take_along_axis(below >= above, take, -1)[..., 0]
    shape = gap.shape

    def pick(a: np.ndarray) -> np.ndarray:
        return np.take_along_axis(np.broadcast_to(a, shape), take, -1)[..., 0]

    sep = np.where(i_low, 0.5 * (pick(hi_i) + pick(lo_j)), 0.5 * (pick(lo_i) + pick(hi_j)))
    separable = np.take_along_axis(gap, take, -1)[..., 0] >= -SEPARATION_TOLERANCE_M

    def cat(xs: list, shape: tuple, dtype: npt.DTypeLike = np.float64) -> np.ndarray:
        return np.concatenate(xs) if xs else np.zeros(shape, dtype=dtype)

    return SceneMesh(
        vertices=cat(verts, (0, 3)),
        vert_obj=cat(vobj, (0,), np.int64),
        faces=cat(faces, (0, MAX_FACE_VERTS), np.int32),
        face_sizes=cat(sizes, (0,), np.int32),
        normals=cat(normals, (0, 3)),
        centroids=cat(cents, (0, 3)),
        parents=cat(parents, (0,), np.int32),
        face_obj=cat(fobj, (0,), np.int64),
        face_part=cat(fpart, (0,), np.int32),
        face_start=np.array(starts),
        albedo=cat(alb, (0, 3)),
        emissive=cat(emit, (0,), bool),
        emissive_color=cat(ecol, (0, 3)),
        object_albedo=cat([a[None] for a in obj_alb], (0, 3)),
        part_centre=0.5 * (part_lo + part_hi),
        part_valid=valid,
        sep_axis=axis,
        sep_value=sep,
        i_low=i_low,
        separable=separable,
    )

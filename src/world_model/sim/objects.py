"""Objects in the cameras: shaded convex parts painted far-to-near (painter's algorithm).

Per frame, all objects' template meshes are moved into the LiDAR frame at once; per view, object
boxes are frustum-culled, faces are back-face culled, clipped against the near plane and ordered:
objects by distance from the camera to their box, parts of one object by their separating planes
(see :mod:`world_model.sim.mesh`), decals right after their face.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from world_model.scene import SceneFrame
from world_model.sensors import CameraRig
from world_model.sim.lighting import Lighting, emissive_table, role_albedos
from world_model.sim.mesh import MAX_FACE_VERTS, Mesh
from world_model.sim.poses import ObjectPoses
from world_model.sim.shapes import category_mesh

# Two parts whose boxes overlap by more than this (m) are ordered by centre distance instead.
SEPARATION_TOLERANCE_M = 1e-6
# Near-plane clipped vertices can project far off screen; clamp them so fixed-point stays in int32.
FIXED_POINT_LIMIT_PX = 1 << 20


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
    verts, vobj, faces, sizes, normals, cents, parents, fobj, fpart, alb, emit, ecol, obj_alb = (
        [] for _ in range(13)
    )
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

    def cat(xs: list, shape: tuple, dtype=np.float64) -> np.ndarray:
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


@dataclass
class DrawPlan:
    """Polygons to paint, per view in painting order."""

    polygons: list[list[np.ndarray]]  # per view: int32 (n, 2) fixed-point pixel coordinates
    colors: list[list[tuple[float, float, float]]]
    objects: list[list[int]]  # object index of each polygon


def _clip_near(poly: np.ndarray, near: float) -> np.ndarray:
    """Clip a camera-frame polygon (n, 3) against z >= near (Sutherland-Hodgman, one plane)."""
    out = []
    n = len(poly)
    for i in range(n):
        a, b = poly[i], poly[(i + 1) % n]
        a_in, b_in = a[2] >= near, b[2] >= near
        if a_in:
            out.append(a)
        if a_in != b_in:
            t = (near - a[2]) / (b[2] - a[2])
            out.append(a + t * (b - a))
    return np.array(out) if out else np.zeros((0, 3))


def face_colors(
    sm: SceneMesh, normals: np.ndarray, centroids: np.ndarray, sun_l: np.ndarray, lighting: Lighting
) -> np.ndarray:
    """(F, 3) shaded, fogged colours of every face (LiDAR-frame normals and centroids)."""
    light = lighting.ambient + lighting.sun * np.maximum(normals @ sun_l, 0.0)
    if lighting.lamps > 0:
        dist_xy = np.maximum(np.hypot(centroids[:, 0], centroids[:, 1]), 1e-6)
        facing = np.maximum(
            -(normals[:, 0] * centroids[:, 0] + normals[:, 1] * centroids[:, 1]) / dist_xy, 0.0
        )
        light = light + lighting.headlight(centroids[:, 0], centroids[:, 1]) * facing
    col = sm.albedo * light[:, None] * lighting.tint
    if lighting.lamps > 0:
        col = np.where(
            sm.emissive[:, None], (1 - lighting.lamps) * col + lighting.lamps * sm.emissive_color, col
        )
    fog = lighting.fog_factor(np.linalg.norm(centroids, axis=1))[:, None]
    return np.clip((1 - fog) * col + fog * lighting.fog_color, 0.0, 255.0)


def _impostor_colors(sm: SceneMesh, poses: ObjectPoses, sun_l: np.ndarray, lighting: Lighting) -> np.ndarray:
    """(N, 3) one flat colour per object for far-away impostors: mean albedo, averaged light."""
    light = lighting.ambient + 0.5 * lighting.sun * max(sun_l[2], 0.0)
    col = sm.object_albedo * light * lighting.tint
    fog = lighting.fog_factor(np.linalg.norm(poses.centre, axis=1))[:, None]
    return np.clip((1 - fog) * col + fog * lighting.fog_color, 0.0, 255.0)


def plan_objects(
    frame: SceneFrame,
    sm: SceneMesh,
    poses: ObjectPoses,
    rig: CameraRig,
    lighting: Lighting,
    near: float,
    min_area: float,
    impostor_px: float,
    shift: int,
) -> DrawPlan:
    """Everything the painter needs for all views of ``frame`` (see module docstring).

    Objects whose projected box spans fewer than ``impostor_px`` pixels are drawn as one flat
    polygon (the hull of their projected box) instead of their faces.
    """
    nviews = rig.num_views
    plan = DrawPlan([[] for _ in range(nviews)], [[] for _ in range(nviews)], [[] for _ in range(nviews)])
    if not frame.objects:
        return plan
    h, w = rig.resolution
    cy, sy = poses.cos, poses.sin

    def to_lidar(p: np.ndarray, obj: np.ndarray, translate: bool) -> np.ndarray:
        c, s = cy[obj], sy[obj]
        out = np.stack([c * p[:, 0] - s * p[:, 1], s * p[:, 0] + c * p[:, 1], p[:, 2]], axis=1)
        return out + poses.centre[obj] if translate else out

    Rs = np.stack([c.R for c in rig.cameras])  # (V, 3, 3) camera -> LiDAR
    ts = np.stack([c.t for c in rig.cameras])  # (V, 3)
    fx = np.array([c.K[0, 0] for c in rig.cameras])
    fy = np.array([c.K[1, 1] for c in rig.cameras])
    cx = np.array([c.K[0, 2] for c in rig.cameras])
    cyy = np.array([c.K[1, 2] for c in rig.cameras])

    # Object-level culling and level of detail from the projected 3D boxes.
    cc = ((poses.corners.reshape(1, -1, 3) - ts[:, None]) @ Rs).reshape(
        nviews, -1, 8, 3
    )  # p_cam = R^T (p - t)
    z = cc[..., 2]
    front = z > near
    zs = np.where(front, z, 1.0)
    u = fx[:, None, None] * cc[..., 0] / zs + cx[:, None, None]
    v = fy[:, None, None] * cc[..., 1] / zs + cyy[:, None, None]
    umin, umax = np.where(front, u, np.inf).min(-1), np.where(front, u, -np.inf).max(-1)
    vmin, vmax = np.where(front, v, np.inf).min(-1), np.where(front, v, -np.inf).max(-1)
    all_in = front.all(-1)
    on = (umin < w) & (umax > 0) & (vmin < h) & (vmax > 0)
    candidate = front.any(-1) & (on | ~all_in)  # (V, N)
    impostor = candidate & all_in & (np.maximum(umax - umin, vmax - vmin) < impostor_px)
    detailed = candidate & ~impostor

    # Objects are painted far to near: distance from the camera to the closest point of the box.
    rel = ts[:, None, :] - poses.centre[None]  # (V, N, 3)
    c_loc = np.stack(
        [cy * rel[..., 0] + sy * rel[..., 1], -sy * rel[..., 0] + cy * rel[..., 1], rel[..., 2]], -1
    )
    obj_dist = np.linalg.norm(c_loc - np.clip(c_loc, -poses.half, poses.half), axis=-1)  # (V, N)

    # Faces of detailed (view, object) pairs, parts ordered by their separating planes.
    pv, pn = np.nonzero(detailed)
    cam = c_loc[pv, pn]  # (Q, 3) camera in each pair's object frame
    axes = sm.sep_axis[pn]  # (Q, P, P)
    cam_coord = np.take_along_axis(cam, axes.reshape(len(pn), -1 if len(pn) else 0), 1).reshape(axes.shape)
    in_front = sm.i_low[pn] == (cam_coord < sm.sep_value[pn])
    part_dist = np.linalg.norm(sm.part_centre[pn] - cam[:, None, :], axis=-1)  # (Q, P)
    closer = part_dist[:, :, None] < part_dist[:, None, :]
    in_front = np.where(sm.separable[pn], in_front, closer) & sm.part_valid[pn][:, None, :]
    part_rank = in_front.sum(-1)  # (Q, P): parts in front of more parts are painted later

    counts = sm.face_start[pn + 1] - sm.face_start[pn]
    kpair = np.repeat(np.arange(len(pn)), counts)
    kview, kobj = pv[kpair], pn[kpair]
    kface = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts) + sm.face_start[kobj]

    verts = to_lidar(sm.vertices, sm.vert_obj, True)
    normals = to_lidar(sm.normals, sm.face_obj, False)
    cents = to_lidar(sm.centroids, sm.face_obj, True)
    cam_verts = (verts[None] - ts[:, None]) @ Rs  # (V, Nv, 3)
    pts = cam_verts[kview[:, None], sm.faces[kface]]  # (K, 8, 3)
    facing = np.sum(normals[kface] * (ts[kview] - cents[kface]), axis=1) > 0
    par = sm.parents[kface]
    is_decal = par >= 0
    parent_pos = np.where(is_decal, np.arange(len(kface)) - (kface - par), 0)
    facing = np.where(is_decal, facing[parent_pos], facing)
    zf = pts[..., 2]
    all_front = (zf > near).all(-1)
    any_front = (zf > near).any(-1)
    zsafe = np.where(zf > near, zf, near)
    uf = fx[kview, None] * pts[..., 0] / zsafe + cx[kview, None]
    vf = fy[kview, None] * pts[..., 1] / zsafe + cyy[kview, None]
    area = 0.5 * np.abs(np.sum(uf * np.roll(vf, -1, -1) - np.roll(uf, -1, -1) * vf, axis=-1))
    onscreen = (uf.min(-1) < w) & (uf.max(-1) > 0) & (vf.min(-1) < h) & (vf.max(-1) > 0)
    keep = np.nonzero(facing & any_front & (~all_front | (onscreen & (area >= min_area))))[0]

    # One draw list: faces of detailed objects and impostors (face -1), in painting order.
    iv, io = np.nonzero(impostor)
    views = np.concatenate([kview[keep], iv])
    objs = np.concatenate([kobj[keep], io])
    faces = np.concatenate([kface[keep], np.full(len(iv), -1)])
    ranks = np.concatenate([part_rank[kpair[keep], sm.face_part[kface[keep]]], np.zeros(len(iv), np.int64)])
    decal = np.concatenate([is_decal[keep], np.zeros(len(iv), bool)])
    order = np.lexsort((faces, decal, ranks, -obj_dist[views, objs], views))
    entries = np.concatenate([keep, -1 - np.arange(len(iv))])[order]

    scale = float(1 << shift)
    sun = lighting.sun_direction
    ce, se = math.cos(frame.ego.yaw), math.sin(frame.ego.yaw)
    sun_l = np.array([ce * sun[0] + se * sun[1], -se * sun[0] + ce * sun[1], sun[2]])
    colors = face_colors(sm, normals, cents, sun_l, lighting).tolist()
    imp_colors = _impostor_colors(sm, poses, sun_l, lighting).tolist()
    # cv2 puts pixel centres at integer coordinates; ours are at +0.5.
    fixed = list(np.round(np.stack([uf - 0.5, vf - 0.5], -1) * scale).astype(np.int32))
    imp_fixed = np.round(np.stack([u - 0.5, v - 0.5], -1) * scale).astype(np.int32)  # (V, N, 8, 2)
    sizes = sm.face_sizes.tolist()
    for e, view, f, obj in zip(
        entries.tolist(), views[order].tolist(), faces[order].tolist(), objs[order].tolist(), strict=True
    ):
        if e < 0:
            poly = cv2.convexHull(imp_fixed[view, obj])
            color = imp_colors[obj]
        elif all_front[e]:
            poly, color = fixed[e][: sizes[f]], colors[f]
        else:
            clipped = _clip_near(pts[e, : sizes[f]], near)
            if len(clipped) < 3:
                continue
            pu = fx[view] * clipped[:, 0] / clipped[:, 2] + cx[view] - 0.5
            pvv = fy[view] * clipped[:, 1] / clipped[:, 2] + cyy[view] - 0.5
            lim = float(FIXED_POINT_LIMIT_PX)
            poly = np.round(np.clip(np.stack([pu, pvv], -1), -lim, lim) * scale).astype(np.int32)
            color = colors[f]
        plan.polygons[view].append(poly)
        plan.colors[view].append(color)
        plan.objects[view].append(obj)
    return plan

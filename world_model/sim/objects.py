"""Objects in the cameras: shaded convex parts painted far-to-near (painter's algorithm).

Per frame, all objects' template meshes are moved into the LiDAR frame at once; per view, object
boxes are frustum-culled, faces are back-face culled, clipped against the near plane and ordered:
objects by distance from the camera to their box, parts of one object by their separating planes
(see :mod:`world_model.sim.mesh`), decals right after their face. Objects that project smaller
than a few pixels are drawn as one flat rectangle (an impostor). Everything up to the final
``cv2.fillConvexPoly`` calls is vectorized over all views and faces.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

from world_model.scene import SceneFrame
from world_model.sensors import CameraRig
from world_model.sim.lighting import Lighting
from world_model.sim.mesh import MAX_FACE_VERTS
from world_model.sim.poses import ObjectPoses
from world_model.sim.scene_mesh import SceneMesh

CLIPPED_VERTS = 2 * MAX_FACE_VERTS  # a polygon clipped by one plane has at most n + 1 vertices
# Near-plane clipped vertices can project far off screen; clamp them so fixed-point stays in int32.
FIXED_POINT_LIMIT_PX = 1 << 20


@dataclass(frozen=True)
class DrawPlan:
    """Polygons to paint in order; M polygons sorted by view, then painting order."""

    polygons: np.ndarray  # (M, CLIPPED_VERTS, 2) int32 fixed-point pixels, padded by repeating a vertex
    colors: np.ndarray  # (M, 3) float64 RGB, shaded and fogged
    albedos: np.ndarray  # (M, 3) float64 RGB: the paint of each polygon's face, unlit
    objects: np.ndarray  # (M,) object index
    view_start: np.ndarray  # (V + 1,) polygons of view v are [view_start[v], view_start[v + 1])

    def view(self, v: int) -> slice:
        return slice(int(self.view_start[v]), int(self.view_start[v + 1]))


def paint(
    image: np.ndarray,
    plan: DrawPlan,
    v: int,
    antialias: bool,
    shift: int,
    value: Callable[[int], float | tuple[float, ...]] | None = None,
) -> None:
    """Paint view ``v``'s polygons onto ``image`` (H, W[, C]) with their colours, or with ``value(obj)``."""
    sl = plan.view(v)
    line = cv2.LINE_AA if antialias else cv2.LINE_8
    colors = plan.colors[sl].tolist() if value is None else [value(o) for o in plan.objects[sl].tolist()]
    for poly, color in zip(list(plan.polygons[sl]), colors, strict=True):
        cv2.fillConvexPoly(image, poly, color, line, shift)


def clip_near(poly: np.ndarray, near: float) -> tuple[np.ndarray, np.ndarray]:
    """Clip camera-frame polygons (K, n, 3) (padded by repeats) against z >= near.

    Returns (K, 2n, 3) vertices, padded by repeating the last one, and (K,) vertex counts
    (0 = entirely behind the plane). Vectorized Sutherland-Hodgman against one plane.
    """
    a, b = poly, np.roll(poly, -1, axis=1)
    a_in, b_in = a[..., 2] >= near, b[..., 2] >= near
    crosses = a_in != b_in  # only there is b.z - a.z nonzero
    dz = np.where(crosses, b[..., 2] - a[..., 2], 1.0)
    t = np.where(crosses, (near - a[..., 2]) / dz, 0.0)
    cross = a + t[..., None] * (b - a)
    k, n = poly.shape[:2]
    cand = np.stack([a, cross], axis=2).reshape(k, 2 * n, 3)  # a0, x0, a1, x1, ...
    valid = np.stack([a_in, crosses], axis=2).reshape(k, 2 * n)
    order = np.argsort(~valid, axis=1, kind="stable")
    count = valid.sum(1)
    pick = np.minimum(np.arange(valid.shape[1])[None], np.maximum(count - 1, 0)[:, None])
    return np.take_along_axis(cand, np.take_along_axis(order, pick, 1)[..., None], 1), count


def face_colors(
    sm: SceneMesh,
    faces: np.ndarray,
    normals: np.ndarray,
    centroids: np.ndarray,
    sun_l: np.ndarray,
    lighting: Lighting,
) -> np.ndarray:
    """(K, 3) shaded, fogged colours of ``faces`` (K,), given all faces' LiDAR-frame normals and centroids."""
    normals, centroids = normals[faces], centroids[faces]
    light = lighting.ambient + lighting.sun * np.maximum(normals @ sun_l, 0.0)
    if lighting.lamps > 0:
        dist_xy = np.maximum(np.hypot(centroids[:, 0], centroids[:, 1]), 1e-6)
        facing = np.maximum(-(normals[:, 0] * centroids[:, 0] + normals[:, 1] * centroids[:, 1]) / dist_xy, 0.0)
        light = light + lighting.headlight(centroids[:, 0], centroids[:, 1]) * facing
    col = sm.albedo[faces] * light[:, None] * lighting.tint
    if lighting.lamps > 0:
        glow = (1 - lighting.lamps) * col + lighting.lamps * sm.emissive_color[faces]
        col = np.where(sm.emissive[faces, None], glow, col)
    fog = lighting.fog_factor(np.linalg.norm(centroids, axis=1))[:, None]
    return np.clip((1 - fog) * col + fog * lighting.fog_color, 0.0, 255.0)


def _impostor_colors(sm: SceneMesh, poses: ObjectPoses, sun_l: np.ndarray, lighting: Lighting) -> np.ndarray:
    """(N, 3) one flat colour per object for far-away impostors: mean albedo, averaged light."""
    light = lighting.ambient + 0.5 * lighting.sun * max(sun_l[2], 0.0)
    col = sm.object_albedo * light * lighting.tint
    fog = lighting.fog_factor(np.linalg.norm(poses.centre, axis=1))[:, None]
    return np.clip((1 - fog) * col + fog * lighting.fog_color, 0.0, 255.0)


def _part_ranks(sm: SceneMesh, pn: np.ndarray, cam: np.ndarray) -> np.ndarray:
    """(Q, P) painting rank of each part of object ``pn[q]`` seen from ``cam[q]`` (object frame):
    the number of its parts it is in front of (by separating plane, else by centre distance)."""
    axes = sm.sep_axis[pn]  # (Q, P, P)
    cam_coord = np.take_along_axis(cam, axes.reshape(len(pn), -1 if len(pn) else 0), 1).reshape(axes.shape)
    in_front = sm.i_low[pn] == (cam_coord < sm.sep_value[pn])
    part_dist = np.linalg.norm(sm.part_centre[pn] - cam[:, None, :], axis=-1)  # (Q, P)
    closer = part_dist[:, :, None] < part_dist[:, None, :]
    in_front = np.where(sm.separable[pn], in_front, closer) & sm.part_valid[pn][:, None, :]
    return in_front.sum(-1)


@dataclass(frozen=True)
class RigArrays:
    """Per-rig constants of :func:`plan_objects` (cache them with the rig)."""

    centres: np.ndarray  # (V, 3) camera centres, LiDAR frame
    fx: np.ndarray  # (V,) focal lengths and principal points
    fy: np.ndarray
    cx: np.ndarray
    cy: np.ndarray
    rotations: np.ndarray  # (3, 3V): every camera's R side by side, so p @ rotations = R^T p for all
    centres_cam: np.ndarray  # (V, 3) R^T t


def rig_arrays(rig: CameraRig) -> RigArrays:
    rs = np.stack([c.R for c in rig.cameras])  # (V, 3, 3) camera -> LiDAR
    ts = np.stack([c.t for c in rig.cameras])  # (V, 3)
    k = np.stack([c.K for c in rig.cameras])
    return RigArrays(
        centres=ts,
        fx=k[:, 0, 0],
        fy=k[:, 1, 1],
        cx=k[:, 0, 2],
        cy=k[:, 1, 2],
        rotations=rs.transpose(1, 0, 2).reshape(3, rig.num_views * 3),
        centres_cam=np.einsum("vj,vjk->vk", ts, rs),
    )


def plan_objects(
    frame: SceneFrame,
    sm: SceneMesh,
    poses: ObjectPoses,
    rig: CameraRig,
    cams: RigArrays,
    lighting: Lighting,
    near: float,
    min_area: float,
    impostor_px: float,
    shift: int,
) -> DrawPlan:
    """Every polygon to paint for all views of ``frame``, in painting order."""
    nviews = rig.num_views
    h, w = rig.resolution
    cy, sy = poses.cos, poses.sin
    ts, fx, fy, cx, cyy = cams.centres, cams.fx, cams.fy, cams.cx, cams.cy
    r_all, t_cam = cams.rotations, cams.centres_cam

    def to_cameras(p: np.ndarray) -> np.ndarray:
        """LiDAR-frame points (M, 3) -> (M, V, 3) in every camera: R^T (p - t), one BLAS product."""
        return (p @ r_all).reshape(len(p), nviews, 3) - t_cam

    # Object-level culling and level of detail from the projected 3D boxes.
    cc = to_cameras(poses.corners.reshape(-1, 3)).reshape(-1, 8, nviews, 3).transpose(2, 0, 1, 3)
    front = cc[..., 2] > near
    zs = np.where(front, cc[..., 2], 1.0)
    u = fx[:, None, None] * cc[..., 0] / zs + cx[:, None, None]
    v = fy[:, None, None] * cc[..., 1] / zs + cyy[:, None, None]
    umin, umax = np.where(front, u, np.inf).min(-1), np.where(front, u, -np.inf).max(-1)
    vmin, vmax = np.where(front, v, np.inf).min(-1), np.where(front, v, -np.inf).max(-1)
    all_in = front.all(-1)
    on = (umin < w) & (umax > 0) & (vmin < h) & (vmax > 0)
    candidate = front.any(-1) & (on | ~all_in)  # (V, N)
    impostor = candidate & all_in & (np.maximum(umax - umin, vmax - vmin) < impostor_px)
    pv, pn = np.nonzero(candidate & ~impostor)

    # Objects are painted far to near: distance from the camera to the closest point of the box.
    rel = ts[:, None, :] - poses.centre[None]  # (V, N, 3)
    c_loc = np.stack([cy * rel[..., 0] + sy * rel[..., 1], -sy * rel[..., 0] + cy * rel[..., 1], rel[..., 2]], -1)
    obj_dist = np.linalg.norm(c_loc - np.clip(c_loc, -poses.half, poses.half), axis=-1)  # (V, N)
    part_rank = _part_ranks(sm, pn, c_loc[pv, pn])

    # Faces of the detailed (view, object) pairs.
    counts = sm.face_start[pn + 1] - sm.face_start[pn]
    kpair = np.repeat(np.arange(len(pn)), counts)
    kview, kobj = pv[kpair], pn[kpair]
    kface = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts) + sm.face_start[kobj]

    def to_lidar(p: np.ndarray, obj: np.ndarray, translate: bool) -> np.ndarray:
        c, s = cy[obj], sy[obj]
        out = np.stack([c * p[:, 0] - s * p[:, 1], s * p[:, 0] + c * p[:, 1], p[:, 2]], axis=1)
        return out + poses.centre[obj] if translate else out

    verts = to_lidar(sm.vertices, sm.vert_obj, True)
    normals = to_lidar(sm.normals, sm.face_obj, False)
    cents = to_lidar(sm.centroids, sm.face_obj, True)
    facing = np.sum(normals[kface] * (ts[kview] - cents[kface]), axis=1) > 0
    par = sm.parents[kface]
    is_decal = par >= 0
    facing = np.where(is_decal, facing[np.where(is_decal, np.arange(len(kface)) - (kface - par), 0)], facing)
    k = np.nonzero(facing)[0]
    pts = to_cameras(verts)[sm.faces[kface[k]], kview[k, None]]  # (K, 8, 3) camera frames
    z_in = pts[..., 2] >= near
    inside, crossing = z_in.all(1), z_in.any(1) & ~z_in.all(1)

    def project(p: np.ndarray, views: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        inv_z = 1.0 / np.maximum(p[..., 2], near)
        u = fx[views, None] * p[..., 0] * inv_z + cx[views, None]
        v = fy[views, None] * p[..., 1] * inv_z + cyy[views, None]
        # Shoelace area; the padding repeats a vertex, which adds nothing.
        twice = np.sum(u[:, :-1] * v[:, 1:] - u[:, 1:] * v[:, :-1], axis=-1) + (u[:, -1] * v[:, 0] - u[:, 0] * v[:, -1])
        ok = (u.min(-1) < w) & (u.max(-1) > 0) & (v.min(-1) < h) & (v.max(-1) > 0) & (np.abs(twice) >= 2 * min_area)
        return u[ok], v[ok], ok

    # Only faces crossing the near plane need clipping; the others are padded to the same layout.
    uf, vf, ok = project(pts[inside], kview[k[inside]])
    uf, vf = (np.concatenate([a, np.repeat(a[:, -1:], CLIPPED_VERTS - MAX_FACE_VERTS, 1)], 1) for a in (uf, vf))
    k_in = k[inside][ok]
    clipped, _ = clip_near(pts[crossing], near)
    uc, vc, ok = project(clipped, kview[k[crossing]])
    k = np.concatenate([k_in, k[crossing][ok]])
    uf, vf = np.concatenate([uf, uc]), np.concatenate([vf, vc])

    # Impostors: the projected box's bounding rectangle, padded to the polygon layout.
    iv, io = np.nonzero(impostor)
    rect_u = np.stack([umin[iv, io], umax[iv, io], umax[iv, io], umin[iv, io]], -1)
    rect_v = np.stack([vmin[iv, io], vmin[iv, io], vmax[iv, io], vmax[iv, io]], -1)
    rect_u = np.concatenate([rect_u, np.repeat(rect_u[:, -1:], CLIPPED_VERTS - 4, 1)], 1)
    rect_v = np.concatenate([rect_v, np.repeat(rect_v[:, -1:], CLIPPED_VERTS - 4, 1)], 1)

    ce, se = math.cos(frame.ego.yaw), math.sin(frame.ego.yaw)
    sun = lighting.sun_direction
    sun_l = np.array([ce * sun[0] + se * sun[1], -se * sun[0] + ce * sun[1], sun[2]])
    views = np.concatenate([kview[k], iv])
    objs = np.concatenate([kobj[k], io])
    faces = np.concatenate([kface[k], np.full(len(iv), -1)])
    ranks = np.concatenate([part_rank[kpair[k], sm.face_part[kface[k]]], np.zeros(len(iv), np.int64)])
    decal = np.concatenate([is_decal[k], np.zeros(len(iv), bool)])
    order = np.lexsort((faces, decal, ranks, -obj_dist[views, objs], views))
    colors = np.concatenate(
        [
            face_colors(sm, kface[k], normals, cents, sun_l, lighting),
            _impostor_colors(sm, poses, sun_l, lighting)[io],
        ]
    )
    albedos = np.concatenate([sm.albedo[kface[k]], sm.object_albedo[io]])
    # cv2 puts pixel centres at integer coordinates; ours are at +0.5.
    lim = float(FIXED_POINT_LIMIT_PX)
    uv = np.stack([np.concatenate([uf, rect_u]), np.concatenate([vf, rect_v])], -1) - 0.5
    polys = np.round(np.clip(uv, -lim, lim) * float(1 << shift)).astype(np.int32)
    return DrawPlan(
        polygons=polys[order],
        colors=colors[order],
        albedos=albedos[order],
        objects=objs[order],
        view_start=np.searchsorted(views[order], np.arange(nviews + 1)),
    )

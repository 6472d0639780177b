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
from typing import NamedTuple

import cv2
import numpy as np

from world_model.scene import SceneFrame
from world_model.sensors import CameraRig
from world_model.sim.config import SimConfig
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


class _BoxesInViews(NamedTuple):
    """Each object's projected 3-D box in each view, (V, N) arrays: its pixel bounds over the corners
    in front of the near plane, and how it is drawn."""

    u_min: np.ndarray
    u_max: np.ndarray
    v_min: np.ndarray
    v_max: np.ndarray
    detailed: np.ndarray  # bool: drawn face by face
    impostor: np.ndarray  # bool: drawn as its bounding rectangle (it projects smaller than impostor_max_px)


class _PairFaces(NamedTuple):
    """The mesh faces of the detailed (view, object) pairs, one row per face of a pair, (K,) each."""

    pair: np.ndarray  # the pair's index
    view: np.ndarray
    obj: np.ndarray
    face: np.ndarray  # the face's index in the scene mesh


def _to_cameras(points: np.ndarray, cams: RigArrays) -> np.ndarray:
    """LiDAR-frame points (M, 3) -> (M, V, 3) in every camera: R^T (p - t), one BLAS product."""
    return (points @ cams.rotations).reshape(len(points), len(cams.fx), 3) - cams.centres_cam


def _boxes_in_views(poses: ObjectPoses, cams: RigArrays, rig: CameraRig, config: SimConfig) -> _BoxesInViews:
    """Object-level culling and level of detail from the projected 3-D boxes."""
    views = len(cams.fx)
    h, w = rig.resolution
    near = config.near_plane_m
    corners = _to_cameras(poses.corners.reshape(-1, 3), cams).reshape(-1, 8, views, 3).transpose(2, 0, 1, 3)
    front = corners[..., 2] > near
    zs = np.where(front, corners[..., 2], 1.0)
    u = cams.fx[:, None, None] * corners[..., 0] / zs + cams.cx[:, None, None]
    v = cams.fy[:, None, None] * corners[..., 1] / zs + cams.cy[:, None, None]
    u_min, u_max = np.where(front, u, np.inf).min(-1), np.where(front, u, -np.inf).max(-1)
    v_min, v_max = np.where(front, v, np.inf).min(-1), np.where(front, v, -np.inf).max(-1)
    all_in = front.all(-1)
    on = (u_min < w) & (u_max > 0) & (v_min < h) & (v_max > 0)
    candidate = front.any(-1) & (on | ~all_in)  # (V, N)
    impostor = candidate & all_in & (np.maximum(u_max - u_min, v_max - v_min) < config.impostor_max_px)
    return _BoxesInViews(u_min, u_max, v_min, v_max, candidate & ~impostor, impostor)


def _cameras_in_objects(poses: ObjectPoses, cams: RigArrays) -> np.ndarray:
    """(V, N, 3) every camera's centre in every object's frame (centred, yaw undone)."""
    rel = cams.centres[:, None, :] - poses.centre[None]  # (V, N, 3)
    cos, sin = poses.cos, poses.sin
    return np.stack([cos * rel[..., 0] + sin * rel[..., 1], -sin * rel[..., 0] + cos * rel[..., 1], rel[..., 2]], -1)


def _pair_faces(sm: SceneMesh, pair_view: np.ndarray, pair_obj: np.ndarray) -> _PairFaces:
    """Every face of the objects of the (view, object) pairs ``pair_view``, ``pair_obj`` (P,)."""
    counts = sm.face_start[pair_obj + 1] - sm.face_start[pair_obj]
    pair = np.repeat(np.arange(len(pair_obj)), counts)
    obj = pair_obj[pair]
    face = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts) + sm.face_start[obj]
    return _PairFaces(pair, pair_view[pair], obj, face)


def _to_lidar(points: np.ndarray, obj: np.ndarray, poses: ObjectPoses, translate: bool) -> np.ndarray:
    """Object-frame points (M, 3) of objects ``obj`` (M,) -> the LiDAR frame (rotated by the object's
    yaw; moved to its centre when ``translate``, directions are not)."""
    cos, sin = poses.cos[obj], poses.sin[obj]
    out = np.stack([cos * points[:, 0] - sin * points[:, 1], sin * points[:, 0] + cos * points[:, 1], points[:, 2]], 1)
    return out + poses.centre[obj] if translate else out


def _facing(
    sm: SceneMesh, faces: _PairFaces, normals: np.ndarray, centroids: np.ndarray, cams: RigArrays
) -> np.ndarray:
    """Indices of ``faces`` that face their camera; a decal faces it when its parent face does."""
    facing = np.sum(normals[faces.face] * (cams.centres[faces.view] - centroids[faces.face]), axis=1) > 0
    parent = sm.parents[faces.face]
    is_decal = parent >= 0
    own_parent = np.where(is_decal, np.arange(len(faces.face)) - (faces.face - parent), 0)
    return np.nonzero(np.where(is_decal, facing[own_parent], facing))[0]


def _project(
    points: np.ndarray, views: np.ndarray, cams: RigArrays, rig: CameraRig, config: SimConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Camera-frame polygons (K, n, 3) in ``views`` (K,) -> the pixel coordinates u, v of those on
    screen and large enough to draw, and which they are (K,) bool."""
    h, w = rig.resolution
    inv_z = 1.0 / np.maximum(points[..., 2], config.near_plane_m)
    u = cams.fx[views, None] * points[..., 0] * inv_z + cams.cx[views, None]
    v = cams.fy[views, None] * points[..., 1] * inv_z + cams.cy[views, None]
    # Shoelace area; the padding repeats a vertex, which adds nothing.
    twice = np.sum(u[:, :-1] * v[:, 1:] - u[:, 1:] * v[:, :-1], axis=-1) + (u[:, -1] * v[:, 0] - u[:, 0] * v[:, -1])
    large = np.abs(twice) >= 2 * config.min_face_area_px
    ok = (u.min(-1) < w) & (u.max(-1) > 0) & (v.min(-1) < h) & (v.max(-1) > 0) & large
    return u[ok], v[ok], ok


def _face_polygons(
    points: np.ndarray, faces: _PairFaces, shown: np.ndarray, cams: RigArrays, rig: CameraRig, config: SimConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The faces ``shown`` (K,) with their camera-frame vertices ``points`` (K, MAX_FACE_VERTS, 3)
    -> the drawn ones (indices into ``faces``) and their pixel polygons u, v (K', CLIPPED_VERTS).
    Only faces crossing the near plane need clipping; the others are padded to the same layout."""
    z_in = points[..., 2] >= config.near_plane_m
    inside, crossing = z_in.all(1), z_in.any(1) & ~z_in.all(1)
    u, v, ok = _project(points[inside], faces.view[shown[inside]], cams, rig, config)
    u, v = (np.concatenate([a, np.repeat(a[:, -1:], CLIPPED_VERTS - MAX_FACE_VERTS, 1)], 1) for a in (u, v))
    drawn_inside = shown[inside][ok]
    clipped, _ = clip_near(points[crossing], config.near_plane_m)
    u_clipped, v_clipped, ok = _project(clipped, faces.view[shown[crossing]], cams, rig, config)
    drawn = np.concatenate([drawn_inside, shown[crossing][ok]])
    return drawn, np.concatenate([u, u_clipped]), np.concatenate([v, v_clipped])


def _impostor_polygons(boxes: _BoxesInViews) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The impostors' views and objects (I,) and their projected box's bounding rectangles, padded
    to the polygon layout: u, v (I, CLIPPED_VERTS)."""
    views, objs = np.nonzero(boxes.impostor)
    u_min, u_max = boxes.u_min[views, objs], boxes.u_max[views, objs]
    v_min, v_max = boxes.v_min[views, objs], boxes.v_max[views, objs]
    u = np.stack([u_min, u_max, u_max, u_min], -1)
    v = np.stack([v_min, v_min, v_max, v_max], -1)
    u = np.concatenate([u, np.repeat(u[:, -1:], CLIPPED_VERTS - 4, 1)], 1)
    v = np.concatenate([v, np.repeat(v[:, -1:], CLIPPED_VERTS - 4, 1)], 1)
    return views, objs, u, v


def _sun_in_lidar_frame(frame: SceneFrame, lighting: Lighting) -> np.ndarray:
    """(3,) the sun's direction in the ego's LiDAR frame."""
    ce, se = math.cos(frame.ego.yaw), math.sin(frame.ego.yaw)
    sun = lighting.sun_direction
    return np.array([ce * sun[0] + se * sun[1], -se * sun[0] + ce * sun[1], sun[2]])


def plan_objects(
    frame: SceneFrame,
    sm: SceneMesh,
    poses: ObjectPoses,
    rig: CameraRig,
    cams: RigArrays,
    lighting: Lighting,
    config: SimConfig,
) -> DrawPlan:
    """Every polygon to paint for all views of ``frame``, in painting order (module docstring):
    ``config``'s near plane, smallest face, impostor size and sub-pixel bits."""
    boxes = _boxes_in_views(poses, cams, rig, config)
    pair_view, pair_obj = np.nonzero(boxes.detailed)
    # Objects are painted far to near: distance from the camera to the closest point of the box.
    cam_local = _cameras_in_objects(poses, cams)
    obj_dist = np.linalg.norm(cam_local - np.clip(cam_local, -poses.half, poses.half), axis=-1)  # (V, N)
    part_rank = _part_ranks(sm, pair_obj, cam_local[pair_view, pair_obj])

    faces = _pair_faces(sm, pair_view, pair_obj)
    verts = _to_lidar(sm.vertices, sm.vert_obj, poses, True)
    normals = _to_lidar(sm.normals, sm.face_obj, poses, False)
    cents = _to_lidar(sm.centroids, sm.face_obj, poses, True)
    shown = _facing(sm, faces, normals, cents, cams)
    points = _to_cameras(verts, cams)[sm.faces[faces.face[shown]], faces.view[shown, None]]  # (K, 8, 3)
    k, uf, vf = _face_polygons(points, faces, shown, cams, rig, config)
    iv, io, rect_u, rect_v = _impostor_polygons(boxes)

    sun_l = _sun_in_lidar_frame(frame, lighting)
    views = np.concatenate([faces.view[k], iv])
    objs = np.concatenate([faces.obj[k], io])
    face_ids = np.concatenate([faces.face[k], np.full(len(iv), -1)])
    ranks = np.concatenate([part_rank[faces.pair[k], sm.face_part[faces.face[k]]], np.zeros(len(iv), np.int64)])
    decal = np.concatenate([sm.parents[faces.face[k]] >= 0, np.zeros(len(iv), bool)])
    order = np.lexsort((face_ids, decal, ranks, -obj_dist[views, objs], views))
    colors = np.concatenate(
        [
            face_colors(sm, faces.face[k], normals, cents, sun_l, lighting),
            _impostor_colors(sm, poses, sun_l, lighting)[io],
        ]
    )
    albedos = np.concatenate([sm.albedo[faces.face[k]], sm.object_albedo[io]])
    # cv2 puts pixel centres at integer coordinates; ours are at +0.5.
    lim = float(FIXED_POINT_LIMIT_PX)
    uv = np.stack([np.concatenate([uf, rect_u]), np.concatenate([vf, rect_v])], -1) - 0.5
    polys = np.round(np.clip(uv, -lim, lim) * float(1 << config.subpixel_bits)).astype(np.int32)
    return DrawPlan(
        polygons=polys[order],
        colors=colors[order],
        albedos=albedos[order],
        objects=objs[order],
        view_start=np.searchsorted(views[order], np.arange(rig.num_views + 1)),
    )

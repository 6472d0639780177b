import numpy as np

from world_model import Box3D, EgoState, LaneLine, MapGeometry, SceneFrame, SceneObject, ScenePrompt
from world_model.data import Clip, list_clips, read_clip, write_clip
from world_model.geometry import BOX_CORNER_SIGNS, box_corners


def _frame(t=0.0, idx=0, ego_x=0.0):
    road = MapGeometry(
        lane_lines=(LaneLine(points=np.array([[0.0, 2.0], [100.0, 2.0]]), kind="dashed"),),
        road_edges=(np.array([[0.0, 6.0], [100.0, 6.0]]),),
        drivable_area=(np.array([[0.0, -2.0], [100.0, -2.0], [100.0, 6.0], [0.0, 6.0]]),),
    )
    obj = SceneObject(
        track_id="a",
        category="car",
        box=Box3D(center=(20.0, 4.0, 0.8), size=(4.5, 1.9, 1.6), yaw=0.0),
        color=(200, 30, 30),
        color_name="red",
        description="a red sedan",
    )
    return SceneFrame(
        time=t,
        frame_index=idx,
        ego=EgoState(x=ego_x, y=0.0, yaw=0.0, speed=20.0),
        objects=(obj,),
        map=road,
        prompt=ScenePrompt("highway", "rain", "night"),
    )


def test_box_corner_order_front_face_first():
    c = box_corners(np.zeros(3), np.array([4.0, 2.0, 1.0]), 0.0)
    assert np.allclose(c[:4, 0], 2.0) and np.allclose(c[4:, 0], -2.0)
    assert np.allclose(c[0], [2, 1, 0.5]) and np.allclose(c[2], [2, -1, -0.5])
    assert np.allclose(c, BOX_CORNER_SIGNS * [2, 1, 0.5])
    # yawed 90 degrees left: the front face now points to +y
    c90 = box_corners(np.zeros(3), np.array([4.0, 2.0, 1.0]), np.pi / 2)
    assert np.allclose(c90[:4, 1], 2.0)


def test_object_corners_in_lidar_frame_stand_on_road():
    fr = _frame(ego_x=5.0)
    corners = fr.object_corners_lidar()[0]
    assert np.allclose(corners[:, 2].min(), -fr.lidar.mount_height)
    assert np.allclose(corners[:, 0].mean(), 15.0) and np.allclose(corners[:, 1].mean(), 4.0)


def test_ego_pose_condition_relative_to_first():
    first = EgoState(x=10.0, y=5.0, yaw=np.pi / 2)
    fr = SceneFrame(time=0, frame_index=0, ego=EgoState(x=10.0, y=8.0, yaw=np.pi / 2), objects=(), map=MapGeometry())
    m = fr.ego_pose_condition(first)
    assert m.shape == (4, 3)
    assert np.allclose(m[:3], np.eye(3), atol=1e-6)
    assert np.allclose(m[3], [3.0, 0.0, 0.0], atol=1e-6)  # 3 m straight ahead of the first pose


def test_scene_frame_json_roundtrip():
    fr = _frame()
    back = SceneFrame.from_json(fr.to_json())
    assert back.to_dict() == fr.to_dict()


def test_clip_write_read_roundtrip(tmp_path):
    frames = [_frame(t=i * 0.1, idx=i, ego_x=i * 2.0) for i in range(3)]
    v, h, w = frames[0].rig.num_views, 8, 16
    cams = np.random.default_rng(0).integers(0, 255, (3, v, h, w, 3), dtype=np.uint8)
    lidar = np.full((3, 4, 32), 12.5, dtype=np.float32)
    bev = np.zeros((3, 8, 8, 3), dtype=np.uint8)
    write_clip(tmp_path, Clip("clip_000", frames, cams, lidar, bev, crops={"a": np.zeros((4, 4, 3), np.uint8)}))
    assert list_clips(tmp_path) == ["clip_000"]
    clip = read_clip(tmp_path, "clip_000")
    assert clip.num_frames == 3 and abs(clip.fps - 10.0) < 1e-6
    assert np.array_equal(clip.cameras, cams) and np.allclose(clip.lidar, 12.5)
    assert clip.frames[2].to_dict() == frames[2].to_dict()
    assert clip.frames[0].map is clip.frames[2].map
    assert "a" in clip.crops

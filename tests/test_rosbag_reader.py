"""ROS 1 / ROS 2 bag reader: bags written here with rosbags writers from real 7-Scenes frames
read back to the observations of the TUM folder they were made from."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from itertools import islice
from pathlib import Path

import numpy as np
import pytest
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from scipy.spatial.transform import Rotation, Slerp

from onfly.cli import main as cli_main
from onfly.readers.rosbag import BagConfig, BagFormatError, BagReader, bag_summary, image_to_array, resolve_bag_path
from onfly.readers.tum import TumReader
from planning.frames import quat_from_matrix
from realdata_paths import REALDATA

KITCHEN = REALDATA / "7scenes-kitchen-tum"
N_FRAMES = 3


@pytest.fixture(scope="module")
def kitchen():
    reader = TumReader(KITCHEN)
    return list(islice(reader, N_FRAMES))


def _typestore(ros2: bool):
    if ros2:
        return get_typestore(Stores.ROS2_HUMBLE)
    store = get_typestore(Stores.ROS1_NOETIC)
    store.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage"))
    return store


def _stamp(store, t_ns: int, frame_id: str, ros2: bool):
    Time = store.types["builtin_interfaces/msg/Time"]
    Header = store.types["std_msgs/msg/Header"]
    stamp = Time(sec=t_ns // 1_000_000_000, nanosec=t_ns % 1_000_000_000)
    return Header(stamp=stamp, frame_id=frame_id) if ros2 else Header(seq=0, stamp=stamp, frame_id=frame_id)


def _image(store, header, arr: np.ndarray, encoding: str, pad_bytes: int = 0):
    h, w = arr.shape[:2]
    row = np.ascontiguousarray(arr).view(np.uint8).reshape(h, -1)
    if pad_bytes:
        row = np.concatenate([row, np.full((h, pad_bytes), 7, np.uint8)], axis=1)
    return store.types["sensor_msgs/msg/Image"](
        header=header, height=h, width=w, encoding=encoding, is_bigendian=0, step=row.shape[1], data=row.reshape(-1)
    )


def _camera_info(store, header, cam, ros2: bool):
    K = np.array([cam.fx, 0, cam.cx, 0, cam.fy, cam.cy, 0, 0, 1], dtype=float)
    RoI = store.types["sensor_msgs/msg/RegionOfInterest"]
    fields = dict(
        header=header,
        height=cam.height,
        width=cam.width,
        distortion_model="plumb_bob",
        binning_x=0,
        binning_y=0,
        roi=RoI(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False),
    )
    mats = {"D": np.zeros(5), "K": K, "R": np.eye(3).reshape(-1), "P": np.zeros(12)}
    fields.update({(k.lower() if ros2 else k): v for k, v in mats.items()})
    return store.types["sensor_msgs/msg/CameraInfo"](**fields)


def _pose_msgs(store, header, T: np.ndarray):
    q = quat_from_matrix(T[:3, :3])
    Point = store.types["geometry_msgs/msg/Point"]
    Quat = store.types["geometry_msgs/msg/Quaternion"]
    pose = store.types["geometry_msgs/msg/Pose"](
        position=Point(x=T[0, 3], y=T[1, 3], z=T[2, 3]), orientation=Quat(x=q[1], y=q[2], z=q[3], w=q[0])
    )
    return pose, q


def write_bag(
    path: Path,
    observations,
    *,
    ros2: bool,
    depth_encoding: str = "32FC1",
    rgb_encoding: str = "rgb8",
    pose_type: str = "odometry",
    rgb_offset_ns: int = 0,
    pose_every: int = 1,
    with_camera_info: bool = True,
    raw_depth_16u: list[np.ndarray] | None = None,
    pad_bytes: int = 0,
) -> Path:
    """Write ``observations`` as a bag: /camera/depth/image_raw, /camera/color/image_raw,
    /camera/depth/camera_info and a pose topic (/odom, /pose or /tf)."""
    store = _typestore(ros2)
    ser = store.serialize_cdr if ros2 else store.serialize_ros1
    pose_types = {
        "odometry": ("/odom", "nav_msgs/msg/Odometry"),
        "posestamped": ("/pose", "geometry_msgs/msg/PoseStamped"),
        "tf": ("/tf", "tf2_msgs/msg/TFMessage"),
    }
    pose_topic, pose_msgtype = pose_types[pose_type]
    writer = Writer2(path, version=9) if ros2 else Writer1(path)
    with writer:
        c_depth = writer.add_connection("/camera/depth/image_raw", "sensor_msgs/msg/Image", typestore=store)
        c_rgb = writer.add_connection("/camera/color/image_raw", "sensor_msgs/msg/Image", typestore=store)
        c_info = writer.add_connection("/camera/depth/camera_info", "sensor_msgs/msg/CameraInfo", typestore=store) if with_camera_info else None
        c_pose = writer.add_connection(pose_topic, pose_msgtype, typestore=store)
        base_ns = 1_000_000  # bag receive times start at 1 ms (a zero receive time is legal but unusual)
        for k, obs in enumerate(observations):
            t_ns = round(obs.t_s * 1e9)
            hdr = _stamp(store, t_ns, "camera_depth_optical_frame", ros2)
            if raw_depth_16u is not None:
                depth_arr = raw_depth_16u[k]
            elif depth_encoding == "32FC1":
                depth_arr = obs.depth_m.astype(np.float32)
            elif depth_encoding in ("16UC1", "mono16"):
                depth_arr = np.round(obs.depth_m * 1000.0).astype(np.uint16)
            else:
                depth_arr = (obs.depth_m * 10).astype(np.uint8)
            writer.write(c_depth, base_ns + t_ns, ser(_image(store, hdr, depth_arr, depth_encoding, pad_bytes), "sensor_msgs/msg/Image"))
            rgb = obs.rgb[:, :, ::-1] if rgb_encoding == "bgr8" else obs.rgb
            hdr_rgb = _stamp(store, t_ns + rgb_offset_ns, "camera_color_optical_frame", ros2)
            writer.write(c_rgb, base_ns + t_ns + rgb_offset_ns, ser(_image(store, hdr_rgb, rgb, rgb_encoding), "sensor_msgs/msg/Image"))
            if c_info is not None:
                writer.write(c_info, base_ns + t_ns, ser(_camera_info(store, hdr, obs.camera, ros2), "sensor_msgs/msg/CameraInfo"))
            if k % pose_every:
                continue
            hdr_pose = _stamp(store, t_ns, "world", ros2)
            pose, q = _pose_msgs(store, hdr_pose, obs.T_world_cam)
            if pose_type == "odometry":
                PoseCov = store.types["geometry_msgs/msg/PoseWithCovariance"]
                Twist = store.types["geometry_msgs/msg/Twist"]
                TwistCov = store.types["geometry_msgs/msg/TwistWithCovariance"]
                V3 = store.types["geometry_msgs/msg/Vector3"]
                msg = store.types["nav_msgs/msg/Odometry"](
                    header=hdr_pose,
                    child_frame_id="camera",
                    pose=PoseCov(pose=pose, covariance=np.zeros(36)),
                    twist=TwistCov(twist=Twist(linear=V3(x=0, y=0, z=0), angular=V3(x=0, y=0, z=0)), covariance=np.zeros(36)),
                )
            elif pose_type == "posestamped":
                msg = store.types["geometry_msgs/msg/PoseStamped"](header=hdr_pose, pose=pose)
            else:
                V3 = store.types["geometry_msgs/msg/Vector3"]
                Quat = store.types["geometry_msgs/msg/Quaternion"]
                TS = store.types["geometry_msgs/msg/TransformStamped"]
                Tr = store.types["geometry_msgs/msg/Transform"]
                tr = TS(
                    header=hdr_pose,
                    child_frame_id="camera",
                    transform=Tr(
                        translation=V3(x=obs.T_world_cam[0, 3], y=obs.T_world_cam[1, 3], z=obs.T_world_cam[2, 3]),
                        rotation=Quat(x=q[1], y=q[2], z=q[3], w=q[0]),
                    ),
                )
                other = TS(header=_stamp(store, t_ns, "camera", ros2), child_frame_id="imu", transform=tr.transform)
                msg = store.types["tf2_msgs/msg/TFMessage"](transforms=[other, tr])
            writer.write(c_pose, base_ns + t_ns, ser(msg, pose_msgtype))
    return path


def _bag_path(tmp_path: Path, ros2: bool, name: str = "rec") -> Path:
    return tmp_path / (name if ros2 else f"{name}.bag")


def _assert_same(got, want, depth_atol: float = 0.0) -> None:
    assert len(got) == len(want)
    for g, w in zip(got, want):
        assert g.t_s == w.t_s
        np.testing.assert_array_equal(g.rgb, w.rgb)
        assert g.depth_m.dtype == np.float32
        if depth_atol == 0.0:
            np.testing.assert_array_equal(g.depth_m, w.depth_m)
        else:
            np.testing.assert_allclose(g.depth_m, w.depth_m, rtol=0, atol=depth_atol)
        np.testing.assert_allclose(g.T_world_cam, w.T_world_cam, rtol=0, atol=1e-12)
        np.testing.assert_array_equal(g.T_body_cam, w.T_body_cam)
        assert g.camera == w.camera


@pytest.mark.parametrize("ros2", [False, True], ids=["ros1", "ros2"])
@pytest.mark.parametrize("depth_encoding", ["16UC1", "32FC1"])
@pytest.mark.parametrize("pose_type", ["odometry", "posestamped"])
def test_bag_reads_back_the_tum_observations(tmp_path, kitchen, ros2, depth_encoding, pose_type):
    path = write_bag(_bag_path(tmp_path, ros2), kitchen, ros2=ros2, depth_encoding=depth_encoding, pose_type=pose_type)
    with BagReader(path) as reader:
        assert reader.kind == ("ros2-bag" if ros2 else "ros1-bag")
        assert reader.topics["depth"] == "/camera/depth/image_raw"
        assert reader.topics["rgb"] == "/camera/color/image_raw"
        assert reader.topics["camera_info"] == "/camera/depth/camera_info"
        assert len(reader) == N_FRAMES
        got = list(reader)
    # 16UC1 stores whole millimetres: the TUM depth (1/5000 m steps) rounds by at most 0.5 mm.
    _assert_same(got, kitchen, depth_atol=0.0 if depth_encoding == "32FC1" else 0.5e-3 + 1e-7)
    assert got[0].depth_m[got[0].depth_m > 0].size > 0.5 * got[0].depth_m.size


def test_16uc1_with_tum_scale_is_exact(tmp_path, kitchen):
    raw = [np.round(o.depth_m * 5000.0).astype(np.uint16) for o in kitchen]
    path = write_bag(tmp_path / "rec.bag", kitchen, ros2=False, depth_encoding="16UC1", raw_depth_16u=raw)
    with BagReader(path, BagConfig(depth_scale_16u=5000.0)) as reader:
        _assert_same(list(reader), kitchen)


def test_bgr8_padded_rows_and_tf_poses(tmp_path, kitchen):
    path = write_bag(tmp_path / "rec", kitchen, ros2=True, rgb_encoding="bgr8", pose_type="tf", pad_bytes=6)
    cfg = BagConfig(pose_topic="/tf", tf_parent_frame="/world", tf_child_frame="camera")
    with BagReader(path, cfg) as reader:
        _assert_same(list(reader), kitchen)
    # the same transform asked for the other way round is the inverse
    inv = BagConfig(pose_topic="/tf", tf_parent_frame="camera", tf_child_frame="world")
    with BagReader(path, inv) as reader:
        T = next(iter(reader)).T_world_cam
    np.testing.assert_allclose(T @ kitchen[0].T_world_cam, np.eye(4), atol=1e-12)


def test_tf_without_the_named_transform_names_topic_and_frames(tmp_path, kitchen):
    path = write_bag(tmp_path / "rec.bag", kitchen, ros2=False, pose_type="tf")
    with pytest.raises(BagFormatError, match=r"topic /tf has no transform map->base_link \(transforms seen: camera->imu, world->camera\)"):
        BagReader(path, BagConfig(pose_topic="/tf", tf_parent_frame="map", tf_child_frame="base_link"))
    with pytest.raises(BagFormatError, match=r"/tf is a TF topic; pass tf_parent_frame"):
        BagReader(path, BagConfig(pose_topic="/tf"))


def test_rgb_association_tolerance(tmp_path, kitchen):
    # colour 10 ms after depth: within the 20 ms default, frames keep the depth stamp
    path = write_bag(tmp_path / "near.bag", kitchen, ros2=False, rgb_offset_ns=10_000_000)
    with BagReader(path) as reader:
        _assert_same(list(reader), kitchen)
    # 25 ms late at 30 Hz: colour k lies 8.3 ms before depth k+1, so the nearest match pairs
    # depth k+1 with colour k and depth 0 (nothing within 20 ms) is dropped
    path = write_bag(tmp_path / "late.bag", kitchen, ros2=False, rgb_offset_ns=25_000_000)
    with BagReader(path) as reader:
        assert reader.dropped == {"no_rgb": 1, "no_pose": 0}
        got = list(reader)
    assert [o.t_s for o in got] == [o.t_s for o in kitchen[1:]]
    for g, w in zip(got, kitchen[:-1]):
        np.testing.assert_array_equal(g.rgb, w.rgb)
    with pytest.raises(BagFormatError, match=r"no depth image on /camera/depth/image_raw has an rgb image on /camera/color/image_raw within 0.005 s"):
        BagReader(path, BagConfig(max_difference_s=0.005))


def test_pose_interpolated_at_the_depth_stamp(tmp_path, kitchen):
    path = write_bag(tmp_path / "rec.bag", kitchen, ros2=False, pose_every=2)  # poses at frames 0 and 2
    with BagReader(path) as reader:
        got = list(reader)
    assert len(got) == N_FRAMES
    mid = got[1].T_world_cam
    t0, t1, t2 = (o.t_s for o in kitchen)
    u = (t1 - t0) / (t2 - t0)
    np.testing.assert_allclose(mid[:3, 3], (1 - u) * kitchen[0].T_world_cam[:3, 3] + u * kitchen[2].T_world_cam[:3, 3], atol=1e-12)
    ref = Slerp([t0, t2], Rotation.from_matrix([kitchen[0].T_world_cam[:3, :3], kitchen[2].T_world_cam[:3, :3]]))([t1])
    np.testing.assert_allclose(mid[:3, :3], ref.as_matrix()[0], atol=1e-9)
    np.testing.assert_allclose(got[2].T_world_cam, kitchen[2].T_world_cam, atol=1e-12)


def test_missing_topic_names_the_topic_and_lists_what_is_there(tmp_path, kitchen):
    path = write_bag(tmp_path / "rec", kitchen, ros2=True)
    with pytest.raises(BagFormatError, match=r"no topic /camera/aligned_depth for depth \(topics: .*/camera/color/image_raw \(sensor_msgs/msg/Image\)"):
        BagReader(path, BagConfig(depth_topic="/camera/aligned_depth"))
    with pytest.raises(BagFormatError, match=r"topic /odom for rgb has type nav_msgs/msg/Odometry, expected sensor_msgs/msg/Image"):
        BagReader(path, BagConfig(rgb_topic="/odom"))


def test_wrong_depth_encoding_names_the_topic(tmp_path, kitchen):
    path = write_bag(tmp_path / "rec.bag", kitchen, ros2=False, depth_encoding="mono8")
    with pytest.raises(BagFormatError, match=r"topic /camera/depth/image_raw: image encoding 'mono8' is not supported \(expected one of 16UC1, mono16, 32FC1\)"):
        BagReader(path)


def test_no_camera_info_needs_intrinsics(tmp_path, kitchen):
    path = write_bag(tmp_path / "rec.bag", kitchen, ros2=False, with_camera_info=False)
    with pytest.raises(BagFormatError, match=r"no topic for camera_info found; pass camera_info_topic or intrinsics"):
        BagReader(path)
    cam = kitchen[0].camera
    with BagReader(path, BagConfig(intrinsics=(cam.fx, cam.fy, cam.cx, cam.cy))) as reader:
        _assert_same(list(reader), kitchen)


def test_image_to_array_handles_big_endian_and_rejects_short_data(kitchen):
    store = get_typestore(Stores.ROS2_HUMBLE)
    hdr = _stamp(store, 0, "cam", True)
    depth = np.array([[1, 256], [513, 65535]], dtype=np.uint16)
    msg = _image(store, hdr, depth.astype(">u2"), "16UC1")
    msg.is_bigendian = 1
    out = image_to_array(msg, "/d", ("16UC1",))
    assert out.dtype == np.uint16 and out.dtype.isnative
    np.testing.assert_array_equal(out, depth)
    msg.data = msg.data[:5]
    with pytest.raises(BagFormatError, match=r"topic /d: image data of 5 bytes does not hold 2 rows of step 4"):
        image_to_array(msg, "/d", ("16UC1",))


def test_bag_summary_lists_topics_counts_and_span(tmp_path, kitchen):
    for ros2 in (False, True):
        path = write_bag(_bag_path(tmp_path, ros2), kitchen, ros2=ros2, pose_type="posestamped")
        s = bag_summary(path)
        assert s.kind == ("ros2-bag" if ros2 else "ros1-bag")
        assert s.messages == 4 * N_FRAMES
        assert {t.name: (t.msgtype, t.count) for t in s.topics} == {
            "/camera/color/image_raw": ("sensor_msgs/msg/Image", N_FRAMES),
            "/camera/depth/camera_info": ("sensor_msgs/msg/CameraInfo", N_FRAMES),
            "/camera/depth/image_raw": ("sensor_msgs/msg/Image", N_FRAMES),
            "/pose": ("geometry_msgs/msg/PoseStamped", N_FRAMES),
        }
        assert s.start_ns == 1_000_000
        assert s.duration_s == pytest.approx(kitchen[-1].t_s - kitchen[0].t_s, abs=1e-9)


def test_resolve_bag_path_rejects_other_things(tmp_path):
    with pytest.raises(BagFormatError, match=r"nothing\.bag: no such file or directory"):
        resolve_bag_path(tmp_path / "nothing.bag")
    (tmp_path / "notes.txt").write_text("hi")
    with pytest.raises(BagFormatError, match=r"notes\.txt: not a ROS 1 \.bag file or a ROS 2 bag directory"):
        resolve_bag_path(tmp_path / "notes.txt")
    (tmp_path / "broken.bag").write_bytes(b"#ROSBAG V2.0\n garbage")
    with pytest.raises(BagFormatError, match=r"broken\.bag: cannot open bag"):
        BagReader(tmp_path / "broken.bag")


# -- onfly bag-info ------------------------------------------------------------------------------


@pytest.mark.parametrize("ros2", [False, True], ids=["ros1", "ros2"])
def test_bag_info_command_prints_the_table(tmp_path, kitchen, capsys, ros2):
    path = write_bag(_bag_path(tmp_path, ros2), kitchen, ros2=ros2)
    assert cli_main(["bag-info", str(path)]) == 0
    out = capsys.readouterr().out
    assert f"format:    ROS {'2' if ros2 else '1'} bag" in out
    assert "messages:  12" in out
    assert re.search(r"/camera/depth/image_raw\s+sensor_msgs/msg/Image\s+3 msgs", out)
    assert re.search(r"/odom\s+nav_msgs/msg/Odometry\s+3 msgs", out)
    assert "duration:  0.067 s" in out
    assert cli_main(["bag-info", "--json", str(path)]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["messages"] == 12 and {"name": "/odom", "type": "nav_msgs/msg/Odometry", "count": 3} in summary["topics"]


def test_bag_info_on_a_missing_file_is_one_line_and_exit_2(tmp_path):
    proc = subprocess.run(
        [sys.executable, "-m", "onfly.cli", "bag-info", str(tmp_path / "missing.bag")], capture_output=True, text=True, timeout=60
    )
    assert proc.returncode == 2
    assert proc.stderr.strip() == f"onfly bag-info: error: {tmp_path / 'missing.bag'}: no such file or directory"
    assert proc.stdout == ""

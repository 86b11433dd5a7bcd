"""Seeds of the `ros2_messages` fuzz target, serialized by rosbags (an outside CDR encoder):
records `[topic index][u32 LE length][CDR payload]` of a 16UC1 depth image with its
CameraInfo (topics 0, 1), a PointCloud2 (topic 2), a /tf_static TFMessage (topic 3), and an
image, its info and a cloud of the same stamp for one camera (topics 4, 5, 6).

    python3 fuzz/ros2_seeds.py fuzz/seeds/ros2_messages
"""
import struct
import sys
from pathlib import Path

import numpy as np
from rosbags.typesys import Stores, get_typestore

ts = get_typestore(Stores.ROS2_HUMBLE)
Header = ts.types["std_msgs/msg/Header"]
Time = ts.types["builtin_interfaces/msg/Time"]
Image = ts.types["sensor_msgs/msg/Image"]
CameraInfo = ts.types["sensor_msgs/msg/CameraInfo"]
RegionOfInterest = ts.types["sensor_msgs/msg/RegionOfInterest"]
PointCloud2 = ts.types["sensor_msgs/msg/PointCloud2"]
PointField = ts.types["sensor_msgs/msg/PointField"]
TFMessage = ts.types["tf2_msgs/msg/TFMessage"]
TransformStamped = ts.types["geometry_msgs/msg/TransformStamped"]
Transform = ts.types["geometry_msgs/msg/Transform"]
Vector3 = ts.types["geometry_msgs/msg/Vector3"]
Quaternion = ts.types["geometry_msgs/msg/Quaternion"]


def header(frame):
    return Header(stamp=Time(sec=1, nanosec=500), frame_id=frame)


def record(topic, msg, typename):
    payload = bytes(ts.serialize_cdr(msg, typename))
    return struct.pack("<BI", topic, len(payload)) + payload


w, h = 8, 6
depth = (np.arange(w * h, dtype=np.uint16) % 7 + 600).astype("<u2")
image = Image(header=header("cam0"), height=h, width=w, encoding="16UC1", is_bigendian=0,
              step=2 * w, data=np.frombuffer(depth.tobytes(), dtype=np.uint8))
info = CameraInfo(header=header("cam0"), height=h, width=w, distortion_model="plumb_bob",
                  d=np.zeros(5), k=np.array([6.0, 0, 4, 0, 6.0, 3, 0, 0, 1]),
                  r=np.eye(3).flatten(), p=np.array([6.0, 0, 4, 0, 0, 6.0, 3, 0, 0, 0, 1, 0]),
                  binning_x=0, binning_y=0,
                  roi=RegionOfInterest(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))
points = np.array([[0.1 * i, 0.0, 0.6, 0.0] for i in range(5)], dtype="<f4")
cloud = PointCloud2(header=header("cam1"), height=1, width=5,
                    fields=[PointField(name=n, offset=4 * k, datatype=7, count=1)
                            for k, n in enumerate("xyz")],
                    is_bigendian=False, point_step=16, row_step=80,
                    data=np.frombuffer(points.tobytes(), dtype=np.uint8), is_dense=False)
tf = TFMessage(transforms=[TransformStamped(
    header=header("world"), child_frame_id="cam1",
    transform=Transform(translation=Vector3(x=0.0, y=0.0, z=1.0),
                        rotation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)))])

out = Path(sys.argv[1])
out.mkdir(parents=True, exist_ok=True)
img = record(0, image, Image.__msgtype__) + record(1, info, CameraInfo.__msgtype__)
pc = record(3, tf, TFMessage.__msgtype__) + record(2, cloud, PointCloud2.__msgtype__)
(out / "depth_image_and_info").write_bytes(img)
(out / "tf_and_pointcloud").write_bytes(pc)
(out / "all").write_bytes(img + pc)
organized = np.array([[0.01 * i, 0.02, 0.6, 0.0] for i in range(w * h)], dtype="<f4")
beside = PointCloud2(header=header("cam2"), height=h, width=w,
                     fields=[PointField(name=n, offset=4 * k, datatype=7, count=1)
                             for k, n in enumerate("xyz")],
                     is_bigendian=False, point_step=16, row_step=16 * w,
                     data=np.frombuffer(organized.tobytes(), dtype=np.uint8), is_dense=False)
(out / "image_info_and_cloud").write_bytes(
    record(4, image, Image.__msgtype__) + record(6, beside, PointCloud2.__msgtype__)
    + record(5, info, CameraInfo.__msgtype__))

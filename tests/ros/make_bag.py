"""A ROS bag of 7-Scenes frames, written by the `rosbags` package as a RealSense driver's topics
would be recorded, for `tests/tests/ros_bags.rs` and `tests/tests/ros_topics.rs`.

    python make_bag.py SEVEN_SCENES_DIR OUT FRAMES [--raw DIR] [--storage mcap|sqlite3|ros1]
                       [--corrupt]

Colour: `CompressedImage` with each frame's JPEG file as it is; depth: `CompressedImage` in
`16UC1; compressedDepth png` with each frame's PNG file after the plugin's 12-byte
configuration. With --raw DIR, raw `Image`s instead, of the pixels the caller decoded there
(`frame-NNNNNN.grey`: 8-bit, `frame-NNNNNN.depth`: little-endian 16-bit), as `mono8` with
four bytes of padding a row and `16UC1`; the colour camera's `CameraInfo` from
`camera-intrinsics.txt` (plumb_bob, zero distortion). Stamps: 1,700,000,000 s plus the frame's
index times 33,333,333 ns (7-Scenes is 30 Hz without stamps); depth in its own frame_id, as
7-Scenes' depth is not registered. An IMU topic the reader must pass over is recorded too.

Storage: a rosbag2 folder OUT in MCAP (the default) or SQLite (`sqlite3`), or with `ros1` a
ROS 1 bag file OUT (Noetic's message layout, chunks compressed with bz2). With `--corrupt`, a
colour message that is not a message comes after the second frame, which a reader must skip.
"""
import argparse
import os
import struct

import numpy as np
from rosbags.typesys import Stores, get_typestore

BASE_NS = 1_700_000_000 * 10**9
PERIOD_NS = 10**9 // 30
NS = "/camera/camera"


class Messages:
    """The message types of one ROS generation, and how its messages are serialised."""

    def __init__(self, ros1):
        self.ros1 = ros1
        self.store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
        t = self.store.types
        self.Header, self.Time = t["std_msgs/msg/Header"], t["builtin_interfaces/msg/Time"]
        self.Compressed, self.Info = t["sensor_msgs/msg/CompressedImage"], t["sensor_msgs/msg/CameraInfo"]
        self.Roi, self.Imu = t["sensor_msgs/msg/RegionOfInterest"], t["sensor_msgs/msg/Imu"]
        self.Quaternion, self.Vector3 = t["geometry_msgs/msg/Quaternion"], t["geometry_msgs/msg/Vector3"]
        self.Raw = t["sensor_msgs/msg/Image"]

    def serialize(self, msg):
        if self.ros1:
            return self.store.serialize_ros1(msg, msg.__msgtype__)
        return self.store.serialize_cdr(msg, msg.__msgtype__)

    def header(self, stamp, frame):
        time = self.Time(sec=stamp // 10**9, nanosec=stamp % 10**9)
        if self.ros1:
            return self.Header(seq=0, stamp=time, frame_id=frame)
        return self.Header(stamp=time, frame_id=frame)

    def raw_image(self, stamp, frame, encoding, pixels, bytes_per_pixel, padding):
        row = 640 * bytes_per_pixel
        rows = pixels.reshape(480, row)
        padded = np.zeros((480, row + padding), dtype=np.uint8)
        padded[:, :row] = rows
        return self.Raw(header=self.header(stamp, frame), height=480, width=640,
                        encoding=encoding, is_bigendian=0, step=row + padding,
                        data=padded.flatten())

    def camera_info(self, stamp, k):
        fields = dict(d=np.zeros(5), k=np.array(k), r=np.eye(3).flatten(),
                      p=np.array(k[:3] + [0] + k[3:6] + [0] + k[6:] + [0]))
        if self.ros1:
            fields = {name.upper(): value for name, value in fields.items()}
        return self.Info(
            header=self.header(stamp, "camera_color_optical_frame"), height=480, width=640,
            distortion_model="plumb_bob", binning_x=0, binning_y=0,
            roi=self.Roi(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False),
            **fields)

    def imu(self, stamp):
        return self.Imu(
            header=self.header(stamp, "camera_imu_optical_frame"),
            orientation=self.Quaternion(x=0.0, y=0.0, z=0.0, w=1.0),
            orientation_covariance=np.zeros(9),
            angular_velocity=self.Vector3(x=0.0, y=0.0, z=0.0),
            angular_velocity_covariance=np.zeros(9),
            linear_acceleration=self.Vector3(x=0.0, y=0.0, z=9.81),
            linear_acceleration_covariance=np.zeros(9))


def open_bag(out, storage):
    if storage == "ros1":
        from rosbags.rosbag1 import Writer
        writer = Writer(out)
        writer.set_compression(Writer.CompressionFormat.BZ2)
        return writer
    from rosbags.rosbag2 import StoragePlugin, Writer
    plugin = StoragePlugin.SQLITE3 if storage == "sqlite3" else StoragePlugin.MCAP
    return Writer(out, version=9, storage_plugin=plugin)


def main(src, out, frames, raw=None, storage="mcap", corrupt=False):
    m = Messages(storage == "ros1")
    with open(os.path.join(src, "camera-intrinsics.txt")) as f:
        k = [float(v) for v in f.read().split()]
    with open_bag(out, storage) as bag:
        def connect(topic, kind):
            return bag.add_connection(topic, kind.__msgtype__, typestore=m.store)

        if raw:
            colour = connect(f"{NS}/color/image_raw", m.Raw)
            depth = connect(f"{NS}/depth/image_rect_raw", m.Raw)
        else:
            colour = connect(f"{NS}/color/image_raw/compressed", m.Compressed)
            depth = connect(f"{NS}/depth/image_rect_raw/compressedDepth", m.Compressed)
        info = connect(f"{NS}/color/camera_info", m.Info)
        imu = connect(f"{NS}/imu", m.Imu)

        def put(connection, stamp, msg):
            bag.write(connection, stamp, m.serialize(msg))

        for i in range(frames):
            stamp = BASE_NS + i * PERIOD_NS
            put(info, stamp, m.camera_info(stamp, k))
            if raw:
                grey = np.fromfile(os.path.join(raw, f"frame-{i:06d}.grey"), dtype=np.uint8)
                put(colour, stamp, m.raw_image(stamp, "camera_color_optical_frame", "mono8",
                                               grey, 1, 4))
            else:
                with open(os.path.join(src, f"frame-{i:06d}.color.jpg"), "rb") as f:
                    jpeg = f.read()
                put(colour, stamp, m.Compressed(
                    header=m.header(stamp, "camera_color_optical_frame"),
                    format="rgb8; jpeg compressed bgr8",
                    data=np.frombuffer(jpeg, dtype=np.uint8)))
            put(imu, stamp + PERIOD_NS // 2, m.imu(stamp + PERIOD_NS // 2))
            if corrupt and i == 2:
                bag.write(colour, stamp + 2_000_000, b"\x00\x01\x00\x00not an image")
            # Depth is logged a little after colour, as a driver's second stream would be.
            if raw:
                mm = np.fromfile(os.path.join(raw, f"frame-{i:06d}.depth"), dtype=np.uint8)
                put(depth, stamp + 1_000_000, m.raw_image(stamp, "camera_depth_optical_frame",
                                                          "16UC1", mm, 2, 0))
            else:
                with open(os.path.join(src, f"frame-{i:06d}.depth.png"), "rb") as f:
                    png = f.read()
                put(depth, stamp + 1_000_000, m.Compressed(
                    header=m.header(stamp, "camera_depth_optical_frame"),
                    format="16UC1; compressedDepth png",
                    data=np.frombuffer(struct.pack("<iff", 0, 0.0, 0.0) + png, dtype=np.uint8)))


if __name__ == "__main__":
    parser = argparse.ArgumentParser()
    parser.add_argument("src")
    parser.add_argument("out")
    parser.add_argument("frames", type=int)
    parser.add_argument("--raw")
    parser.add_argument("--storage", default="mcap", choices=["mcap", "sqlite3", "ros1"])
    parser.add_argument("--corrupt", action="store_true")
    a = parser.parse_args()
    main(a.src, a.out, a.frames, a.raw, a.storage, a.corrupt)

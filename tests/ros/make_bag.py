"""A ROS 2 bag (MCAP) of 7-Scenes frames, written by the `rosbags` package as a RealSense
driver's topics would be recorded, for `tests/tests/ros_bags.rs`.

    python make_bag.py SEVEN_SCENES_DIR OUT_BAG_DIR FRAMES [--raw DIR] [--storage sqlite3]
                       [--corrupt]

Colour: `CompressedImage` with each frame's JPEG file as it is; depth: `CompressedImage` in
`16UC1; compressedDepth png` with each frame's PNG file after the plugin's 12-byte
configuration. With --raw DIR, raw `Image`s instead, of the pixels the caller decoded there
(`frame-NNNNNN.grey`: 8-bit, `frame-NNNNNN.depth`: little-endian 16-bit), as `mono8` with
four bytes of padding a row and `16UC1`; the colour camera's `CameraInfo` from `camera-intrinsics.txt` (plumb_bob, zero
distortion). Stamps: 1,700,000,000 s plus the frame's index times 33,333,333 ns (7-Scenes is
30 Hz without stamps); depth in its own frame_id, as 7-Scenes' depth is not registered. An IMU
topic the reader must pass over is recorded too. The storage is MCAP, or SQLite (`.db3`) with
`--storage sqlite3`. With `--corrupt`, a colour message that is not CDR comes after the second
frame, which a reader must skip.
"""
import argparse
import os
import struct

import numpy as np
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

TS = get_typestore(Stores.ROS2_HUMBLE)
T = TS.types
Header, Time = T["std_msgs/msg/Header"], T["builtin_interfaces/msg/Time"]
Compressed, Info = T["sensor_msgs/msg/CompressedImage"], T["sensor_msgs/msg/CameraInfo"]
Roi, Imu = T["sensor_msgs/msg/RegionOfInterest"], T["sensor_msgs/msg/Imu"]
Quaternion, Vector3 = T["geometry_msgs/msg/Quaternion"], T["geometry_msgs/msg/Vector3"]
Raw = T["sensor_msgs/msg/Image"]

BASE_NS = 1_700_000_000 * 10**9
PERIOD_NS = 10**9 // 30
NS = "/camera/camera"


def header(stamp, frame):
    return Header(stamp=Time(sec=stamp // 10**9, nanosec=stamp % 10**9), frame_id=frame)


def raw_image(stamp, frame, encoding, pixels, bytes_per_pixel, padding):
    row = 640 * bytes_per_pixel
    rows = pixels.reshape(480, row)
    padded = np.zeros((480, row + padding), dtype=np.uint8)
    padded[:, :row] = rows
    return Raw(header=header(stamp, frame), height=480, width=640, encoding=encoding,
               is_bigendian=0, step=row + padding, data=padded.flatten())


def main(src, out, frames, raw=None, storage="mcap", corrupt=False):
    with open(os.path.join(src, "camera-intrinsics.txt")) as f:
        k = [float(v) for v in f.read().split()]
    plugin = StoragePlugin.SQLITE3 if storage == "sqlite3" else StoragePlugin.MCAP
    with Writer(out, version=9, storage_plugin=plugin) as bag:
        if raw:
            colour = bag.add_connection(f"{NS}/color/image_raw", Raw.__msgtype__, typestore=TS)
            depth = bag.add_connection(f"{NS}/depth/image_rect_raw", Raw.__msgtype__,
                                       typestore=TS)
        else:
            colour = bag.add_connection(f"{NS}/color/image_raw/compressed",
                                        Compressed.__msgtype__, typestore=TS)
            depth = bag.add_connection(f"{NS}/depth/image_rect_raw/compressedDepth",
                                       Compressed.__msgtype__, typestore=TS)
        info = bag.add_connection(f"{NS}/color/camera_info", Info.__msgtype__, typestore=TS)
        imu = bag.add_connection(f"{NS}/imu", Imu.__msgtype__, typestore=TS)

        def put(connection, stamp, msg):
            bag.write(connection, stamp, TS.serialize_cdr(msg, msg.__msgtype__))

        for i in range(frames):
            stamp = BASE_NS + i * PERIOD_NS
            with open(os.path.join(src, f"frame-{i:06d}.color.jpg"), "rb") as f:
                jpeg = f.read()
            with open(os.path.join(src, f"frame-{i:06d}.depth.png"), "rb") as f:
                png = f.read()
            put(info, stamp, Info(
                header=header(stamp, "camera_color_optical_frame"), height=480, width=640,
                distortion_model="plumb_bob", d=np.zeros(5), k=np.array(k),
                r=np.eye(3).flatten(), p=np.array(k[:3] + [0] + k[3:6] + [0] + k[6:] + [0]),
                binning_x=0, binning_y=0,
                roi=Roi(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)))
            if raw:
                grey = np.fromfile(os.path.join(raw, f"frame-{i:06d}.grey"), dtype=np.uint8)
                put(colour, stamp, raw_image(stamp, "camera_color_optical_frame", "mono8", grey,
                                             1, 4))
            else:
                put(colour, stamp, Compressed(
                    header=header(stamp, "camera_color_optical_frame"),
                    format="rgb8; jpeg compressed bgr8",
                    data=np.frombuffer(jpeg, dtype=np.uint8)))
            put(imu, stamp + PERIOD_NS // 2, Imu(
                header=header(stamp + PERIOD_NS // 2, "camera_imu_optical_frame"),
                orientation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0),
                orientation_covariance=np.zeros(9), angular_velocity=Vector3(x=0.0, y=0.0, z=0.0),
                angular_velocity_covariance=np.zeros(9),
                linear_acceleration=Vector3(x=0.0, y=0.0, z=9.81),
                linear_acceleration_covariance=np.zeros(9)))
            if corrupt and i == 2:
                bag.write(colour, stamp + 2_000_000, b"\x00\x01\x00\x00not an image")
            # Depth is logged a little after colour, as a driver's second stream would be.
            if raw:
                mm = np.fromfile(os.path.join(raw, f"frame-{i:06d}.depth"), dtype=np.uint8)
                put(depth, stamp + 1_000_000, raw_image(stamp, "camera_depth_optical_frame",
                                                        "16UC1", mm, 2, 0))
                continue
            put(depth, stamp + 1_000_000, Compressed(
                header=header(stamp, "camera_depth_optical_frame"),
                format="16UC1; compressedDepth png",
                data=np.frombuffer(struct.pack("<iff", 0, 0.0, 0.0) + png, dtype=np.uint8)))


if __name__ == "__main__":
    parser = argparse.ArgumentParser()
    parser.add_argument("src")
    parser.add_argument("out")
    parser.add_argument("frames", type=int)
    parser.add_argument("--raw")
    parser.add_argument("--storage", default="mcap", choices=["mcap", "sqlite3"])
    parser.add_argument("--corrupt", action="store_true")
    a = parser.parse_args()
    main(a.src, a.out, a.frames, a.raw, a.storage, a.corrupt)

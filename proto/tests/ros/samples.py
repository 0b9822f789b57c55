"""ROS 2 camera messages serialised by an implementation independent of ours (the `rosbags`
package's CDR serialiser), for `proto/tests/ros_messages.rs`.

    python samples.py OUT_DIR

writes `NAME.cdr` (the message's bytes as a ROS 2 publisher sends them) and `expected.json`
(each message's type and what vsgraphs must read from it, computed here from the values put in).
"""
import json
import math
import os
import struct
import sys
import zlib

import numpy as np
from rosbags.typesys import Stores, get_typestore

TS = get_typestore(Stores.ROS2_HUMBLE)
T = TS.types
Header, Time = T["std_msgs/msg/Header"], T["builtin_interfaces/msg/Time"]
Image, Compressed = T["sensor_msgs/msg/Image"], T["sensor_msgs/msg/CompressedImage"]
Info, Roi = T["sensor_msgs/msg/CameraInfo"], T["sensor_msgs/msg/RegionOfInterest"]

STAMP = (1700000000, 123456789)


def header(frame="camera_color_optical_frame"):
    return Header(stamp=Time(sec=STAMP[0], nanosec=STAMP[1]), frame_id=frame)


def png16(values, width, height):
    """A 16-bit greyscale PNG, written by hand (filter 0 on every row)."""
    raw = b"".join(b"\0" + struct.pack(f">{width}H", *values[y * width:(y + 1) * width])
                   for y in range(height))

    def chunk(kind, data):
        return (struct.pack(">I", len(data)) + kind + data
                + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF))

    ihdr = struct.pack(">IIBBBBB", width, height, 16, 0, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(raw))
            + chunk(b"IEND", b""))


def mm(metres):
    """The depth rule: millimetres rounded, 0 for what cannot be a depth (REP 118 metres)."""
    if not math.isfinite(metres):
        return 0
    v = round(metres * 1000.0)
    return v if 1 <= v <= 65535 else 0


def main(out):
    os.makedirs(out, exist_ok=True)
    expected = {}

    def put(name, msg, **what):
        with open(os.path.join(out, name + ".cdr"), "wb") as f:
            f.write(bytes(TS.serialize_cdr(msg, msg.__msgtype__)))
        expected[name] = dict(type=msg.__msgtype__, stamp_ns=STAMP[0] * 10**9 + STAMP[1],
                              frame_id=msg.header.frame_id, **what)

    # Colour: a 3x2 rgb8 image whose rows are padded to 12 bytes.
    pixels = list(range(1, 19))
    padded = pixels[:9] + [0, 0, 0] + pixels[9:] + [0, 0, 0]
    put("rgb8_padded", Image(header=header(), height=2, width=3, encoding="rgb8", is_bigendian=0,
                             step=12, data=np.array(padded, dtype=np.uint8)),
        encoding="raw", pixel_format="rgb8", data=pixels, width=3, height=2)
    bgra = [10, 20, 30, 255, 40, 50, 60, 255, 70, 80, 90, 0, 100, 110, 120, 7]
    put("bgra8", Image(header=header(), height=2, width=2, encoding="bgra8", is_bigendian=0,
                       step=8, data=np.array(bgra, dtype=np.uint8)),
        encoding="raw", pixel_format="bgr8",
        data=[v for i, v in enumerate(bgra) if i % 4 != 3], width=2, height=2)
    put("mono8", Image(header=header(""), height=1, width=4, encoding="mono8", is_bigendian=0,
                       step=4, data=np.array([0, 1, 254, 255], dtype=np.uint8)),
        encoding="raw", pixel_format="mono8", data=[0, 1, 254, 255], width=4, height=1)

    # Depth images.
    depth = [0, 1, 500, 1234, 65535, 4000]
    put("depth_16uc1", Image(header=header("depth"), height=2, width=3, encoding="16UC1",
                             is_bigendian=0, step=6,
                             data=np.frombuffer(struct.pack("<6H", *depth), dtype=np.uint8)),
        depth_mm=depth, width=3, height=2)
    put("depth_16uc1_big_endian_padded",
        Image(header=header("depth"), height=2, width=3, encoding="16UC1", is_bigendian=1,
              step=8, data=np.frombuffer(struct.pack(">3Hxx3Hxx", *depth), dtype=np.uint8)),
        depth_mm=depth, width=3, height=2)
    metres = np.array([0.5, np.nan, np.inf, -1.0, 1.2346, 70.0], dtype=np.float32)
    put("depth_32fc1", Image(header=header("depth"), height=3, width=2, encoding="32FC1",
                             is_bigendian=0, step=8,
                             data=np.frombuffer(metres.astype("<f4").tobytes(), dtype=np.uint8)),
        depth_mm=[mm(float(m)) for m in metres], width=2, height=3)

    # Compressed colour: the bytes are passed on unchanged, whatever they hold.
    blob = list(b"\xff\xd8 not really a jpeg \xff\xd9")
    put("jpeg", Compressed(header=header(), format="rgb8; jpeg compressed bgr8",
                           data=np.array(blob, dtype=np.uint8)),
        encoding="jpeg", data=blob)
    put("png_old_format", Compressed(header=header(), format="png",
                                     data=np.array(blob, dtype=np.uint8)),
        encoding="png", data=blob)

    # compressedDepth (image_transport's plugin): a 12-byte configuration, then a 16-bit PNG.
    config = struct.pack("<iff", 0, 0.0, 0.0)
    cd = config + png16(depth, 3, 2)
    put("compressed_depth_16uc1", Compressed(header=header("depth"),
                                             format="16UC1; compressedDepth png",
                                             data=np.frombuffer(cd, dtype=np.uint8)),
        depth_mm=depth, width=3, height=2)
    # 32FC1: inverse depth quantised, q = a / z + b, as the plugin does with its defaults
    # (depth_max 10 m, depth_quantization 100).
    a = np.float32(100.0)
    b = np.float32(1.0 - 100.0 / 10.0)
    z = [0.0, 0.45, 1.0, 2.5, 4.2, 9.9]
    q = [0 if v == 0 else int(round(float(a) / v + float(b))) for v in z]
    back = [0 if v == 0 else mm(float(a) / (v - float(b))) for v in q]
    cd = struct.pack("<iff", 0, a, b) + png16(q, 3, 2)
    put("compressed_depth_32fc1", Compressed(header=header("depth"),
                                             format="32FC1; compressedDepth png",
                                             data=np.frombuffer(cd, dtype=np.uint8)),
        depth_mm=back, metres=z, quantisation=float(a), width=3, height=2)

    # Camera info.
    k = [615.3, 0.0, 320.7, 0.0, 615.9, 241.2, 0.0, 0.0, 1.0]
    r = [1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0]
    p = [615.3, 0, 320.7, 0, 0, 615.9, 241.2, 0, 0, 0, 1.0, 0]

    def info(model, d, bx=0, by=0, roi=Roi(x_offset=0, y_offset=0, height=0, width=0,
                                            do_rectify=False)):
        return Info(header=header(), height=480, width=640, distortion_model=model,
                    d=np.array(d, dtype=np.float64), k=np.array(k, dtype=np.float64),
                    r=np.array(r, dtype=np.float64), p=np.array(p, dtype=np.float64),
                    binning_x=bx, binning_y=by, roi=roi)

    d5 = [0.1, -0.25, 0.001, -0.002, 0.05]
    put("info_plumb_bob", info("plumb_bob", d5),
        camera=dict(width=640, height=480, fx=k[0], fy=k[4], cx=k[2], cy=k[5], distortion=d5))
    d8 = d5 + [0.01, 0.02, 0.03]
    put("info_rational", info("rational_polynomial", d8),
        camera=dict(width=640, height=480, fx=k[0], fy=k[4], cx=k[2], cy=k[5], distortion=d8))
    put("info_binned_roi",
        info("plumb_bob", d5, bx=2, by=2,
             roi=Roi(x_offset=100, y_offset=40, height=400, width=440, do_rectify=False)),
        camera=dict(width=220, height=200, fx=k[0] / 2, fy=k[4] / 2, cx=(k[2] - 100) / 2,
                    cy=(k[5] - 40) / 2, distortion=d5))
    put("info_equidistant", info("equidistant", [0.1, 0.01, 0.0, 0.0]), error="distortion model")

    with open(os.path.join(out, "expected.json"), "w") as f:
        json.dump(expected, f, indent=1, allow_nan=False)


if __name__ == "__main__":
    main(sys.argv[1])

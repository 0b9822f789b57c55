"""The Python SDK against a real server, as `tests/tests/python_sdk.rs` runs it: frames come on
stdin (per frame: the stamp as a little-endian u64, then the RGB image, then the depth as
little-endian u16), the robot publishes each and waits until the server has processed it, then
the client reads back the map, its rooms and the robot's trajectory. The last line of stdout
is what was read, as JSON, for the Rust side to compare with its own client.

Environment: VSGRAPHS_ZENOH (endpoint), VSGRAPHS_URL (HTTP), VSGRAPHS_CAMERA (JSON: width,
height, fx, fy, cx, cy, depth_scale), VSGRAPHS_FRAMES (how many come).
"""
import json
import os
import sys
import time

import numpy as np

import vsgraphs

ROBOT = "py-robot"


def wait_for(what, check, timeout_s=60.0):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = check()
        if value:
            return value
        time.sleep(0.01)
    raise AssertionError(f"timed out waiting for {what}")


def read_exactly(stream, n):
    data = stream.read(n)
    assert len(data) == n, f"{len(data)} of {n} bytes on stdin"
    return data


def main():
    camera_json = json.loads(os.environ["VSGRAPHS_CAMERA"])
    width, height = camera_json["width"], camera_json["height"]
    camera = vsgraphs.Camera(camera_json["fx"], camera_json["fy"], camera_json["cx"],
                             camera_json["cy"])
    frames = int(os.environ["VSGRAPHS_FRAMES"])
    client = vsgraphs.Client(os.environ["VSGRAPHS_URL"])

    # Errors a user meets: the API's, and arrays of the wrong kind.
    try:
        client.robot("nobody")
        raise AssertionError("an unknown robot is an error")
    except vsgraphs.ApiError as e:
        assert e.status == 404 and e.code == "robot_not_found", e

    with vsgraphs.Robot(ROBOT, os.environ["VSGRAPHS_ZENOH"], reliable=True) as robot:
        wait_for("the server", lambda: robot.server_online, 20)
        for bad, why in [
            ((np.zeros((height, width), np.float32), np.zeros((height, width), np.uint16)), "uint8"),
            ((np.zeros((height, width), np.uint8), np.zeros((height, width), np.float32)), "uint16"),
            ((np.zeros((height, width), np.uint8), np.zeros((height, 2), np.uint16)), "depth is"),
        ]:
            try:
                robot.publish(*bad, camera, 1)
                raise AssertionError(f"{why}: refused")
            except ValueError as e:
                assert why in str(e), e
        assert robot.frames_published == 0

        stdin = sys.stdin.buffer
        for i in range(frames):
            stamp = int.from_bytes(read_exactly(stdin, 8), "little")
            rgb = np.frombuffer(read_exactly(stdin, width * height * 3), np.uint8)
            depth = np.frombuffer(read_exactly(stdin, width * height * 2), "<u2")
            sequence = robot.publish(rgb.reshape(height, width, 3),
                                     depth.reshape(height, width).astype(np.uint16), camera, stamp,
                                     depth_scale=camera_json["depth_scale"])
            assert sequence == i, (sequence, i)

            def handled():
                f = client.robot(ROBOT)["frames"]
                return f["processed"] + f["dropped"] + f["rejected"] > i

            wait_for(f"frame {i} processed", handled)
        assert robot.frames_published == frames

    status = client.robot(ROBOT)
    assert status["frames"]["processed"] == frames, status["frames"]
    maps = [m for m in client.maps() if ROBOT in m.get("robots", [])]
    assert len(maps) == 1, client.maps()
    map_id = maps[0]["id"]
    # The semantic layer lands a little after the last keyframe.
    rooms = wait_for("a room", lambda: client.rooms(map_id), 30)
    trajectory = client.trajectory(ROBOT)
    print(json.dumps({
        "map": map_id,
        "rooms": sorted(r["name"] for r in rooms),
        "spaces": sorted(s["name"] for s in client.spaces(map_id)),
        "doorways": len(client.doorways(map_id)),
        "trajectory": len(trajectory),
        "frames_tracked": status["tracking"]["frames_tracked"],
    }))


if __name__ == "__main__":
    main()

"""vsgraphs for Python: a robot that streams RGB-D frames (numpy arrays) to a vsgraphs server
over zenoh, and a client of the server's REST API (rooms, doorways, maps, robots,
trajectories).

    import vsgraphs
    robot = vsgraphs.Robot("arm-cam", connect="tcp/127.0.0.1:7447")
    robot.publish(rgb, depth_mm, vsgraphs.Camera(fx=525, fy=525, cx=319.5, cy=239.5), stamp_ns)
    client = vsgraphs.Client("http://127.0.0.1:8080")
    print(client.rooms(client.maps()[0]["id"]))
"""

from .client import ApiError, Client
from .robot import Camera, Robot

__all__ = ["ApiError", "Camera", "Client", "Robot"]

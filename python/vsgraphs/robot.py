"""A robot: frames as numpy arrays in, encoded and published over zenoh by the Rust SDK."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence, Union

import numpy as np

from . import _native


@dataclass(frozen=True)
class Camera:
    """A pinhole camera in pixels, with OpenCV's distortion coefficients (k1 k2 p1 p2 [k3 ...];
    empty: none)."""

    fx: float
    fy: float
    cx: float
    cy: float
    distortion: Sequence[float] = field(default_factory=tuple)


class Robot:
    """A robot publishing to a vsgraphs server.

    ``connect`` is the server's zenoh endpoint (or a list of them), e.g. ``"tcp/10.0.0.5:7447"``.
    A live robot's frames are dropped rather than queued when the network is slow; with
    ``reliable=True`` (recorded data) publishing waits instead.
    """

    def __init__(
        self,
        robot_id: str,
        connect: Union[str, Sequence[str]] = "tcp/127.0.0.1:7447",
        *,
        reliable: bool = False,
    ) -> None:
        endpoints = [connect] if isinstance(connect, str) else list(connect)
        self.robot_id = robot_id
        self._native = _native.Robot(robot_id, endpoints, reliable)

    def publish(
        self,
        colour: np.ndarray,
        depth: np.ndarray,
        camera: Camera,
        stamp_ns: int,
        *,
        depth_scale: float = 1000.0,
        pixel_format: str = "rgb8",
        jpeg_quality: int = 90,
    ) -> int:
        """Publishes one frame and returns its sequence number.

        ``colour``: ``uint8`` of shape (height, width, 3) in ``pixel_format`` ("rgb8" or
        "bgr8"), or (height, width) for grey. ``depth``: ``uint16`` of shape (height, width) in
        units of 1/``depth_scale`` m (1000: millimetres), 0 where there is no depth, aligned to
        the colour image. ``stamp_ns``: capture time, ns since the Unix epoch, increasing.
        """
        colour = np.asarray(colour)
        depth = np.asarray(depth)
        if colour.dtype != np.uint8:
            raise ValueError(f"colour must be uint8, not {colour.dtype}")
        if colour.ndim == 2:
            pixel_format = "mono8"
        elif colour.ndim != 3 or colour.shape[2] != 3:
            raise ValueError(f"colour must be (height, width, 3) or (height, width), not {colour.shape}")
        if depth.dtype != np.uint16:
            raise ValueError(f"depth must be uint16, not {depth.dtype}")
        height, width = colour.shape[:2]
        if depth.shape != (height, width):
            raise ValueError(f"depth is {depth.shape}; the colour image is {(height, width)}")
        return self._native.publish(
            int(stamp_ns),
            width,
            height,
            np.ascontiguousarray(colour).tobytes(),
            pixel_format,
            np.ascontiguousarray(depth, dtype="<u2").tobytes(),
            float(depth_scale),
            float(camera.fx),
            float(camera.fy),
            float(camera.cx),
            float(camera.cy),
            [float(d) for d in camera.distortion],
            int(jpeg_quality),
        )

    @property
    def server_online(self) -> bool:
        """Whether the server is there (its liveliness is seen)."""
        return self._native.server_online()

    @property
    def frames_published(self) -> int:
        return self._native.frames_published()

    def close(self) -> None:
        """Leaves: the server sees the robot go offline."""
        self._native.close()

    def __enter__(self) -> "Robot":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

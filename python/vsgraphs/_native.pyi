from typing import List

class Robot:
    def __init__(self, robot_id: str, connect: List[str], reliable: bool) -> None: ...
    def publish(
        self,
        stamp_ns: int,
        width: int,
        height: int,
        pixels: bytes,
        pixel_format: str,
        depth: bytes,
        depth_scale: float,
        fx: float,
        fy: float,
        cx: float,
        cy: float,
        distortion: List[float],
        jpeg_quality: int,
    ) -> int: ...
    def server_online(self) -> bool: ...
    def frames_published(self) -> int: ...
    def close(self) -> None: ...

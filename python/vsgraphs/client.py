"""The server's REST API (``/api/v1``) from Python, with the standard library only. Answers are
the API's JSON as dicts and lists (README, "REST API")."""

from __future__ import annotations

import json
import urllib.error
import urllib.parse
import urllib.request
from typing import Any, Dict, List, Optional

Json = Dict[str, Any]


class ApiError(Exception):
    """An error answer: its HTTP status, the API's code (``robot_not_found``, ...) and message."""

    def __init__(self, status: int, code: str, message: str) -> None:
        super().__init__(f"{status} {code}: {message}")
        self.status, self.code, self.message = status, code, message


class Client:
    """A client of one server, e.g. ``Client("http://127.0.0.1:8080")``; ``token`` is sent as a
    bearer token (the server's read or admin token) when given."""

    def __init__(self, url: str, token: Optional[str] = None, timeout_s: float = 10.0) -> None:
        self.url = url.rstrip("/")
        self.token = token
        self.timeout_s = timeout_s

    def _get(self, path: str, **query: Any) -> Any:
        url = f"{self.url}/api/v1{path}"
        if query:
            url += "?" + urllib.parse.urlencode(query)
        request = urllib.request.Request(url, headers={"Accept": "application/json"})
        if self.token:
            request.add_header("Authorization", f"Bearer {self.token}")
        try:
            with urllib.request.urlopen(request, timeout=self.timeout_s) as answer:
                return json.load(answer)
        except urllib.error.HTTPError as e:
            body = e.read()
            try:
                error = json.loads(body)
                raise ApiError(e.code, error.get("error", ""), error.get("message", "")) from None
            except (ValueError, AttributeError):
                raise ApiError(e.code, "", body.decode(errors="replace")) from None

    @staticmethod
    def _quote(segment: Any) -> str:
        return urllib.parse.quote(str(segment), safe="")

    def health(self) -> Json:
        return self._get("/health")

    def robots(self) -> List[Json]:
        """Every robot the server knows: presence, frame counters, tracking, its map."""
        return self._get("/robots")

    def robot(self, robot_id: str) -> Json:
        return self._get(f"/robots/{self._quote(robot_id)}")

    def trajectory(self, robot_id: str) -> List[Json]:
        """The robot's poses (``timestamp_ns``, ``map``, ``world_from_camera``), oldest first."""
        return self._get(f"/robots/{self._quote(robot_id)}/trajectory")

    def maps(self) -> List[Json]:
        """The server's maps: contributing robots, counts, merges."""
        return self._get("/maps")

    def spaces(self, map_id: int) -> List[Json]:
        """A map's rooms and corridors (``kind``), with centres, walls, doorways, neighbours."""
        return self._get(f"/maps/{int(map_id)}/spaces")

    def rooms(self, map_id: int) -> List[Json]:
        return [s for s in self.spaces(map_id) if s.get("kind") == "room"]

    def corridors(self, map_id: int) -> List[Json]:
        return [s for s in self.spaces(map_id) if s.get("kind") == "corridor"]

    def doorways(self, map_id: int) -> List[Json]:
        """A map's doorways: pose, width, the two spaces each joins."""
        return self._get(f"/maps/{int(map_id)}/doorways")

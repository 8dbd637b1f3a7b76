"""The planner's HTTP client for the service's REST API (standard library only).

    api = PlannerClient("http://127.0.0.1:8080", token=os.environ.get("MNEMOSLAM_API_TOKEN"))
    door = api.nearest_object("door", robot="r1")          # {"object": {...}, "distance", "node_id"}
    path = api.object_path(door["object"]["id"], robot="r1")  # node ids and positions along the graph

Errors are `ApiError` (status, detail); `last_semantics` is the X-Semantics header ("on" /
"off") of the last object answer: whether the service is fusing objects now."""
from __future__ import annotations

import json
import urllib.error
import urllib.parse
import urllib.request


class ApiError(Exception):
    def __init__(self, status: int, detail: str):
        super().__init__(f"HTTP {status}: {detail}")
        self.status, self.detail = status, detail


class PlannerClient:
    def __init__(self, base_url: str = "http://127.0.0.1:8080", timeout: float = 10.0, token: str | None = None):
        self.base_url = base_url.rstrip("/")
        self.timeout = timeout
        self.token = token or None  # sent as 'Authorization: Bearer <token>' (needed to change the map)
        self.last_semantics: str | None = None

    def request(self, method: str, path: str, body=None, **params) -> object:
        query = urllib.parse.urlencode({k: v for k, v in params.items() if v is not None})
        url = f"{self.base_url}{path}" + (f"?{query}" if query else "")
        headers = {"Accept": "application/json"}
        if self.token:
            headers["Authorization"] = f"Bearer {self.token}"
        data = None
        if body is not None:
            data = json.dumps(body).encode()
            headers["Content-Type"] = "application/json"
        req = urllib.request.Request(url, data=data, method=method, headers=headers)
        try:
            with urllib.request.urlopen(req, timeout=self.timeout) as r:
                body = r.read()
                ctype = r.headers.get("content-type", "")
                self.last_semantics = r.headers.get("x-semantics", self.last_semantics)
        except urllib.error.HTTPError as e:
            self.last_semantics = e.headers.get("x-semantics", self.last_semantics)
            try:
                detail = json.loads(e.read()).get("detail", e.reason)
            except (ValueError, AttributeError):
                detail = e.reason
            raise ApiError(e.code, str(detail)) from None
        return json.loads(body) if "json" in ctype else body.decode()

    def get(self, path: str, **params) -> object:
        return self.request("GET", path, **params)

    def health(self) -> dict:
        return self.get("/health")

    def robots(self) -> list[dict]:
        return self.get("/robots")

    def robot(self, robot: str) -> dict:
        return self.get(f"/robots/{urllib.parse.quote(robot)}")

    def sessions(self) -> list[dict]:
        return self.get("/sessions")

    def nodes(self, session_id: int, bbox=None, limit: int = 100, offset: int = 0) -> dict:
        box = ",".join(f"{v:g}" for v in (*bbox[0], *bbox[1])) if bbox else None
        return self.get(f"/sessions/{session_id}/nodes", bbox=box, limit=limit, offset=offset)

    def trajectory(self, session_id: int, format: str = "json"):
        return self.get(f"/sessions/{session_id}/trajectory", format=format)

    def graph(self, session_id: int) -> dict:
        return self.get(f"/sessions/{session_id}/graph")

    def stats(self) -> dict:
        return self.get("/stats")

    # -- semantic map ------------------------------------------------------------------------
    def semantics(self) -> dict:
        """{"enabled", "source", "model", "reason" (why off), "classes"}."""
        return self.get("/semantics")

    def nearest_object(self, label: str, point=None, robot: str | None = None) -> dict:
        """The `label` object nearest to `point` (x, y, z) or to `robot`'s current pose:
        {"object": {"id", "label", "confidence", "position", "extent", "observations", ...},
        "distance", "node_id"}; ApiError 404 (with the reason) when there is none."""
        x, y, z = point if point is not None else (None, None, None)
        return self.get("/objects/nearest", label=label, x=x, y=y, z=z, robot=robot)

    def objects(self, label: str | None = None, point=None, radius: float | None = None,
                limit: int = 100, offset: int = 0) -> dict:
        """{"total", "limit", "offset", "objects": [...]}: by distance to `point` when given."""
        x, y, z = point if point is not None else (None, None, None)
        return self.get("/objects", label=label, x=x, y=y, z=z, radius=radius, limit=limit, offset=offset)

    def object(self, object_id: int) -> dict:
        return self.get(f"/objects/{int(object_id)}")

    def labels(self) -> dict:
        """{"total": objects, "labels": [{"label", "count"}, ...]} (most frequent first)."""
        return self.get("/labels")

    def object_path(self, object_id: int, robot: str) -> dict:
        """A path along the pose graph from `robot`'s node to the node nearest the object:
        {"object", "robot", "start_node", "goal_node", "nodes": [{"id", "position"}], "length",
        "goal_distance"}."""
        return self.get(f"/objects/{int(object_id)}/path", robot=robot)

    # -- the maps: occupancy grid, cloud, paths on the grid (docs/grid.md) ----------------------
    def maps(self) -> list[dict]:
        """[{"map", "id", "keyframes", "sessions", "robots", "objects", "last_change"}] of the database."""
        return self.get("/maps")

    def grid(self, map_id: int, resolution: float | None = None) -> dict:
        """The map's occupancy grid: {"resolution", "origin", "width", "height", "data" (row-major
        from the origin cell: -1 unknown, 0 free, 100 occupied), "map_to_grid", map_server's
        YAML fields, "keyframes"}."""
        return self.get(f"/maps/{int(map_id)}/grid", resolution=resolution, format="json")

    def cloud(self, map_id: int, voxel: float = 0.05) -> dict:
        """The map's coloured point cloud as JSON {"count", "voxel", "points", "colors"} (for
        small maps; GET /maps/{map}/cloud?format=ply for the binary PLY)."""
        return self.get(f"/maps/{int(map_id)}/cloud", voxel=voxel, format="json")

    def path(self, robot: str, to: int | None = None, point=None) -> dict:
        """A path on the occupancy grid from `robot` to an object (`to`) or a point (x, y, z):
        {"robot", "map", "start", "goal", "points", "grid_points", "length", "goal_distance",
        "object"}."""
        x, y, z = point if point is not None else (None, None, None)
        return self.get("/path", robot=robot, to=to, x=x, y=y, z=z)

    # -- changes (need the token) --------------------------------------------------------------
    def label_node(self, node_id: int, label: str | None) -> dict:
        """Name a keyframe (None clears its name); the node."""
        return self.request("POST", f"/nodes/{int(node_id)}/label", body={"label": label})

    def delete_object(self, object_id: int) -> dict:
        return self.request("DELETE", f"/objects/{int(object_id)}")

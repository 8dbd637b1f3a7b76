"""The REST API (FastAPI): health, robots, sessions, a map's nodes, trajectory and graph,
statistics. Reads go to the service's live state and to the SQLite long-term memory; the
API never writes. OpenAPI docs at /docs."""
from __future__ import annotations

import math
from typing import Annotated

from fastapi import FastAPI, HTTPException, Path, Query
from fastapi.responses import PlainTextResponse

from client.protocol import ROBOT_PATTERN
from client.trajectory import format_tum
from storage import MapRepository

from .server import SlamService

LINK_TYPES = {0: "odometry", 1: "loop", 2: "proximity", 3: "local_time", 4: "user", 5: "virtual"}

# The largest SQLite INTEGER (signed 64-bit): a bigger id or offset cannot be bound to a query.
# Bounding the parameters makes such input a 422 (and documents the range in the OpenAPI).
SQLITE_INT_MAX = 2**63 - 1
DbId = Annotated[int, Path(ge=0, le=SQLITE_INT_MAX, description="a database id (0 .. 2^63-1)")]
RobotId = Annotated[str, Path(pattern=f"^{ROBOT_PATTERN.pattern}$", description="a robot id as on the wire")]


def _pose_list(pose) -> list[float]:
    return [float(v) for v in pose.reshape(-1)]


def _node_json(n) -> dict:
    return {"id": n.id, "session_id": n.session_id, "robot": n.robot, "stamp": n.stamp,
            "position": _pose_list(n.pose[:3, 3]), "pose": _pose_list(n.pose), "weight": n.weight, "label": n.label}


def _parse_bbox(text: str | None):
    if text is None:
        return None
    parts = text.split(",")
    try:
        v = [float(p) for p in parts]
    except ValueError:
        raise HTTPException(400, f"bbox must be 6 comma-separated numbers xmin,ymin,zmin,xmax,ymax,zmax; got {text!r}")
    if len(v) != 6 or not all(math.isfinite(x) for x in v):
        raise HTTPException(400, f"bbox must be 6 finite numbers xmin,ymin,zmin,xmax,ymax,zmax; got {text!r}")
    lo, hi = v[:3], v[3:]
    if any(a > b for a, b in zip(lo, hi)):
        raise HTTPException(400, "bbox minimum exceeds its maximum")
    return tuple(lo), tuple(hi)


def create_app(service: SlamService) -> FastAPI:
    app = FastAPI(title="mnemoslam", description="Long-term visual SLAM service: map state and queries.",
                  version="0.1.0")

    def store() -> MapRepository:
        if service.store is None:
            raise HTTPException(503, "the service is not running")
        return service.store

    def session_or_404(session_id: int):
        s = store().session(session_id)
        if s is None:
            raise HTTPException(404, f"no session {session_id}")
        return s

    @app.get("/health")
    def health():
        return {"status": "ok" if service.store is not None else "stopped", **{
            k: v for k, v in service.status().items() if k in ("uptime_s", "robots", "rejected_total")}}

    @app.get("/robots")
    def robots():
        return service.robots()

    @app.get("/robots/{robot}")
    def robot(robot: RobotId):
        for r in service.robots():
            if r["robot"] == robot:
                return r
        raise HTTPException(404, f"unknown robot {robot!r}")

    @app.get("/sessions")
    def sessions():
        return [s.to_dict() for s in store().sessions()]

    @app.get("/sessions/{session_id}/nodes")
    def nodes(session_id: DbId, bbox: str | None = Query(None, description="xmin,ymin,zmin,xmax,ymax,zmax (metres)"),
              limit: int = Query(100, ge=1, le=10000), offset: int = Query(0, ge=0, le=SQLITE_INT_MAX)):
        session_or_404(session_id)
        box = _parse_bbox(bbox)
        st = store()
        return {"total": st.count_nodes(session_id=session_id, bbox=box), "limit": limit, "offset": offset,
                "nodes": [_node_json(n) for n in st.nodes(session_id=session_id, bbox=box, limit=limit, offset=offset)]}

    @app.get("/sessions/{session_id}/trajectory")
    def trajectory(session_id: DbId, format: str = Query("json", pattern="^(json|tum)$")):
        session_or_404(session_id)
        traj = store().trajectory(session_id)
        if format == "tum":
            return PlainTextResponse(format_tum(traj))
        return {"session_id": session_id, "poses": [
            {"stamp": float(t), "pose": _pose_list(p)} for t, p in zip(traj.stamps, traj.poses)]}

    @app.get("/sessions/{session_id}/graph")
    def graph(session_id: DbId):
        session_or_404(session_id)
        st = store()
        nodes = st.nodes(session_id=session_id, limit=10**9, offset=0)
        links = st.links(session_id=session_id)
        return {"nodes": [_node_json(n) for n in nodes],
                "links": [{"from": l.from_id, "to": l.to_id, "type": LINK_TYPES.get(l.type, str(l.type)),
                           "transform": _pose_list(l.transform)} for l in links]}

    @app.get("/nodes/{node_id}/statistics")
    def node_statistics(node_id: DbId):
        """Why a loop was or wasn't closed at this keyframe: hypothesis, posterior, likelihood
        top-k, decision, verification inliers, time per step."""
        data = store().statistics(node_id)
        if data is None:
            raise HTTPException(404, f"no statistics for node {node_id}")
        return data

    @app.get("/stats")
    def stats():
        st = service.status()
        st.pop("config", None)
        return {"service": st, "robots": service.robots(), "database": store().stats()}

    @app.get("/config")
    def config():
        return service.status()["config"]

    return app

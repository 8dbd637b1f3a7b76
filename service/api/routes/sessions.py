"""The sessions and their maps: GET /sessions, /sessions/{id} (with its configuration), a
session's nodes (paged, in a box), trajectory (JSON or TUM) and graph, a node's loop-closure
statistics; POST /nodes/{id}/label (token) names a keyframe."""
from __future__ import annotations

import math
from typing import Annotated, Any

from fastapi import Body, HTTPException, Query, Request
from fastapi.responses import PlainTextResponse

from mnemoslam.client.kernel.protocol import ROBOT_PATTERN
from mnemoslam.client.kernel.trajectory import format_tum
from mnemoslam.storage import StoreError, UnknownIdError, link_name

from ..dependencies import SessionDep, StoreDep, read_router, write_router
from ..models import (
    DbId,
    GraphOut,
    LabelIn,
    Limit,
    NodeOut,
    NodePage,
    Offset,
    SessionOut,
    SessionSummary,
    TrajectoryOut,
    error_responses,
)

read_routes = read_router()
write_routes = write_router()


# -- conversions ----------------------------------------------------------------------------
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
        raise HTTPException(
            400, f"bbox must be 6 comma-separated numbers xmin,ymin,zmin,xmax,ymax,zmax; got {text!r}") from None
    if len(v) != 6 or not all(math.isfinite(x) for x in v):
        raise HTTPException(400, f"bbox must be 6 finite numbers xmin,ymin,zmin,xmax,ymax,zmax; got {text!r}")
    lo, hi = v[:3], v[3:]
    if any(a > b for a, b in zip(lo, hi)):
        raise HTTPException(400, "bbox minimum exceeds its maximum")
    return tuple(lo), tuple(hi)


# -- reads ----------------------------------------------------------------------------------
def _with_map(sessions, store, index) -> list[dict]:
    """Each session's dict with the map it is in and when it joined it (`SessionSummary`)."""
    joins = {s.id: index.join(s.id) for s in sessions}
    first = {n.id: n.pose for n in store.get_nodes([j.first_node for j in joins.values()
                                                     if j is not None and j.first_node is not None])}
    out = []
    for s in sessions:
        d, j = s.to_dict(), joins[s.id]
        if j is not None and j.first_node is not None:
            d["map"] = j.map
            if j.first_node in first:
                d["T_map_session"] = [float(v) for v in first[j.first_node].reshape(-1)]
            if j.joined:
                d.update(joined=True, joined_keyframe=j.node, joined_stamp=j.stamp, joined_peer=j.peer,
                         joined_link=link_name(j.link))
        out.append(d)
    return out


@read_routes.get("/sessions", response_model=list[SessionSummary])
def sessions(store: StoreDep, request: Request, robot: Annotated[str | None, Query(
        pattern=f"^{ROBOT_PATTERN.pattern}$", description="only this robot's sessions")] = None):
    """The sessions, oldest first (only `robot`'s with ?robot=), each with the map it is in,
    when it joined it and `T_map_session`; each one's configuration is in GET /sessions/{id}."""
    return _with_map(store.sessions(robot=robot), store, request.app.state.maps.get(store))


@read_routes.get("/sessions/{session_id}", response_model=SessionOut, responses=error_responses(404))
def session(session: SessionDep, store: StoreDep, request: Request):
    """One session, with its map (as GET /sessions) and the configuration it ran with."""
    return _with_map([session], store, request.app.state.maps.get(store))[0]


@read_routes.get("/sessions/{session_id}/nodes", response_model=NodePage, responses=error_responses(400, 404))
def nodes(session: SessionDep, store: StoreDep,
          bbox: str | None = Query(None, description="xmin,ymin,zmin,xmax,ymax,zmax (metres)"),
          limit: Limit = 100, offset: Offset = 0):
    box = _parse_bbox(bbox)
    return {"total": store.count_nodes(session_id=session.id, bbox=box), "limit": limit, "offset": offset,
            "nodes": [_node_json(n) for n in store.nodes(session_id=session.id, bbox=box, limit=limit, offset=offset)]}


@read_routes.get("/sessions/{session_id}/trajectory", response_model=TrajectoryOut, responses={
    **error_responses(404), 200: {"content": {"text/plain": {"schema": {"type": "string"}}},
                          "description": "JSON, or TUM text with format=tum"}})
def trajectory(session: SessionDep, store: StoreDep, format: str = Query("json", pattern="^(json|tum)$")):
    traj = store.trajectory(session.id)
    if format == "tum":
        return PlainTextResponse(format_tum(traj))
    return {"session_id": session.id, "poses": [
        {"stamp": float(t), "pose": _pose_list(p)} for t, p in zip(traj.stamps, traj.poses)]}


@read_routes.get("/sessions/{session_id}/graph", response_model=GraphOut, responses=error_responses(404))
def graph(session: SessionDep, store: StoreDep):
    nodes = store.nodes(session_id=session.id, limit=10**9, offset=0)
    links = store.links(session_id=session.id)
    return {"nodes": [_node_json(n) for n in nodes],
            "links": [{"from": lk.from_id, "to": lk.to_id, "type": link_name(lk.type),
                       "transform": _pose_list(lk.transform)} for lk in links]}


@read_routes.get("/nodes/{node_id}/statistics", response_model=dict[str, Any], responses=error_responses(404))
def node_statistics(node_id: DbId, store: StoreDep):
    """Why a loop was or wasn't closed at this keyframe: hypothesis, posterior, likelihood
    top-k, decision, verification inliers, time per step."""
    data = store.statistics(node_id)
    if data is None:
        raise HTTPException(404, f"no statistics for node {node_id}")
    return data


# -- changes (token) ------------------------------------------------------------------------------
@write_routes.post("/nodes/{node_id}/label", response_model=NodeOut, responses=error_responses(404, 409))
def label_node(node_id: DbId, store: StoreDep, body: Annotated[LabelIn, Body()]):
    """Name a keyframe (unique in the map, as RTAB-Map's labels); a null label clears it."""
    try:
        store.set_label(node_id, body.label)
    except UnknownIdError:
        raise HTTPException(404, f"no node {node_id}") from None
    except ValueError as e:
        raise HTTPException(400, str(e)) from None
    except StoreError as e:  # the label is on another node
        raise HTTPException(409, str(e)) from None
    return _node_json(store.get_node(node_id))

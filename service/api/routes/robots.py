"""The robots: GET /robots (each connected robot's status) and GET /robots/{robot} (one, with
the map it is localized in)."""
from __future__ import annotations

from fastapi import HTTPException, Request

from ..dependencies import ServiceDep, read_router
from ..models import RobotId, RobotStatus, error_responses

read_routes = read_router()


@read_routes.get("/robots", response_model=list[RobotStatus])
def robots(service: ServiceDep):
    return service.robots()


@read_routes.get("/robots/{robot}", response_model=RobotStatus, responses=error_responses(404))
def robot(robot: RobotId, service: ServiceDep, request: Request):
    """A robot's status, with `map`: the map id of the oldest session that links join its
    latest keyframe to (its own session's until it relocalizes in an older map)."""
    for r in service.robots():
        if r["robot"] == robot:
            maps = None
            if r.get("node_id") is not None and service.store is not None:
                maps = request.app.state.objects.get(service.store).maps([r["node_id"]])
            return {**r, "map": maps[0] if maps else None}
    raise HTTPException(404, f"unknown robot {robot!r}")

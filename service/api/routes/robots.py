"""The robots: GET /robots (each connected robot's status) and GET /robots/{robot} (one), each
with `map`, the map it is localized in (the same answer in both)."""
from __future__ import annotations

from fastapi import HTTPException, Request

from ..dependencies import ServiceDep, read_router, robots_with_maps
from ..models import RobotId, RobotStatus, error_responses

read_routes = read_router()


@read_routes.get("/robots", response_model=list[RobotStatus])
def robots(service: ServiceDep, request: Request):
    """Every connected robot's status, with `map` (see GET /robots/{robot})."""
    return robots_with_maps(service, request.app.state.maps)


@read_routes.get("/robots/{robot}", response_model=RobotStatus, responses=error_responses(404))
def robot(robot: RobotId, service: ServiceDep, request: Request):
    """A robot's status, with `map`: the map id of the oldest session that links join its
    latest keyframe to (its own session's until it relocalizes in an older map)."""
    for r in robots_with_maps(service, request.app.state.maps):
        if r["robot"] == robot:
            return r
    raise HTTPException(404, f"unknown robot {robot!r}")

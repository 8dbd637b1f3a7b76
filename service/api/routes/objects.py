"""The semantic map's objects: GET /objects/nearest (of a label, to a point or a robot),
/objects (by label, around a point), /objects/{id}, /objects/{id}/path (along the pose graph
from a robot), /labels (with counts); DELETE /objects/{id} (token). Every answer carries
`X-Semantics: on|off`; the queries are the query layer's (`service.semantics.queries`)."""
from __future__ import annotations

from typing import Annotated

from fastapi import HTTPException, Query
from fastapi.concurrency import run_in_threadpool

from mnemoslam.client.kernel.protocol import ROBOT_PATTERN

from ...semantics.queries import NotFound, ObjectView, QueryError, robot_location
from ..dependencies import ObjectContext, ObjectsDep, read_router, write_router
from ..models import (
    Coordinate,
    DbId,
    DeletedOut,
    LabelQuery,
    LabelsOut,
    Limit,
    NearestOut,
    ObjectOut,
    ObjectPage,
    Offset,
    PathOut,
    Radius,
    RobotQuery,
    error_responses,
)

read_routes = read_router()
write_routes = write_router()


def _object_json(o: ObjectView) -> dict:
    return o.to_dict()


# -- reads ----------------------------------------------------------------------------------
@read_routes.get("/objects/nearest", response_model=NearestOut, responses=error_responses(400, 404))
async def nearest_object(label: LabelQuery, objects: ObjectsDep, x: Coordinate = None, y: Coordinate = None,
                         z: Coordinate = None, robot: RobotQuery = None):
    """The object labelled `label` nearest to a point (x, y, z) or to a robot's current pose
    (`robot`; exactly one of the two; then only among objects that links join to the robot's
    keyframe, i.e. in its frame). 404 says why there is none (no such label, no objects,
    unknown robot, robot without a pose, robot not yet localized in the map)."""
    point = objects.point(x, y, z)
    with objects.errors():  # in the event loop: microseconds on the index
        if (robot is None) == (point is None):
            raise QueryError("give either x, y, z or robot (one of them)")
        if point is not None:
            n = objects.index.nearest(label, point)
        else:  # a robot's fallback pose, and links newer than the index, read the map
            n = await run_in_threadpool(_nearest_to_robot, objects, label, robot)
    return {"object": _object_json(n.object), "distance": n.distance, "node_id": n.node_id}


def _nearest_to_robot(objects: ObjectContext, label: str, robot: str):
    at = robot_location(objects.service.robots(), robot, objects.store)
    return objects.index.nearest(label, at.position, joined_to=at.node_id)


@read_routes.get("/objects", response_model=ObjectPage, responses=error_responses(400))
def list_objects(objects: ObjectsDep, label: Annotated[str | None, Query(min_length=1, max_length=128)] = None,
                 x: Coordinate = None, y: Coordinate = None, z: Coordinate = None,
                 radius: Radius = None,
                 limit: Limit = 100, offset: Offset = 0):
    """Objects, optionally of one label and within `radius` of x, y, z; ordered by distance
    to the point when one is given, else by id."""
    point = objects.point(x, y, z)
    with objects.errors():
        page = objects.index.find(label, point, radius, limit=limit, offset=offset)
    return {"total": page.total, "limit": limit, "offset": offset, "objects": [_object_json(o) for o in page.objects]}


@read_routes.get("/objects/{object_id}", response_model=ObjectOut, responses=error_responses(404))
async def get_object(object_id: DbId, objects: ObjectsDep):
    with objects.errors():
        return _object_json(objects.index.get(object_id))


@read_routes.get("/objects/{object_id}/path", response_model=PathOut, responses=error_responses(404))
def object_path(object_id: DbId, robot: Annotated[str, Query(pattern=f"^{ROBOT_PATTERN.pattern}$")],
                objects: ObjectsDep):
    """A path along the pose graph from the robot's node (its latest keyframe) to the map
    node nearest the object ("navigate to the chair")."""
    with objects.errors():
        p = objects.index.path(object_id, robot_location(objects.service.robots(), robot, objects.store))
    return {"object": _object_json(p.object), "robot": robot, "start_node": p.start_node, "goal_node": p.goal_node,
            "nodes": [{"id": i, "position": list(x)} for i, x in zip(p.nodes, p.positions)],
            "length": p.length, "goal_distance": p.goal_distance}


@read_routes.get("/labels", response_model=LabelsOut)
async def labels(objects: ObjectsDep):
    """The object classes in the map with their object counts."""
    with objects.errors():
        counts = objects.index.labels()
    return {"total": sum(n for _, n in counts), "labels": [{"label": k, "count": n} for k, n in counts]}


# -- changes (token) ------------------------------------------------------------------------------
@write_routes.delete("/objects/{object_id}", response_model=DeletedOut, responses=error_responses(404, 409))
def delete_object(object_id: DbId, objects: ObjectsDep):
    """Drop a wrong or stale object from the map (a chair moved away). While the service fuses
    objects (semantics on) the deletion goes through its semantic worker, which holds the
    objects it tracks; a thing still in view then comes back as a new object. Refused (409)
    by a service that fuses objects but cannot delete through its worker."""
    live = objects.semantics.get("enabled")
    delete = getattr(objects.service, "delete_object", None)
    if live and delete is None:
        raise HTTPException(409, "objects are being fused live (semantics on) and this service cannot delete through "
                                 "its semantic worker, which would write the object again; delete it with semantics "
                                 "off (semantics.enabled: false)", headers=objects.errors().headers)
    with objects.errors():
        if not live:
            return {"deleted": objects.index.delete(object_id)}
        objects.index.get(object_id)  # NotFound when it is not in the map
        n = delete(int(object_id))
        objects.index.refresh()
        if not n:
            raise NotFound(f"no object {object_id}")
        return {"deleted": int(n)}

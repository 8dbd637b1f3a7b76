"""The maps a planner can use (issue 25): GET /maps (the maps of the database),
/maps/{map}/grid (the occupancy grid: JSON, PNG, PGM or map_server YAML), /maps/{map}/cloud
(the coloured point cloud, PLY) and /path (a path on the grid from a robot to an object or a
point). The grids are `service.grid.maps.MapGrids`', kept up to date by a background thread
(new and moved keyframes only) once asked for; a request waits at most grid.max_wait for it."""
from __future__ import annotations

import threading
from typing import Annotated, Literal

import numpy as np
from fastapi import HTTPException, Query, Request, Response

from mnemoslam.client.kernel.protocol import ROBOT_PATTERN

from ...grid import cloud as grid_cloud
from ...grid import files
from ...grid.maps import MapGrids, NoMap
from ...grid.path import NoPath, plan
from ...semantics.queries import NotFound, robot_location
from ..dependencies import ServiceDep, StoreDep, read_router
from ..models import SQLITE_INT_MAX, CloudOut, Coordinate, DbId, GridOut, GridPathOut, MapOut, error_responses

read_routes = read_router()

Resolution = Annotated[float | None, Query(ge=0.01, le=10.0, allow_inf_nan=False,
                                           description="m per cell; default grid.cell_size")]
Voxel = Annotated[float, Query(ge=0.005, le=1.0, allow_inf_nan=False, description="voxel size (m)")]


def _grids(request: Request, store) -> MapGrids:
    return request.app.state.grids.get(store)


@read_routes.get("/maps", response_model=list[MapOut])
def maps(request: Request, store: StoreDep):
    """The maps of the database: connected parts of the pose graph, each named by the map id of
    its oldest session (storage.connectivity.MapIndex), with the sessions whose keyframes are in
    it (a session that relocalized in an older map is that map's), their robots, keyframes,
    objects and last change."""
    index = request.app.state.maps.get(store)
    maps = index.maps()
    anchors = store.object_arrays()["node_id"]
    objects = {m: int(np.isin(anchors, e["node_ids"]).sum()) for m, e in maps.items()}
    return [{"map": m, "id": m, "keyframes": e["keyframes"], "sessions": e["sessions"], "robots": e["robots"],
             "objects": objects[m], "last_change": e["last_change"]} for m, e in sorted(maps.items())]


@read_routes.get("/maps/{map_id}/grid", response_model=GridOut, responses={
    **error_responses(404), 200: {"content": {"image/png": {}, "image/x-portable-graymap": {}, "text/yaml": {}},
                                  "description": "the grid (json), or its image / map_server YAML"}})
def map_grid(map_id: DbId, request: Request, store: StoreDep, resolution: Resolution = None,
             format: Literal["json", "png", "pgm", "yaml"] = "json",
             wait: Annotated[float | None, Query(ge=0.0, le=600.0, allow_inf_nan=False, description=(
                 "s to wait for the grid to follow the latest poses (default grid.max_wait); then the last "
                 "grid assembled, with X-Map-Current: false"))] = None):
    """The map's 2-D occupancy grid, assembled from its keyframes' local grids at their
    optimised poses (it follows loop closure). `json`: nav_msgs/OccupancyGrid's data with
    map_server's YAML fields and `map_to_grid` (grid ← map frame, row-major 4×4); `png` /
    `pgm`: map_server's image (0 occupied, 254 free, 205 unknown; top row = largest y) with
    the fields in headers (X-Map-Resolution, X-Map-Origin, X-Map-To-Grid); `yaml`: map_server's
    YAML for an image saved as grid.pgm. A thread keeps the grid up to date; the request waits
    at most `wait` s for it (after a loop closure of a large map the re-placing takes seconds),
    else gets the last grid assembled (X-Map-Current: false)."""
    try:
        grid, current = _grids(request, store).latest(map_id, wait)
    except NoMap as e:
        raise HTTPException(404, str(e)) from None
    # the answer's bytes are kept with the grid image (a new image when the grid changes): a
    # planner polling a map gets them without encoding its ~10^6 cells again
    key = (format, None if resolution is None else float(resolution))
    with _ENCODED_LOCK:
        kept = grid.encoded.get(key)
    if kept is None:
        g = grid if resolution is None else grid.resampled(resolution)
        f = files.map_yaml_fields(g, "grid.pgm")
        fields = {"X-Map-Resolution": f"{g.resolution:.9g}", "X-Map-Origin": ",".join(f"{v:.9g}" for v in f["origin"]),
                  "X-Map-To-Grid": ",".join(f"{v:.9g}" for v in f["map_to_grid"]), "X-Map-Keyframes": str(g.keyframes)}
        body = {"png": files.png_bytes, "pgm": files.pgm_bytes, "yaml": files.map_yaml}.get(format, _grid_json)(g)
        kept = (body, fields)
        with _ENCODED_LOCK:
            if len(grid.encoded) >= 8:  # (a few formats and resolutions)
                grid.encoded.clear()
            grid.encoded[key] = kept
    body, fields = kept
    media = {"png": "image/png", "pgm": "image/x-portable-graymap", "yaml": "text/yaml"}.get(format, "application/json")
    return Response(body, media_type=media, headers={**fields, "X-Map-Current": "true" if current else "false"})


_ENCODED_LOCK = threading.Lock()


def _grid_json(grid) -> bytes:
    """GridOut's JSON, written directly: a 20k-keyframe map's grid has ~10^6 cells, which
    pydantic would validate one by one."""
    import json

    f = files.map_yaml_fields(grid, "")
    head = json.dumps({k: v for k, v in f.items()} | {"width": grid.width, "height": grid.height,
                                                       "keyframes": grid.keyframes})[:-1]
    # each cell's text from a table of 4-byte tokens ("-1,", "0,", "100,"), padding dropped:
    # vectorised (~20 ms for 2 M cells against ~0.5 s for str() per cell)
    table = np.frombuffer(b"-1,\x000,\x00\x00100,", np.uint8).reshape(3, 4)
    code = np.where(grid.states == -1, 0, np.where(grid.states == 0, 1, 2)).reshape(-1)
    text = table[code].reshape(-1)
    data = text[text != 0].tobytes()[:-1]
    return head.encode() + b', "data": [' + data + b"]}"


@read_routes.get("/maps/{map_id}/cloud", response_model=CloudOut, responses={**error_responses(404), 200: {
    "content": {"application/octet-stream": {}}, "description": "binary PLY (x, y, z float32, red, green, blue "
    "uint8), or with format=json the points as lists"}})
def map_cloud(map_id: DbId, request: Request, store: StoreDep, voxel: Voxel = 0.02,
              format: Literal["ply", "json"] = "ply"):
    """The map's coloured point cloud in the map frame: every keyframe's stored depth and
    colour at its optimised pose, voxel-filtered (`voxel` m). PLY by default (binary, as
    rtabmap-export writes it); `json` for small maps."""
    grids = _grids(request, store)
    try:
        ids, poses = grids.keyframes(map_id)
    except NoMap as e:
        raise HTTPException(404, str(e)) from None
    P, C = grid_cloud.map_cloud(store, ids, poses, voxel, cache=grids.clouds)
    if len(P) == 0:
        raise HTTPException(404, f"map {map_id} has no stored depth (storage.keep_images false, or a stereo map)")
    if format == "json":
        return {"count": len(P), "voxel": voxel, "points": np.round(P, 4).tolist(), "colors": C.tolist()}
    return Response(grid_cloud.ply_bytes(P, C), media_type="application/octet-stream",
                    headers={"Content-Disposition": f'attachment; filename="map{map_id}.ply"',
                             "X-Points": str(len(P))})


@read_routes.get("/path", response_model=GridPathOut, responses=error_responses(400, 404))
def grid_path(request: Request, service: ServiceDep, store: StoreDep,
              robot: Annotated[str, Query(pattern=f"^{ROBOT_PATTERN.pattern}$", description="the robot")],
              to: Annotated[int | None, Query(ge=0, le=SQLITE_INT_MAX, description="an object id")] = None,
              x: Coordinate = None, y: Coordinate = None, z: Coordinate = None):
    """A path on the robot's map's occupancy grid from its current position to an object
    (`to`) or a point (x, y, z, map frame): A* over the free cells at least
    grid.robot_radius from obstacles, shortened by line of sight. 404 says why there is
    none (unknown robot, no pose, no grid, the goal in another map, not reachable)."""
    point = [v is not None for v in (x, y, z)]
    if any(point) and not all(point):
        raise HTTPException(400, "a point needs all of x, y and z")
    if (to is not None) == all(point):
        raise HTTPException(400, "give either to=OBJECT_ID or x, y, z (one of them)")
    cfg = request.app.state.grids.config
    grids = _grids(request, store)
    try:
        at = robot_location(service.robots(), robot, store)
    except NotFound as e:
        raise HTTPException(404, str(e)) from None
    if at.node_id is None:
        raise HTTPException(404, f"robot {robot!r} has no keyframe yet: no map to plan in")
    map_id = grids.map_of(at.node_id)
    obj = None
    if to is not None:
        obj = store.get_object(to)
        if obj is None:
            raise HTTPException(404, f"no object {to}")
        if grids.map_of(obj.node_id) != map_id:
            raise HTTPException(404, f"object {to} is in another map than robot {robot!r} (map "
                                f"{grids.map_of(obj.node_id)}, the robot's: {map_id}): not localized there yet")
        goal = np.asarray(obj.position, np.float64)
    else:
        goal = np.array([x, y, z], np.float64)
    try:
        grid, _ = grids.latest(map_id)
        start_g, goal_g = grid.to_grid(np.asarray(at.position, np.float64)), grid.to_grid(goal)
        p = plan(grid, start_g[:2], goal_g[:2], cfg.robot_radius, cfg.path_unknown)
    except (NoMap, NoPath) as e:
        raise HTTPException(404, f"no path for robot {robot!r}: {e}") from None
    inv = np.linalg.inv(grid.map_to_grid)
    pg = np.column_stack([p.points, np.full(len(p.points), start_g[2]), np.ones(len(p.points))])
    pts = (pg @ inv.T)[:, :3]
    out = {"robot": robot, "map": map_id, "start": [float(v) for v in at.position],
           "goal": [float(v) for v in goal], "points": pts.round(4).tolist(),
           "grid_points": p.points.round(4).tolist(), "length": p.length, "goal_distance": p.goal_snap}
    if obj is not None:
        from ...runner import object_dict

        out["object"] = {**object_dict(obj), "class_id": int(obj.class_id)}
    return out

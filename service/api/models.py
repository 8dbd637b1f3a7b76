"""The API's schemas: the path and query parameters' types (bounds and descriptions in the
OpenAPI), the request body and the response models (every response has one in the OpenAPI),
and `error_responses`, the documented error answers."""
from __future__ import annotations

from typing import Annotated, Any

from fastapi import Path, Query
from pydantic import BaseModel, ConfigDict, Field

from mnemoslam.client.kernel.protocol import ROBOT_PATTERN

# -- request parameters ---------------------------------------------------------------------
# The largest SQLite INTEGER (signed 64-bit): a bigger id or offset cannot be bound to a query.
# Bounding the parameters makes such input a 422 (and documents the range in the OpenAPI).
SQLITE_INT_MAX = 2**63 - 1
DbId = Annotated[int, Path(ge=0, le=SQLITE_INT_MAX, description="a database id (0 .. 2^63-1)")]
RobotId = Annotated[str, Path(pattern=f"^{ROBOT_PATTERN.pattern}$", description="a robot id as on the wire")]
RobotQuery = Annotated[str | None, Query(pattern=f"^{ROBOT_PATTERN.pattern}$",
                                         description="a robot id: from its current pose")]
LabelQuery = Annotated[str, Query(min_length=1, max_length=128, description="an object class, e.g. door")]
Coordinate = Annotated[float | None, Query(allow_inf_nan=False, description="metres, map frame")]
Limit = Annotated[int, Query(ge=1, le=10000)]
Radius = Annotated[float | None, Query(ge=0, allow_inf_nan=False, description="m around x, y, z")]
Offset = Annotated[int, Query(ge=0, le=SQLITE_INT_MAX)]


# -- response models ------------------------------------------------------------------------
class Open(BaseModel):
    """A model that keeps fields added later by the service (documented ones are typed)."""
    model_config = ConfigDict(extra="allow")


class Health(Open):
    status: str = Field(description="ok, or stopped when the service is shutting down")
    uptime_s: float | None = None
    robots: int | None = None
    rejected_total: int | None = None


class RobotStatus(Open):
    robot: str
    state: str = Field(description="waiting_for_frames | tracking | lost | stopped")
    queue_depth: int
    queue_mb: float
    frames_received: int
    frames_processed: int
    frames_dropped: int
    frames_rejected: dict[str, int]
    tracked: int
    lost: int
    keyframes: int
    fps: float
    processing_ms: float
    last_stamp: float | None
    session_id: int | None
    position: list[float] | None = Field(None, description="map-frame position of its last tracked frame")
    pose: list[float] | None = Field(None, description="its last tracked frame's camera pose (row-major 4x4, "
                                     "camera-to-map, OpenCV axes) in the frame `map` names")
    node_id: int | None = Field(None, description="its latest keyframe")
    keyframes_mapped: int
    map_backlog: int
    restarts: int = Field(0, description="camera restarts (stamps back by more than service.restart_gap): its "
                          "session ended \"restarted\" and session_id is the new one's")
    map: int | None = Field(None, description="the map id of the oldest session that links join its latest keyframe "
                            "to: its own session's until it relocalizes in an older map (null without a keyframe); "
                            "a localizing robot's: the map it is relocalized in (null until it is)")
    mode: str = Field("mapping", description="mapping | localization (nothing of the robot is written to the map: "
                      "memory.incremental false, or its camera info's `localize`; no session_id then, and node_id "
                      "is the map's keyframe its own keyframes are linked to)")
    localized: bool = Field(False, description="its poses (position, the pose messages) are in an older map's frame: "
                            "a mapping robot's session joined one, a localizing robot relocalized in `map`")


class CalibrationOut(BaseModel):
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    baseline: float | None
    depth_scale: float


class SessionSummary(BaseModel):
    id: int
    robot: str
    map_id: int
    started_at: float
    ended_at: float | None
    calibration: CalibrationOut
    end_reason: str | None = Field(description='"stopped", "idle", "restarted" (a camera restart), "crashed"; '
                                               'null while it runs')
    map: int | None = Field(None, description="the map its keyframes are in now: map_id (its own) until a link "
                            "joined them to an older map's, then that map's id (null: no keyframe yet)")
    joined: bool = Field(False, description="whether its keyframes joined an older map")
    joined_keyframe: int | None = Field(None, description="its keyframe at the link that joined it to that map")
    joined_stamp: float | None = Field(None, description="that keyframe's stamp (s, the camera's clock)")
    joined_peer: int | None = Field(None, description="the map's keyframe at that link")
    joined_link: str | None = Field(None, description="that link's type (loop, proximity, merged, ...)")
    T_map_session: list[float] | None = Field(None, description=(
        "the session's frame in its map's frame, row-major 4×4: the session's odometry starts at the identity on "
        "its first keyframe, so this is that keyframe's current (optimised) pose; the identity for a session that "
        "is its own map's first; null without a keyframe"))


class SessionOut(SessionSummary):
    config: dict[str, Any] | None = Field(description="the service's configuration the session ran with")


class NodeOut(BaseModel):
    id: int
    session_id: int
    robot: str
    stamp: float
    position: list[float] = Field(description="x, y, z (m)")
    pose: list[float] = Field(description="4×4 camera-to-world, row-major")
    weight: int
    label: str | None


class NodePage(BaseModel):
    total: int
    limit: int
    offset: int
    nodes: list[NodeOut]


class PoseOut(BaseModel):
    stamp: float
    pose: list[float]


class TrajectoryOut(BaseModel):
    session_id: int
    poses: list[PoseOut]


class LinkOut(BaseModel):
    model_config = ConfigDict(populate_by_name=True)
    from_: int = Field(alias="from")
    to: int
    type: str
    transform: list[float]


class GraphOut(BaseModel):
    nodes: list[NodeOut]
    links: list[LinkOut]


class DatabaseStats(Open):
    schema_version: int
    sessions: int
    nodes: int
    links: int
    links_by_type: dict[str, int]
    features: int
    keypoints: int
    words: int
    images: int
    statistics: int
    file_bytes: int
    wal_bytes: int


class StatsOut(BaseModel):
    service: dict[str, Any]
    robots: list[RobotStatus]
    database: DatabaseStats


class ObjectOut(BaseModel):
    id: int
    label: str
    class_id: int
    confidence: float = Field(description="posterior probability of the label")
    position: list[float] = Field(description="x, y, z (m) in the map frame")
    extent: list[float] = Field(description="axis-aligned size x, y, z (m)")
    observations: int = Field(description="keyframes that observed it")
    node_id: int = Field(description="its anchor keyframe (it moves with it when the graph is corrected)")


class NearestOut(BaseModel):
    object: ObjectOut
    distance: float = Field(description="m from the query point (or the robot) to the object")
    node_id: int = Field(description="the object's anchor keyframe: the place it was seen from")


class ObjectPage(BaseModel):
    total: int
    limit: int
    offset: int
    objects: list[ObjectOut]


class LabelCount(BaseModel):
    label: str
    count: int


class LabelsOut(BaseModel):
    total: int = Field(description="objects in the map")
    labels: list[LabelCount] = Field(description="most frequent first")


class PathNode(BaseModel):
    id: int
    position: list[float]


class PathOut(BaseModel):
    object: ObjectOut
    robot: str
    start_node: int = Field(description="the robot's node (its latest keyframe)")
    goal_node: int = Field(description="the graph node nearest the object that the robot's node reaches")
    nodes: list[PathNode] = Field(description="start_node .. goal_node along the pose graph's links")
    length: float = Field(description="m along the path")
    goal_distance: float = Field(description="m from goal_node to the object")


class SemanticsOut(Open):
    enabled: bool
    source: str | None = None
    model: str | None = None
    reason: str | None = Field(None, description="why semantics are off")
    model_reason: str | None = Field(None, description="why there is no model (source auto: the camera's labels "
                                     "only; unlabelled keyframes stay unsegmented)")
    classes: list[str] = []
    coverage: dict | None = Field(None, description="the map's keyframes, those segmented (in the semantic map), "
                                  "those skipped (nothing to segment) and the share segmented")
    worker: dict | None = Field(None, description="the map's semantic worker: keyframes processed, deferred to the "
                                "back-fill (queue full), back-filled, dropped, failed and skipped; objects")
    workers: dict[str, dict] = Field({}, description="the same counts of each connected robot's keyframes")


class LabelIn(BaseModel):
    label: str | None = Field(description="the node's new name (unique in the map); null clears it",
                              min_length=1, max_length=128)


class DeletedOut(BaseModel):
    deleted: int


class MapOut(BaseModel):
    map: int = Field(description="the map id (of its oldest session)")
    id: int = Field(description="the same map id")
    keyframes: int = Field(description="its keyframes (not merged into another)")
    sessions: list[int] = Field(description="the sessions whose keyframes are in it (joined or its own)")
    robots: list[str] = Field(description="their robots")
    objects: int = Field(description="semantic objects anchored on its keyframes")
    last_change: float = Field(description="wall time (s since the epoch) of its newest keyframe or session start / "
                               "end")


class GridOut(BaseModel):
    """An occupancy grid as ROS's nav_msgs/OccupancyGrid with map_server's YAML fields."""
    resolution: float = Field(description="m per cell")
    origin: list[float] = Field(description="x, y, yaw of the lower-left cell's corner in the grid frame (m, rad)")
    negate: int = 0
    occupied_thresh: float
    free_thresh: float
    map_to_grid: list[float] = Field(description="the 4×4 transform grid ← map frame, row-major")
    width: int
    height: int
    keyframes: int = Field(description="keyframes assembled into it")
    data: list[int] = Field(description="row-major from the origin cell (row 0 = lowest y): -1 unknown, 0 free, "
                            "100 occupied")
    image: str = ""


class CloudOut(BaseModel):
    count: int
    voxel: float = Field(description="m")
    points: list[list[float]] = Field(description="x, y, z (m, map frame)")
    colors: list[list[int]] = Field(description="red, green, blue (0-255) of each point")


class GridPathOut(BaseModel):
    robot: str
    map: int
    start: list[float] = Field(description="the robot's position (map frame)")
    goal: list[float] = Field(description="the target: the object's position or the point (map frame)")
    points: list[list[float]] = Field(description="the path's corners in the map frame (at the start's height), "
                                      "from the robot's cell to the goal's")
    grid_points: list[list[float]] = Field(description="the same corners in the grid frame (x, y; m)")
    length: float = Field(description="m along the path")
    goal_distance: float = Field(description="m from the path's end to the goal (an object is itself an obstacle: "
                                 "the path ends at the nearest free cell)")
    object: ObjectOut | None = None


class ErrorOut(BaseModel):
    detail: Any


def error_responses(*codes: int) -> dict:
    """The OpenAPI `responses` of a route's (or router's) error codes."""
    text = {400: "bad parameters", 401: "no or wrong API token", 403: "refused (no API token configured)",
            404: "not found (the reason in detail)", 409: "conflict", 503: "the service is not running"}
    return {c: {"model": ErrorOut, "description": text[c]} for c in codes}


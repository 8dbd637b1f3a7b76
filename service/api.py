"""The REST API (FastAPI): health, robots, sessions, a map's nodes, trajectory and graph,
statistics, and the semantic map (objects: nearest of a label, by label / around a point, one,
labels with counts, a path along the pose graph to one). OpenAPI docs at /docs; every
response has a Pydantic model there. Prometheus metrics at /metrics (service/metrics.py; not
in the OpenAPI). The live web viewer at /viewer, fed by server-sent events at /viewer/events
(service/viewer.py; not in the OpenAPI either); serve the app with `ApiServer`, which ends
those streams when it shuts down.

Reads go to the service's live state, to the SQLite long-term memory and, for objects, to the
query layer (`service.semantics.queries`); route handlers only translate its answers to HTTP.
The store, the service, the object index, a session and the access checks are FastAPI
dependencies (`Depends`).

Access control (`api.token`, overridden by the environment variable MNEMOSLAM_API_TOKEN):
- endpoints that change the map (POST / PUT / DELETE) need `Authorization: Bearer <token>`:
  401 without it or with another token; when no token is configured they answer 403 (how to
  set one), so a service is never writable by accident;
- reads are open, or need the token too when `api.protect_reads` is true (that needs a
  token: create_app refuses to start otherwise); /health stays open for liveness probes;
- the viewer's routes are reads, but with api.protect_reads they also take the token as
  `?token=` (a browser's EventSource sends no header); no other route does.

Semantics off (`semantics.enabled` false or no model): the object endpoints still answer
from the objects the database holds (earlier sessions' objects stay queryable) and say so:
every object response carries the header `X-Semantics: on|off`, a 404 for a missing label
adds why semantics are off, and GET /semantics tells the state and why.
"""
from __future__ import annotations

import hmac
import math
import os
import threading
import time
from typing import Annotated, Any

import uvicorn
from fastapi import APIRouter, Body, Depends, FastAPI, HTTPException, Path, Query, Request, Response
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import HTMLResponse, PlainTextResponse, StreamingResponse
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from pydantic import BaseModel, ConfigDict, Field

from client.protocol import ROBOT_PATTERN
from client.trajectory import format_tum
from storage import MapRepository, SessionRecord, StoreError, UnknownIdError, link_name

from .config import Config
from .metrics import Metrics, RequestTimer
from .semantics.queries import NotFound, ObjectIndex, ObjectView, QueryError, Unavailable, robot_location
from .server import SlamService
from .viewer import Viewer

TOKEN_ENV = "MNEMOSLAM_API_TOKEN"

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
    node_id: int | None = Field(None, description="its latest keyframe")
    keyframes_mapped: int
    map_backlog: int
    restarts: int = Field(0, description="camera restarts (stamps back by more than service.restart_gap): its "
                          "session ended \"restarted\" and session_id is the new one's")
    map: int | None = Field(None, description="(GET /robots/{robot}) the map id of the oldest session that links "
                            "join its latest keyframe to: its own session's until it relocalizes in an older map")


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


class ErrorOut(BaseModel):
    detail: Any


def _errors(*codes: int) -> dict:
    text = {400: "bad parameters", 401: "no or wrong API token", 403: "refused (no API token configured)",
            404: "not found (the reason in detail)", 409: "conflict", 503: "the service is not running"}
    return {c: {"model": ErrorOut, "description": text[c]} for c in codes}


# -- conversions ----------------------------------------------------------------------------
def _pose_list(pose) -> list[float]:
    return [float(v) for v in pose.reshape(-1)]


def _node_json(n) -> dict:
    return {"id": n.id, "session_id": n.session_id, "robot": n.robot, "stamp": n.stamp,
            "position": _pose_list(n.pose[:3, 3]), "pose": _pose_list(n.pose), "weight": n.weight, "label": n.label}


def _object_json(o: ObjectView) -> dict:
    return o.to_dict()


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


# -- dependencies ---------------------------------------------------------------------------
class Access:
    """The access rule of one app: the token (config, overridden by MNEMOSLAM_API_TOKEN) and
    whether reads need it."""

    def __init__(self, token: str, protect_reads: bool):
        if protect_reads and not token:
            raise ValueError(f"api.protect_reads needs a token: set api.token or {TOKEN_ENV}")
        self.token, self.protect_reads = token, protect_reads

    @classmethod
    def from_config(cls, config: Config) -> "Access":
        return cls(os.environ.get(TOKEN_ENV) or config.api.token, config.api.protect_reads)

    def check(self, credentials: HTTPAuthorizationCredentials | None) -> None:
        if not self.token:
            raise HTTPException(403, "this endpoint changes the map and no API token is configured: set api.token "
                                     f"in the service's config or the environment variable {TOKEN_ENV}, then send "
                                     "'Authorization: Bearer <token>'")
        given = credentials.credentials if credentials is not None else None
        if given is None:
            raise HTTPException(401, "missing API token: send 'Authorization: Bearer <token>'",
                                headers={"WWW-Authenticate": "Bearer"})
        if not hmac.compare_digest(given.encode(), self.token.encode()):
            raise HTTPException(401, "wrong API token", headers={"WWW-Authenticate": 'Bearer error="invalid_token"'})


_bearer = HTTPBearer(auto_error=False, description="the service's API token (api.token / MNEMOSLAM_API_TOKEN)")
Credentials = Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]


# Cheap dependencies are `async def`: FastAPI runs a sync one in its thread pool (a thread hop
# each), which at hundreds of requests/s costs more than the query itself.
async def get_service(request: Request) -> SlamService:
    return request.app.state.service


async def require_token(request: Request, credentials: Credentials) -> None:
    """Endpoints that change the map."""
    request.app.state.access.check(credentials)


async def read_access(request: Request, credentials: Credentials) -> None:
    """Reads: open, unless api.protect_reads."""
    access: Access = request.app.state.access
    if access.protect_reads:
        access.check(credentials)


async def viewer_access(request: Request, credentials: Credentials,
                        token: Annotated[str | None, Query(description="the API token, with api.protect_reads (a "
                                                                       "browser's EventSource sends no header)")] = None
                        ) -> None:
    """The viewer's page and events: reads, but the token may also come as `?token=` (the
    browser's EventSource cannot send an Authorization header). Only there, and only looked at
    with api.protect_reads."""
    access: Access = request.app.state.access
    if access.protect_reads:
        if credentials is None and token is not None:
            credentials = HTTPAuthorizationCredentials(scheme="Bearer", credentials=token)
        try:
            access.check(credentials)
        except HTTPException as e:
            raise HTTPException(e.status_code, f"{e.detail} (the viewer: open /viewer?token=<token>)",
                                headers=e.headers) from None


ServiceDep = Annotated[SlamService, Depends(get_service)]


async def get_store(service: ServiceDep) -> MapRepository:
    store = service.store
    if store is None:
        raise HTTPException(503, "the service is not running")
    return store


StoreDep = Annotated[MapRepository, Depends(get_store)]


def get_session(session_id: DbId, store: StoreDep) -> SessionRecord:
    s = store.session(session_id)
    if s is None:
        raise HTTPException(404, f"no session {session_id}")
    return s


SessionDep = Annotated[SessionRecord, Depends(get_session)]


class _IndexHolder:
    """One ObjectIndex per open store of the service (a restarted service gets a new one)."""

    def __init__(self):
        self._lock = threading.Lock()
        self._store = None
        self._index: ObjectIndex | None = None

    def get(self, store) -> ObjectIndex:
        with self._lock:
            if self._index is None or self._store is not store:
                if self._index is not None:
                    self._index.close()
                self._store, self._index = store, ObjectIndex(store)
            return self._index

    def close(self) -> None:
        with self._lock:
            if self._index is not None:
                self._index.close()
            self._index = self._store = None


def _semantics_of(service) -> dict:
    status = getattr(service, "semantics_status", None)
    if status is None:
        return {"enabled": False, "source": None, "model": None,
                "reason": "this service has no semantic pipeline", "classes": []}
    return status()


class ObjectContext:
    """What an object endpoint needs, in one dependency (each dependency costs FastAPI ~20 µs
    to solve per request; the nearest query itself ~50 µs): the service, its store, the
    object index and the semantic state; `errors()` turns query-layer exceptions into HTTP."""

    def __init__(self, service: SlamService, store: MapRepository, index: ObjectIndex, semantics: dict):
        self.service, self.store, self.index, self.semantics = service, store, index, semantics

    def errors(self) -> "_QueryErrors":
        return _QueryErrors(self.semantics)

    def point(self, x: float | None, y: float | None, z: float | None) -> tuple[float, float, float] | None:
        """x, y, z given together (or none of them)."""
        given = [v is not None for v in (x, y, z)]
        if any(given) and not all(given):
            raise HTTPException(400, "a point needs all of x, y and z", headers=self.errors().headers)
        return (x, y, z) if all(given) else None


async def object_context(request: Request, response: Response) -> ObjectContext:
    """The object endpoints' dependency. The semantic state is asked at most once a second (it
    looks at the model file; GET /semantics asks every time) and marks the response
    (X-Semantics: on|off); the index's first build reads every object (≈0.5 s at 100k): off
    the event loop."""
    state = request.app.state
    service = state.service
    store = service.store
    if store is None:
        raise HTTPException(503, "the service is not running")
    cached = state.semantics
    now = time.monotonic()
    if cached is None or now - cached[0] > 1.0:
        cached = state.semantics = (now, _semantics_of(service))
    semantics = cached[1]
    response.headers["X-Semantics"] = "on" if semantics.get("enabled") else "off"
    index = state.objects.get(store)
    if not index.ready:
        with _QueryErrors(semantics):
            await run_in_threadpool(index.snapshot)
    return ObjectContext(service, store, index, semantics)


ObjectsDep = Annotated[ObjectContext, Depends(object_context)]


class _QueryErrors:
    """Query-layer exceptions as HTTP errors (400, 404 with the reason, 503), with the
    X-Semantics header; a 404 says why semantics are off when they are."""

    def __init__(self, semantics: dict):
        self.semantics = semantics
        self.headers = {"X-Semantics": "on" if semantics.get("enabled") else "off"}

    def __enter__(self):
        return self

    def __exit__(self, typ, e, tb):
        on, headers = bool(self.semantics.get("enabled")), self.headers
        if isinstance(e, NotFound):
            reason = str(e)
            if not on:
                reason += f" (semantics are off: {self.semantics.get('reason') or 'semantics.enabled is false'})"
            raise HTTPException(404, reason, headers=headers) from None
        if isinstance(e, QueryError):
            raise HTTPException(400, str(e), headers=headers) from None
        if isinstance(e, Unavailable):
            raise HTTPException(503, str(e), headers=headers) from None
        return False


# -- routes -----------------------------------------------------------------------------------
def create_app(service: SlamService) -> FastAPI:
    app = FastAPI(title="mnemoslam", description="Long-term visual SLAM service: map state, semantic objects "
                  "and planner queries. Endpoints that change the map need 'Authorization: Bearer <token>'.",
                  version="0.2.0")
    app.state.service = service
    app.state.access = Access.from_config(service.config)
    app.state.objects = _IndexHolder()
    app.state.semantics = None  # (when, semantics_status()) for the object endpoints
    app.state.metrics = Metrics(service)
    app.state.viewer = Viewer(service, objects=app.state.objects.get)
    app.add_middleware(RequestTimer, observe=app.state.metrics.observe_request)
    app.router.add_event_handler("shutdown", app.state.objects.close)
    app.include_router(open_routes)
    app.include_router(read_routes)
    app.include_router(write_routes)
    app.include_router(viewer_routes)
    return app


open_routes = APIRouter()
read_routes = APIRouter(dependencies=[Depends(read_access)], responses=_errors(401, 403))
write_routes = APIRouter(dependencies=[Depends(require_token)], responses=_errors(401, 403))
# the live viewer: not in the OpenAPI (a page and an endless event stream, no JSON API)
viewer_routes = APIRouter(dependencies=[Depends(viewer_access)], include_in_schema=False)


@open_routes.get("/health", response_model=Health)
def health(service: ServiceDep):
    """Liveness: always open (no token)."""
    return {"status": "ok" if service.store is not None else "stopped", **{
        k: v for k, v in service.status().items() if k in ("uptime_s", "robots", "rejected_total")}}


@read_routes.get("/robots", response_model=list[RobotStatus])
def robots(service: ServiceDep):
    return service.robots()


@read_routes.get("/robots/{robot}", response_model=RobotStatus, responses=_errors(404))
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


@read_routes.get("/sessions", response_model=list[SessionSummary])
def sessions(store: StoreDep, robot: Annotated[str | None, Query(
        pattern=f"^{ROBOT_PATTERN.pattern}$", description="only this robot's sessions")] = None):
    """The sessions, oldest first (only `robot`'s with ?robot=); each one's configuration is
    in GET /sessions/{id}."""
    return [s.to_dict() for s in store.sessions(robot=robot)]


@read_routes.get("/sessions/{session_id}", response_model=SessionOut, responses=_errors(404))
def session(session: SessionDep):
    """One session, with the configuration it ran with."""
    return session.to_dict()


@read_routes.get("/sessions/{session_id}/nodes", response_model=NodePage, responses=_errors(400, 404))
def nodes(session: SessionDep, store: StoreDep,
          bbox: str | None = Query(None, description="xmin,ymin,zmin,xmax,ymax,zmax (metres)"),
          limit: Limit = 100, offset: Offset = 0):
    box = _parse_bbox(bbox)
    return {"total": store.count_nodes(session_id=session.id, bbox=box), "limit": limit, "offset": offset,
            "nodes": [_node_json(n) for n in store.nodes(session_id=session.id, bbox=box, limit=limit, offset=offset)]}


@read_routes.get("/sessions/{session_id}/trajectory", response_model=TrajectoryOut, responses={
    **_errors(404), 200: {"content": {"text/plain": {"schema": {"type": "string"}}},
                          "description": "JSON, or TUM text with format=tum"}})
def trajectory(session: SessionDep, store: StoreDep, format: str = Query("json", pattern="^(json|tum)$")):
    traj = store.trajectory(session.id)
    if format == "tum":
        return PlainTextResponse(format_tum(traj))
    return {"session_id": session.id, "poses": [
        {"stamp": float(t), "pose": _pose_list(p)} for t, p in zip(traj.stamps, traj.poses)]}


@read_routes.get("/sessions/{session_id}/graph", response_model=GraphOut, responses=_errors(404))
def graph(session: SessionDep, store: StoreDep):
    nodes = store.nodes(session_id=session.id, limit=10**9, offset=0)
    links = store.links(session_id=session.id)
    return {"nodes": [_node_json(n) for n in nodes],
            "links": [{"from": lk.from_id, "to": lk.to_id, "type": link_name(lk.type),
                       "transform": _pose_list(lk.transform)} for lk in links]}


@read_routes.get("/nodes/{node_id}/statistics", response_model=dict[str, Any], responses=_errors(404))
def node_statistics(node_id: DbId, store: StoreDep):
    """Why a loop was or wasn't closed at this keyframe: hypothesis, posterior, likelihood
    top-k, decision, verification inliers, time per step."""
    data = store.statistics(node_id)
    if data is None:
        raise HTTPException(404, f"no statistics for node {node_id}")
    return data


@read_routes.get("/stats", response_model=StatsOut)
def stats(service: ServiceDep, store: StoreDep):
    st = service.status()
    st.pop("config", None)
    return {"service": st, "robots": service.robots(), "database": store.stats()}


@read_routes.get("/metrics", include_in_schema=False)
def metrics(request: Request):
    """Prometheus metrics (text format 0.0.4, or OpenMetrics when asked for): the service's
    counters, each robot's, the map updates', REST latency (service/metrics.py). A read:
    behind the token with api.protect_reads (a scraper sends it as a bearer token). Not in the
    OpenAPI: it is no JSON API."""
    body, content_type = request.app.state.metrics.render(request.headers.get("accept"))
    return Response(body, media_type=content_type)


@read_routes.get("/config", response_model=Config)
def config(service: ServiceDep, request: Request):
    """The service's configuration (the API token is shown as *** when set, also by
    MNEMOSLAM_API_TOKEN)."""
    config = service.status()["config"]
    if request.app.state.access.token:
        config = {**config, "api": {**config["api"], "token": "***"}}
    return config


# -- semantic map -----------------------------------------------------------------------------
@read_routes.get("/semantics", response_model=SemanticsOut)
def semantics(service: ServiceDep):
    """Whether the service fuses semantic labels into objects now (source, model, classes), or
    why not. The object endpoints answer from the database either way."""
    return _semantics_of(service)


@read_routes.get("/objects/nearest", response_model=NearestOut, responses=_errors(400, 404))
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


@read_routes.get("/objects", response_model=ObjectPage, responses=_errors(400))
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


@read_routes.get("/objects/{object_id}", response_model=ObjectOut, responses=_errors(404))
async def get_object(object_id: DbId, objects: ObjectsDep):
    with objects.errors():
        return _object_json(objects.index.get(object_id))


@read_routes.get("/objects/{object_id}/path", response_model=PathOut, responses=_errors(404))
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
@write_routes.post("/nodes/{node_id}/label", response_model=NodeOut, responses=_errors(404, 409))
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


@write_routes.delete("/objects/{object_id}", response_model=DeletedOut, responses=_errors(404, 409))
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


# -- the live viewer (service/viewer.py) -------------------------------------------------------------
@viewer_routes.get("/viewer", response_class=HTMLResponse)
def viewer_page(request: Request):
    """The viewer: top-down and 3D views of each session's trajectory and graph (loop links),
    the objects, the robots' live poses and the memory sizes, updated from /viewer/events."""
    return HTMLResponse(request.app.state.viewer.page(), headers={"Cache-Control": "no-cache"})


@viewer_routes.get("/viewer/events")
async def viewer_events(request: Request):
    """Server-sent events: a compact JSON update every ~0.5 s (service/viewer.py)."""
    return StreamingResponse(request.app.state.viewer.events(request.is_disconnected), media_type="text/event-stream",
                             headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"})


class ApiServer(uvicorn.Server):
    """uvicorn's server for an app of `create_app`. At shutdown it first ends the app's event
    streams (the viewer's): uvicorn waits for open responses to end before it tells the app to
    shut down, and an event stream does not end by itself."""

    async def shutdown(self, sockets=None) -> None:
        viewer = getattr(getattr(self.config.app, "state", None), "viewer", None)
        if viewer is not None:
            viewer.close()
        await super().shutdown(sockets)


class ApiThread:
    """An app served by uvicorn on a free local port in a thread (tests, benchmarks):
    `with ApiThread(create_app(service)) as url: ...`."""

    def __init__(self, app: FastAPI, host: str = "127.0.0.1", **uvicorn_options):
        import socket

        # TCP explicitly, for TCP_NODELAY on its connections (service/cli.py `_listen_socket`)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM, socket.IPPROTO_TCP)
        self.sock.bind((host, 0))
        self.port = self.sock.getsockname()[1]
        self.url = f"http://{host}:{self.port}"
        self.server = ApiServer(uvicorn.Config(app, log_level="warning", access_log=False, **uvicorn_options))
        self._thread = threading.Thread(target=self.server.run, kwargs={"sockets": [self.sock]}, daemon=True,
                                        name="api-thread")

    def start(self, timeout: float = 20.0) -> "ApiThread":
        self._thread.start()
        deadline = time.monotonic() + timeout
        while not self.server.started:
            if not self._thread.is_alive() or time.monotonic() > deadline:
                raise RuntimeError("the API server did not start")
            time.sleep(0.02)
        return self

    def stop(self) -> None:
        self.server.should_exit = True
        self._thread.join(10)
        self.sock.close()

    def __enter__(self) -> str:
        return self.start().url

    def __exit__(self, *exc):
        self.stop()

"""The API's dependencies (FastAPI `Depends`): access control (`Access`: the token and whether
reads need it; `require_token`, `read_access`, `viewer_access`), the service, its store, a
session, and the object endpoints' context (the object index, the semantic state, query-layer
errors as HTTP). `open_router`, `read_router`, `write_router` and `viewer_router` make a
resource's routers with the access rule of their kind (service/api/routes/)."""
from __future__ import annotations

import hmac
import os
import threading
import time
from typing import Annotated

from fastapi import APIRouter, Depends, HTTPException, Query, Request, Response
from fastapi.concurrency import run_in_threadpool
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from mnemoslam.storage import ApiStore, SessionRecord
from mnemoslam.storage.connectivity import MapIndex

from ..config import Config
from ..semantics.queries import NotFound, ObjectIndex, QueryError, Unavailable
from ..server import SlamService
from .models import DbId, error_responses

TOKEN_ENV = "MNEMOSLAM_API_TOKEN"


# -- access control -------------------------------------------------------------------------
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
    """Endpoints that change the map: the token; 409 from a service that only localizes (its
    map is open read-only)."""
    request.app.state.access.check(credentials)
    if getattr(request.app.state.service, "localization_only", False):
        raise HTTPException(409, "this service only localizes (memory.incremental: false): its map is open "
                                 "read-only and nothing changes it")


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


# -- the service, its store, a session ---------------------------------------------------------
ServiceDep = Annotated[SlamService, Depends(get_service)]


async def get_store(service: ServiceDep) -> ApiStore:
    store = service.store
    if store is None:
        raise HTTPException(503, "the service is not running")
    return store


StoreDep = Annotated[ApiStore, Depends(get_store)]


def get_session(session_id: DbId, store: StoreDep) -> SessionRecord:
    s = store.session(session_id)
    if s is None:
        raise HTTPException(404, f"no session {session_id}")
    return s


SessionDep = Annotated[SessionRecord, Depends(get_session)]


# -- the maps ---------------------------------------------------------------------------------------
class MapsHolder:
    """One `storage.connectivity.MapIndex` per open store of the service (which map each
    keyframe and session is in), brought up to date at each `get`: /maps, /sessions, /robots."""

    def __init__(self):
        self._lock = threading.Lock()
        self._store = None
        self._index: MapIndex | None = None

    def get(self, store) -> MapIndex:
        with self._lock:
            if self._index is None or self._store is not store:
                self._store, self._index = store, MapIndex()
            self._index.refresh(store)
            return self._index


def robots_with_maps(service, maps: MapsHolder) -> list[dict]:
    """The service's robots, each with `map`: the map its latest keyframe is in (its own
    session's until its keyframes joined an older map; None without a keyframe; a localizing
    robot's: the map of the map keyframe its keyframes are linked to, None while it is not
    relocalized), and `localized`: its poses are in an older map's frame (a mapping robot's
    session joined one, a localizing robot relocalized)."""
    robots = service.robots()
    if service.store is None or not any(r.get("node_id") is not None for r in robots):
        return [{**r, "map": None, "localized": False} for r in robots]
    index = maps.get(service.store)
    out = []
    for r in robots:
        m = index.map_of(r["node_id"]) if r.get("node_id") is not None else None
        if r.get("mode") == "localization":
            localized = m is not None
        else:
            j = index.join(r["session_id"]) if r.get("session_id") is not None else None
            localized = bool(j is not None and j.joined)
        out.append({**r, "map": m, "localized": localized})
    return out


# -- the object endpoints ----------------------------------------------------------------------
class IndexHolder:
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


def semantics_of(service) -> dict:
    status = getattr(service, "semantics_status", None)
    if status is None:
        return {"enabled": False, "source": None, "model": None,
                "reason": "this service has no semantic pipeline", "classes": []}
    return status()


class ObjectContext:
    """What an object endpoint needs, in one dependency (each dependency costs FastAPI ~20 µs
    to solve per request; the nearest query itself ~50 µs): the service, its store, the
    object index and the semantic state; `errors()` turns query-layer exceptions into HTTP."""

    def __init__(self, service: SlamService, store: ApiStore, index: ObjectIndex, semantics: dict):
        self.service, self.store, self.index, self.semantics = service, store, index, semantics

    def errors(self) -> "QueryErrors":
        return QueryErrors(self.semantics)

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
        cached = state.semantics = (now, semantics_of(service))
    semantics = cached[1]
    response.headers["X-Semantics"] = "on" if semantics.get("enabled") else "off"
    index = state.objects.get(store)
    if not index.ready:
        with QueryErrors(semantics):
            await run_in_threadpool(index.snapshot)
    return ObjectContext(service, store, index, semantics)


ObjectsDep = Annotated[ObjectContext, Depends(object_context)]


class QueryErrors:
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



# -- routers of each access kind --------------------------------------------------------------
def open_router() -> APIRouter:
    """Routes open to anyone, whatever api.protect_reads says (/health: liveness probes)."""
    return APIRouter()


def read_router() -> APIRouter:
    """Reads: open, or behind the token with api.protect_reads."""
    return APIRouter(dependencies=[Depends(read_access)], responses=error_responses(401, 403))


def write_router() -> APIRouter:
    """Changes to the map: always behind the token."""
    return APIRouter(dependencies=[Depends(require_token)], responses=error_responses(401, 403))


def viewer_router() -> APIRouter:
    """The live viewer: reads that also take `?token=`; not in the OpenAPI (a page and an
    endless event stream, no JSON API)."""
    return APIRouter(dependencies=[Depends(viewer_access)], include_in_schema=False)

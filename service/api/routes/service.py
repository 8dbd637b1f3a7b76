"""The service: GET /stats (the service's, each robot's and the database's counters),
/metrics (Prometheus; not in the OpenAPI), /config (the token masked) and /semantics (whether
objects are fused now, or why not; the coverage)."""
from __future__ import annotations

from fastapi import Request, Response

from ...config import Config
from ..dependencies import ServiceDep, StoreDep, read_router, semantics_of
from ..models import SemanticsOut, StatsOut

read_routes = read_router()


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


@read_routes.get("/semantics", response_model=SemanticsOut)
def semantics(service: ServiceDep):
    """Whether the service fuses semantic labels into objects now (source, model, classes), or
    why not. The object endpoints answer from the database either way."""
    return semantics_of(service)

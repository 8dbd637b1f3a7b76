"""GET /health: liveness, open to anyone (no token, whatever api.protect_reads says)."""
from __future__ import annotations

from ..dependencies import ServiceDep, open_router
from ..models import Health

open_routes = open_router()


@open_routes.get("/health", response_model=Health)
def health(service: ServiceDep):
    """Liveness: always open (no token)."""
    return {"status": "ok" if service.store is not None else "stopped", **{
        k: v for k, v in service.status().items() if k in ("uptime_s", "robots", "rejected_total")}}

"""The live viewer (service/viewer.py): GET /viewer (the page) and /viewer/events (server-sent
events). Reads that also take the token as `?token=` with api.protect_reads (a browser's
EventSource sends no header); not in the OpenAPI."""
from __future__ import annotations

from fastapi import Request
from fastapi.responses import HTMLResponse, StreamingResponse

from ..dependencies import viewer_router

viewer_routes = viewer_router()


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

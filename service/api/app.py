"""The FastAPI app (`create_app`): its state (the service, the access rule, the object index,
the metrics, the viewer), the request timer middleware and the routers (service/api/routes/);
`ApiServer` serves it with uvicorn and `ApiThread` in a thread (tests, benchmarks)."""
from __future__ import annotations

import threading
import time

import uvicorn
from fastapi import FastAPI

from ..grid.maps import GridHolder
from ..metrics import Metrics, RequestTimer
from ..server import SlamService
from ..viewer import Viewer
from .dependencies import Access, IndexHolder, MapsHolder
from .routes import ROUTERS


def create_app(service: SlamService) -> FastAPI:
    app = FastAPI(title="mnemoslam", description="Long-term visual SLAM service: map state, semantic objects "
                  "and planner queries. Endpoints that change the map need 'Authorization: Bearer <token>'.",
                  version="0.2.0")
    app.state.service = service
    app.state.access = Access.from_config(service.config)
    app.state.objects = IndexHolder()
    app.state.maps = MapsHolder()  # which map each keyframe and session is in (storage.connectivity)
    app.state.grids = GridHolder(service.config.grid)  # the maps' occupancy grids (service/grid)
    app.state.semantics = None  # (when, semantics_status()) for the object endpoints
    app.state.metrics = Metrics(service)
    app.state.viewer = Viewer(service, objects=app.state.objects.get)
    app.add_middleware(RequestTimer, observe=app.state.metrics.observe_request)
    app.router.add_event_handler("shutdown", app.state.objects.close)
    app.router.add_event_handler("shutdown", app.state.grids.close)
    for router in ROUTERS:
        app.include_router(router)
    return app


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

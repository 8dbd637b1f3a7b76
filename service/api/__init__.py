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

The package: `app` (create_app, the uvicorn server), `dependencies` (access control, the
service, its store, a session, the object context), `models` (parameters, request and
response schemas) and `routes/`, one module per resource (health, robots, sessions, service,
objects, viewer), each with routers of one access kind.

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

from .app import ApiServer, ApiThread, create_app
from .dependencies import TOKEN_ENV, Access

__all__ = ["TOKEN_ENV", "Access", "ApiServer", "ApiThread", "create_app"]

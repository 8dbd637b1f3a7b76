"""The API's routes, one module per resource: health, robots, sessions (sessions, nodes,
trajectory, graph, statistics, a node's label), service (stats, metrics, config, semantics),
objects (the semantic map: nearest, by label / around a point, one, its path, labels, delete),
maps (the occupancy grid, the point cloud, paths on the grid) and the viewer. Each module's
routers carry their access rule (service/api/dependencies.py):
`open_routes`, `read_routes`, `write_routes`, `viewer_routes`.

`ROUTERS` is the order the app includes them in: it is the order of the paths in the OpenAPI
(and of the operations under one path), and a fixed path (/objects/nearest) is matched before a
parametric one (/objects/{object_id}) only by coming first in its module."""
from __future__ import annotations

from . import health, maps, objects, robots, service, sessions, viewer

ROUTERS = [
    health.open_routes,
    robots.read_routes,
    sessions.read_routes,
    service.read_routes,
    objects.read_routes,
    maps.read_routes,
    sessions.write_routes,
    objects.write_routes,
    viewer.viewer_routes,
]

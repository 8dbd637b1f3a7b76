"""The semantic query layer under the REST API: "where is the nearest door?", objects by label
or around a point, one object, the labels with their counts, and a path along the pose graph
from a robot to an object. Route handlers call these and only translate the answers to HTTP;
no query logic or SQL lives in `service.api`.

`ObjectIndex` holds the map's objects as numpy columns (`MapStore.object_arrays()`: ids,
labels, world positions, extents, ...) grouped by label, and answers from them with vectorized
distances: a nearest-object query over 100k objects costs tens of microseconds (one label's
rows) to ~1 ms (all rows one label). The columns are an immutable snapshot swapped
atomically, so any number of request threads read it without a lock.

Freshness: object positions are the anchor keyframes' poses applied to their centroids, so
they change when objects are written *and* when loop closure corrects the graph. The index
watches the database's `PRAGMA data_version` on its own read connection (it changes on every
commit by any other connection or process, e.g. the mapping child writing corrected poses);
at most every `check_interval` s a query looks at it, and when it changed and the last
rebuild is `min_rebuild_interval` s old, one background thread rebuilds the snapshot while
queries keep answering from the previous one. A planner therefore sees positions at most
~`min_rebuild_interval` + one rebuild (≈0.5 s at 100k objects) old; `refresh()` rebuilds
now (the API calls it after its own writes, so a deleted object is gone at once).

The graph for paths (node positions and `link_pairs()`) is cached the same way, built on the
first path query after a change.

Frames: positions are comparable only where links join the keyframes (a robot, session or
segment not yet placed in the map has a frame of its own). The snapshot keeps each anchor's
component (`connectivity.MapConnectivity`, read incrementally from the links); a query from a
robot's keyframe (`nearest(..., joined_to=)`, `path`) answers only from objects joined to it.
"""
from __future__ import annotations

import heapq
import logging
import math
import sqlite3
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mnemoslam.storage.connectivity import MapConnectivity

log = logging.getLogger("mnemoslam.semantics.queries")


class QueryError(Exception):
    """The query cannot be answered as asked (HTTP 400)."""


class NotFound(Exception):
    """Nothing answers the query; `str(e)` says why (HTTP 404)."""


class Unavailable(Exception):
    """The map holds no objects table (a database before schema v4) or is closed (HTTP 503)."""


@dataclass(frozen=True)
class ObjectView:
    """One object as the queries return it: world position (the anchor keyframe's current pose
    applied to the stored centroid), axis-aligned extent (m), the argmax label and its
    posterior probability, how many keyframes observed it, and its anchor keyframe."""
    id: int
    label: str
    class_id: int
    confidence: float
    position: tuple[float, float, float]
    extent: tuple[float, float, float]
    observations: int
    node_id: int

    def to_dict(self) -> dict:
        return {"id": self.id, "label": self.label, "class_id": self.class_id, "confidence": self.confidence,
                "position": list(self.position), "extent": list(self.extent), "observations": self.observations,
                "node_id": self.node_id}


@dataclass(frozen=True)
class Nearest:
    object: ObjectView
    distance: float  # m, from the query point to the object's position
    node_id: int  # the object's anchor keyframe (the place it was seen from)


@dataclass(frozen=True)
class Page:
    total: int  # objects matching the filters
    objects: list[ObjectView]  # objects[offset:offset + limit] of them (by distance with a point, else by id)


@dataclass(frozen=True)
class GraphPath:
    object: ObjectView
    start_node: int  # the robot's node
    goal_node: int  # the graph node nearest the object (among those the robot's node reaches)
    nodes: list[int]  # start_node .. goal_node along graph links
    positions: list[tuple[float, float, float]]  # of those nodes
    length: float  # m along the path (straight segments between node positions)
    goal_distance: float  # m from the goal node to the object


@dataclass(frozen=True)
class RobotLocation:
    robot: str
    position: tuple[float, float, float]
    node_id: int | None  # its latest keyframe (None: not known)
    source: str  # "tracking" (the robot's last tracked pose) or "keyframe" (its latest keyframe in the map)


def _finite_point(point) -> np.ndarray:
    p = np.asarray(point, np.float64).reshape(-1)
    if p.shape != (3,) or not np.isfinite(p).all():
        raise QueryError(f"a point is 3 finite numbers x, y, z; got {point!r}")
    return p


@dataclass(frozen=True)
class _Snapshot:
    """The objects' columns, rows ordered by id, and per label the rows of that label."""
    ids: np.ndarray  # (N,) int64, ascending
    labels: np.ndarray  # (N,) object (str)
    class_id: np.ndarray
    position: np.ndarray  # (N, 3) float64
    extent: np.ndarray  # (N, 3)
    confidence: np.ndarray
    observations: np.ndarray
    node_id: np.ndarray
    root: np.ndarray | None = None  # (N,) the anchor's component when the index was built (connectivity)
    by_label: dict[str, np.ndarray] = field(default_factory=dict)  # label -> rows (ascending ids)
    label_positions: dict[str, np.ndarray] = field(default_factory=dict)  # label -> (n, 3) contiguous positions
    label_blocks: dict[str, "_Blocks"] = field(default_factory=dict)  # labels with many objects: spatial blocks
    label_roots: dict[str, tuple] = field(default_factory=dict)  # label -> (its rows' distinct roots, row -> which)
    version: object = None
    built_at: float = 0.0
    build_s: float = 0.0

    @classmethod
    def from_arrays(cls, a: dict, version=None,
                    root_of: Callable[[np.ndarray], np.ndarray] | None = None) -> "_Snapshot":
        t = time.perf_counter()
        ids = np.asarray(a["id"], np.int64).reshape(-1)
        n = len(ids)
        order = np.argsort(ids, kind="stable") if n and np.any(np.diff(ids) < 0) else slice(None)
        col = lambda k, dt, shape=(n,): np.ascontiguousarray(np.asarray(a[k], dt).reshape(shape)[order])  # noqa: E731
        labels = np.asarray(a["labels"], dtype=object).reshape(-1)[order]
        snap = cls(ids=ids[order], labels=labels, class_id=col("class_id", np.int64),
                   position=col("position", np.float64, (n, 3)), extent=col("extent", np.float64, (n, 3)),
                   confidence=col("confidence", np.float64), observations=col("observations", np.int64),
                   node_id=col("node_id", np.int64), version=version, built_at=time.monotonic())
        if root_of is not None:
            object.__setattr__(snap, "root", root_of(snap.node_id))
        if n:
            names, inverse = np.unique(labels.astype(str), return_inverse=True)
            rows = np.argsort(inverse, kind="stable")
            bounds = np.searchsorted(inverse[rows], np.arange(len(names) + 1))
            for i, name in enumerate(names):
                r = rows[bounds[i]:bounds[i + 1]]
                snap.by_label[str(name)] = r
                snap.label_positions[str(name)] = np.ascontiguousarray(snap.position[r])
                if len(r) > 2 * _Blocks.SIZE:
                    snap.label_blocks[str(name)] = _Blocks.build(r, snap.position[r])
                if snap.root is not None:
                    snap.label_roots[str(name)] = np.unique(snap.root[r], return_inverse=True)
        object.__setattr__(snap, "build_s", time.perf_counter() - t)
        return snap

    def view(self, row: int) -> ObjectView:
        p, e = self.position[row], self.extent[row]
        return ObjectView(int(self.ids[row]), str(self.labels[row]), int(self.class_id[row]),
                          float(self.confidence[row]), (float(p[0]), float(p[1]), float(p[2])),
                          (float(e[0]), float(e[1]), float(e[2])), int(self.observations[row]), int(self.node_id[row]))

    def row_of(self, object_id: int) -> int | None:
        i = int(np.searchsorted(self.ids, object_id))
        return i if i < len(self.ids) and self.ids[i] == object_id else None


@dataclass(frozen=True)
class _Blocks:
    """One label's objects packed into spatial blocks of SIZE (sort-tile-recursive: slabs by
    x, then y, then runs by z) with their bounding boxes, for an exact nearest search that
    visits only the blocks that can hold something nearer than the best so far: a few blocks
    instead of every row (~30 µs at 100k objects of one label instead of ~1 ms)."""
    SIZE = 256
    rows: np.ndarray  # (n,) snapshot rows in block order
    position: np.ndarray  # (n, 3) in block order
    lo: np.ndarray  # (B, 3) block bounding boxes
    hi: np.ndarray

    @classmethod
    def build(cls, rows: np.ndarray, pos: np.ndarray) -> "_Blocks":
        n = len(rows)
        nb = -(-n // cls.SIZE)
        s = max(1, math.ceil(nb ** (1 / 3)))
        rank_x = np.empty(n, np.int64)
        rank_x[np.argsort(pos[:, 0], kind="stable")] = np.arange(n)
        slab_x = rank_x * s // n
        by_y = np.lexsort((pos[:, 1], slab_x))
        rank_y = np.empty(n, np.int64)
        rank_y[by_y] = np.arange(n)
        start = np.searchsorted(slab_x[by_y], slab_x)  # first sorted position of each row's x slab
        size = np.bincount(slab_x, minlength=s)[slab_x]
        slab_y = (rank_y - start) * s // np.maximum(size, 1)
        order = np.lexsort((pos[:, 2], slab_y, slab_x))
        p = np.ascontiguousarray(pos[order])
        edges = np.arange(0, n, cls.SIZE)
        return cls(rows[order], p, np.minimum.reduceat(p, edges, axis=0), np.maximum.reduceat(p, edges, axis=0))

    def nearest(self, q: np.ndarray) -> tuple[int, float]:
        """(snapshot row, squared distance) of the nearest object; ties: the lowest row."""
        gap = np.maximum(np.maximum(self.lo - q, q - self.hi), 0.0)
        bound = np.einsum("ij,ij->i", gap, gap)
        best_row, best = -1, np.inf
        for b in np.argsort(bound, kind="stable"):
            if bound[b] > best:
                break
            k = int(b) * self.SIZE
            d = self.position[k:k + self.SIZE] - q
            d2 = np.einsum("ij,ij->i", d, d)
            m = float(d2.min())
            if m > best:
                continue
            cand = k + np.flatnonzero(d2 == m)
            row = int(self.rows[cand].min())  # ties: the lowest row (= the lowest object id)
            if m < best or row < best_row:
                best_row, best = row, m
        return best_row, best


@dataclass(frozen=True)
class _Graph:
    """The map's nodes (not merged keyframes) and their adjacency, for paths."""
    ids: np.ndarray  # (M,) int64 ascending
    position: np.ndarray  # (M, 3)
    neighbours: list[list[int]]  # per node row: rows of the nodes it links to (both directions)

    @classmethod
    def from_store(cls, store) -> "_Graph":
        nodes = store.nodes(limit=None, merged=False)
        ids = np.array([n.id for n in nodes], np.int64)
        pos = np.array([n.pose[:3, 3] for n in nodes], np.float64).reshape(-1, 3)
        order = np.argsort(ids)
        ids, pos = ids[order], pos[order]
        pairs = np.asarray(store.link_pairs(), np.int64).reshape(-1, 2)
        neighbours: list[list[int]] = [[] for _ in range(len(ids))]
        if len(pairs) and len(ids):
            a, b = np.searchsorted(ids, pairs[:, 0]), np.searchsorted(ids, pairs[:, 1])
            a_ok = (a < len(ids)) & (ids[np.minimum(a, len(ids) - 1)] == pairs[:, 0])
            b_ok = (b < len(ids)) & (ids[np.minimum(b, len(ids) - 1)] == pairs[:, 1])
            for i, j in zip(a[a_ok & b_ok].tolist(), b[a_ok & b_ok].tolist()):
                neighbours[i].append(j)
                neighbours[j].append(i)
        return cls(ids, pos, neighbours)

    def row_of(self, node_id: int) -> int | None:
        i = int(np.searchsorted(self.ids, node_id))
        return i if i < len(self.ids) and self.ids[i] == node_id else None

    def distances_from(self, start: int) -> tuple[np.ndarray, np.ndarray]:
        """Dijkstra from row `start`, edge length = distance between the node positions:
        (distance per row, inf = unreachable; predecessor row, -1 = none)."""
        dist = np.full(len(self.ids), np.inf)
        prev = np.full(len(self.ids), -1, np.int64)
        dist[start] = 0.0
        heap = [(0.0, start)]
        pos = self.position
        while heap:
            d, i = heapq.heappop(heap)
            if d > dist[i]:
                continue
            for j in self.neighbours[i]:
                nd = d + float(np.sqrt(((pos[i] - pos[j]) ** 2).sum()))
                if nd < dist[j]:
                    dist[j], prev[j] = nd, i
                    heapq.heappush(heap, (nd, j))
        return dist, prev


_EMPTY = {"id": np.zeros(0, np.int64), "class_id": np.zeros(0, np.int64), "labels": np.zeros(0, object),
          "position": np.zeros((0, 3)), "extent": np.zeros((0, 3)), "confidence": np.zeros(0),
          "observations": np.zeros(0, np.int64), "node_id": np.zeros(0, np.int64)}


def data_version_of(path) -> Callable[[], int]:
    """A cheap change counter of the SQLite file at `path`: `PRAGMA data_version` on a
    private read-only connection (it changes whenever another connection or process commits)."""
    conn = sqlite3.connect(f"{Path(path).resolve().as_uri()}?mode=ro", uri=True, check_same_thread=False)
    lock = threading.Lock()

    def version() -> int:
        with lock:
            return conn.execute("PRAGMA data_version").fetchone()[0]

    version.close = conn.close  # type: ignore[attr-defined]
    return version


class ObjectIndex:
    """The map's objects for queries (see the module docstring). `store` provides
    `object_arrays()` (and, for paths, `nodes()` / `link_pairs()` / `get_node()`); `version`
    is a change counter of it (default: `PRAGMA data_version` of `store.path`, or none: then
    only `refresh()` rebuilds). Thread-safe."""

    def __init__(self, store, *, version: Callable[[], object] | None = None, check_interval: float = 0.05,
                 min_rebuild_interval: float = 0.5):
        self.store = store
        if version is None and getattr(store, "path", None) is not None:
            try:
                version = data_version_of(store.path)
            except sqlite3.Error as e:  # noqa: PERF203
                log.warning("object index: no change counter for %s (%s); refresh() only", store.path, e)
        self._version = version
        self.check_interval = check_interval
        self.min_rebuild_interval = min_rebuild_interval
        self._snap: _Snapshot | None = None
        self._graph: tuple[object, _Graph, float] | None = None  # (version it was built at, graph, when)
        # which anchors share a frame with a robot's keyframe (None: a store without links_after)
        self._links = MapConnectivity() if hasattr(store, "links_after") else None
        self._links_lock = threading.Lock()
        self._map_of_root: dict[int, int | None] = {}  # a component's root node -> its session's map id (fixed)
        self._build_lock = threading.Lock()
        self._state_lock = threading.Lock()
        self._last_check = 0.0
        self._seen_version: object = None
        self._rebuilding = False
        self.rebuilds = 0

    @property
    def ready(self) -> bool:
        """Built at least once: queries answer without reading the store."""
        return self._snap is not None

    # -- freshness ----------------------------------------------------------------------
    def _current_version(self):
        try:
            return self._version() if self._version is not None else None
        except sqlite3.Error:
            return None

    def refresh(self) -> None:
        """Rebuild the snapshot from the store now (blocking)."""
        with self._build_lock:
            self._rebuild()

    def _rebuild(self) -> None:
        v = self._current_version()
        if not hasattr(self.store, "object_arrays"):  # a store without objects: an empty map of them
            arrays = _EMPTY
        else:
            try:
                arrays = self.store.object_arrays()
            except Exception as e:  # the store is closed
                raise Unavailable(f"cannot read the map's objects: {e}") from e
        self._snap = _Snapshot.from_arrays(arrays, v, self._roots if self._links is not None else None)
        with self._state_lock:
            self._seen_version = v
            self.rebuilds += 1
        log.debug("object index rebuilt: %d objects in %.0f ms", len(self._snap.ids), self._snap.build_s * 1e3)

    def _background_refresh(self) -> None:
        try:
            self.refresh()
        except Exception as e:
            log.warning("object index refresh failed: %s", e)
        finally:
            with self._state_lock:
                self._rebuilding = False

    def snapshot(self) -> _Snapshot:
        snap = self._snap
        if snap is None:
            with self._build_lock:  # the first query builds it; concurrent ones wait for that build
                if self._snap is None:
                    self._rebuild()
            return self._snap
        now = time.monotonic()
        if self._version is None or now - self._last_check < self.check_interval:
            return snap
        with self._state_lock:
            if self._rebuilding or now - self._last_check < self.check_interval:
                return snap
            self._last_check = now
        v = self._current_version()
        with self._state_lock:
            if v == self._seen_version or self._rebuilding or now - snap.built_at < self.min_rebuild_interval:
                return snap
            self._rebuilding = True
        threading.Thread(target=self._background_refresh, name="object-index", daemon=True).start()
        return snap

    # -- frames ---------------------------------------------------------------------------
    def _roots(self, nodes: np.ndarray) -> np.ndarray:
        """The current component of each node (after reading the links stored since the last look)."""
        with self._links_lock:
            self._links.refresh(self.store)
            return self._links.roots(nodes)

    def maps(self, nodes) -> list[int | None] | None:
        """For each keyframe, the map id of the oldest session that links join it to (after
        reading the links stored since the last look): keyframes with the same one share a
        frame, and a robot's keyframe shows which map it is localized in (its own session's
        until a link places it in an older one). None when the store has no links view; None
        for a node not in the map."""
        if self._links is None:
            return None
        roots = self._roots(np.asarray(nodes, np.int64)).tolist()  # a component's root is its oldest node
        new = set(roots) - self._map_of_root.keys()  # (a root's map never changes: read each once)
        if new:
            session = {n.id: n.session_id for n in self.store.get_nodes(new)}
            map_id = {s.id: s.map_id for s in self.store.sessions()}
            self._map_of_root.update({r: map_id.get(session.get(r)) for r in new})
        return [self._map_of_root[r] for r in roots]

    def _joined(self, snap: _Snapshot, rows: np.ndarray, node_id: int | None,
                label: str | None = None) -> np.ndarray | None:
        """Mask of `rows` (all of `label`'s when given) whose anchors a chain of links joins to
        keyframe `node_id` (positions in one frame), or None when every row qualifies (no node,
        or no links to tell)."""
        if node_id is None or snap.root is None:
            return None
        u, inv = snap.label_roots[label] if label is not None else np.unique(snap.root[rows], return_inverse=True)
        with self._links_lock:
            if not self._links.knows(node_id):  # a keyframe newer than the last look
                self._links.refresh(self.store)
            root = self._links.find(int(node_id))
            now = self._links.roots(u)  # components only merge: re-find the snapshot's roots
        same = now == root
        return None if same.all() else same[inv].reshape(-1)

    def close(self) -> None:
        close = getattr(self._version, "close", None)
        if close is not None:
            close()

    # -- queries --------------------------------------------------------------------------
    def count(self) -> int:
        return len(self.snapshot().ids)

    def labels(self) -> list[tuple[str, int]]:
        """(label, objects with it), most frequent first (then by name)."""
        snap = self.snapshot()
        return sorted(((k, len(v)) for k, v in snap.by_label.items()), key=lambda kv: (-kv[1], kv[0]))

    def get(self, object_id: int) -> ObjectView:
        snap = self.snapshot()
        row = snap.row_of(int(object_id))
        if row is None:
            raise NotFound(f"no object {object_id}")
        return snap.view(row)

    def nearest(self, label: str, point, joined_to: int | None = None) -> Nearest:
        """The object labelled `label` nearest to `point` (ties: the lowest id); with
        `joined_to` (a robot's keyframe), only among objects whose anchors links join to that
        keyframe: a robot not yet placed in the map is in a frame of its own."""
        p = _finite_point(point)
        snap = self.snapshot()
        rows = snap.by_label.get(label)
        if rows is None:
            if not len(snap.ids):
                raise NotFound("the map has no objects")
            known = ", ".join(k for k, _ in self.labels()[:10])
            raise NotFound(f"no object labelled {label!r} in the map (labels: {known})")
        joined = self._joined(snap, rows, joined_to, label)
        if joined is not None and not joined.any():
            raise NotFound(f"no object labelled {label!r} in the robot's part of the map: no link joins its "
                           f"keyframe {joined_to} to the {len(rows)} such object(s) yet "
                           "(it is not localized in the map)")
        blocks = snap.label_blocks.get(label)
        if blocks is not None and joined is None:
            row, best = blocks.nearest(p)
        else:
            d = snap.label_positions[label] - p
            d2 = np.einsum("ij,ij->i", d, d)
            if joined is not None:
                d2[~joined] = np.inf
            i = int(np.argmin(d2))
            row, best = int(rows[i]), float(d2[i])
        return Nearest(snap.view(row), float(math.sqrt(best)), int(snap.node_id[row]))

    def find(self, label: str | None = None, point=None, radius: float | None = None,
             limit: int = 100, offset: int = 0) -> Page:
        """Objects with `label` (any when None) within `radius` m of `point` (anywhere when no
        radius); ordered by distance to `point` when given, else by id; objects[offset:offset+limit]."""
        if radius is not None and point is None:
            raise QueryError("radius needs a point (x, y, z)")
        if radius is not None and not (math.isfinite(radius) and radius >= 0):
            raise QueryError(f"radius must be a finite number >= 0, got {radius!r}")
        if limit < 0 or offset < 0:
            raise QueryError("limit and offset must be >= 0")
        snap = self.snapshot()
        if label is None:
            rows, pos = np.arange(len(snap.ids)), snap.position
        else:
            rows = snap.by_label.get(label, np.zeros(0, np.int64))
            pos = snap.label_positions.get(label, np.zeros((0, 3)))
        if point is not None:
            p = _finite_point(point)
            d = pos - p
            d2 = np.einsum("ij,ij->i", d, d)
            if radius is not None:
                keep = d2 <= radius * radius
                rows, d2 = rows[keep], d2[keep]
            total = len(rows)
            end = min(total, offset + limit)
            if offset >= total or limit == 0:
                return Page(total, [])
            if end < total:  # only the first `end` by distance need sorting
                part = np.argpartition(d2, end - 1)[:end]
                order = part[np.lexsort((rows[part], d2[part]))]
            else:
                order = np.lexsort((rows, d2))
            rows = rows[order[offset:end]]
        else:
            total = len(rows)
            offset = min(offset, total)
            rows = rows[offset:offset + min(limit, total)]
        return Page(total, [snap.view(int(r)) for r in rows])

    def delete(self, object_id: int) -> int:
        """Remove an object from the map (`store.delete_objects`); the index forgets it at once."""
        self.get(object_id)  # NotFound when it is not in the map
        n = self.store.delete_objects([int(object_id)])
        if not n:
            raise NotFound(f"no object {object_id}")
        self.refresh()
        return int(n)

    # -- paths ----------------------------------------------------------------------------
    def graph(self) -> _Graph:
        """The map's nodes and links; rebuilt when the store changed, at most every
        `min_rebuild_interval` s (a live map commits every keyframe)."""
        v = self._current_version()
        cached = self._graph
        if cached is not None and (v is None or cached[0] == v
                                   or time.monotonic() - cached[2] < self.min_rebuild_interval):
            return cached[1]
        g = _Graph.from_store(self.store)
        self._graph = (v, g, time.monotonic())
        return g

    def path(self, object_id: int, start: RobotLocation) -> GraphPath:
        """The shortest path along the pose graph's links (by length) from the robot's node
        (its latest keyframe, or the map node nearest its position) to the node nearest the
        object among those it reaches."""
        obj = self.get(object_id)
        g = self.graph()
        if not len(g.ids):
            raise NotFound("the map has no nodes")
        start_row = self._start_row(g, start)
        snap = self.snapshot()
        row = snap.row_of(obj.id)
        joined = None if row is None else self._joined(snap, np.array([row]), int(g.ids[start_row]))
        if joined is not None and not joined[0]:
            raise NotFound(f"object {obj.id} is in another part of the map: no link joins the robot's node "
                           f"{int(g.ids[start_row])} to its keyframe {obj.node_id} yet")
        dist, prev = g.distances_from(start_row)
        reach = np.flatnonzero(np.isfinite(dist))
        d = g.position[reach] - np.asarray(obj.position)
        d2 = np.einsum("ij,ij->i", d, d)
        goal = int(reach[int(np.argmin(d2))])
        rows = [goal]
        while rows[-1] != start_row:
            rows.append(int(prev[rows[-1]]))
        rows.reverse()
        return GraphPath(obj, int(g.ids[start_row]), int(g.ids[goal]), [int(g.ids[r]) for r in rows],
                         [tuple(float(v) for v in g.position[r]) for r in rows], float(dist[goal]),
                         float(math.sqrt(float(d2.min()))))

    def _start_row(self, g: _Graph, start: RobotLocation) -> int:
        if start.node_id is not None:
            row = g.row_of(start.node_id)
            if row is None and hasattr(self.store, "get_node"):  # merged by rehearsal: its survivor
                n = self.store.get_node(start.node_id)
                if n is not None and n.merged_into is not None:
                    row = g.row_of(n.merged_into)
            if row is not None:
                return row
        d = g.position - np.asarray(start.position)
        return int(np.argmin(np.einsum("ij,ij->i", d, d)))


def robot_location(robots: Iterable[dict], robot: str, store=None) -> RobotLocation:
    """Where `robot` is: its last tracked pose and latest keyframe from the service's robot
    status (`SlamService.robots()`: "position" / "pose" and "node_id" when reported), else its
    session's latest keyframe in the map. NotFound when the robot is unknown or has no pose."""
    r = next((r for r in robots if r.get("robot") == robot), None)
    if r is None:
        raise NotFound(f"unknown robot {robot!r} (not connected to the service)")
    node_id = r.get("node_id")
    pos = r.get("position")
    if pos is None and r.get("pose") is not None:
        pose = np.asarray(r["pose"], np.float64).reshape(-1)
        if pose.size == 16:
            pos = pose.reshape(4, 4)[:3, 3]
        elif pose.size >= 3:
            pos = pose[:3]
    if pos is not None and np.isfinite(np.asarray(pos, np.float64)).all():
        return RobotLocation(robot, tuple(float(v) for v in pos), None if node_id is None else int(node_id), "tracking")
    sid = r.get("session_id")
    if sid is not None and store is not None:
        n = store.count_nodes(session_id=sid, merged=False)
        if n:
            last = store.nodes(session_id=sid, limit=1, offset=n - 1, merged=False)[0]
            return RobotLocation(robot, tuple(float(v) for v in last.pose[:3, 3]), int(last.id), "keyframe")
    raise NotFound(f"robot {robot!r} has no pose yet (no tracked frame or keyframe)")

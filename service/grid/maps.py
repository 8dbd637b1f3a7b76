"""One occupancy grid per map of the store (`MapGrids`), kept up to date on demand.

A map is a connected part of the pose graph, named by the map id of its oldest session (as
`GET /robots/{id}` names the map a robot is in; storage.connectivity). Each call of `grid`
reads every node's current pose (one query), the links stored since the last call, and
brings that map's `GlobalGrid` to its keyframes: new ones are added, those that moved are
re-placed, those gone (another map joined, a node deleted) taken out. The local grids come
from the store once per node (kept encoded); a keyframe of an older database without one gets
it from its stored depth the first time (then stored).
"""
from __future__ import annotations

import logging
import threading
import time

import numpy as np

from mnemoslam.storage import GridStore
from mnemoslam.storage.connectivity import MapConnectivity

from ..config import GridConfig
from .assembly import GlobalGrid, GridImage
from .local import LocalGridMaker, StoredLocalGrid

log = logging.getLogger("mnemoslam.grid")


class NoMap(LookupError):
    """No such map, or a map without any local grid (the reason is the message)."""


class MapGrids:
    """The store's maps' occupancy grids."""

    def __init__(self, store: GridStore, config: GridConfig):
        self.store, self.config = store, config
        self._lock = threading.Lock()
        self._links = MapConnectivity()
        self._grids: dict[int, GlobalGrid] = {}
        self._local: dict[int, StoredLocalGrid] = {}
        self._map_of_root: dict[int, int | None] = {}
        self._no_grid: set[int] = set()  # nodes that have no grid and cannot get one (no depth)
        self._known_ids: tuple[np.ndarray, np.ndarray] | None = None
        self._roots: tuple | None = None  # (node ids, their parts' roots, their map ids) at the last look
        self.last_update: dict = {}

    def maps(self) -> dict[int, np.ndarray]:
        """{map id: its node ids ascending}, and refreshes the node poses (see `grid`)."""
        with self._lock:
            return {m: ids for m, (ids, _) in self._partition().items()}

    def _partition(self) -> dict[int, tuple[np.ndarray, np.ndarray]]:
        nodes = self.store.grid_nodes(has_grid=False)
        read = self._links.refresh(self.store)
        ids = nodes["id"]
        if len(ids) == 0:
            return {}
        cached = self._roots
        if read == 0 and cached is not None and np.array_equal(cached[0], ids):
            roots, maps = cached[1], cached[2]  # no new link, the same nodes: the same parts (~30 ms at 20k)
        else:
            roots = self._links.roots(ids)
            new = set(roots.tolist()) - self._map_of_root.keys()
            if new:
                session = dict(zip(ids.tolist(), nodes["session_id"].tolist()))
                map_id = {s.id: s.map_id for s in self.store.sessions()}
                for r in new:  # (a root without a node row here, e.g. a merged keyframe: no map)
                    sid = session.get(r)
                    self._map_of_root[r] = None if sid is None else map_id.get(sid)
            maps = np.array([-1 if self._map_of_root[r] is None else self._map_of_root[r] for r in roots.tolist()],
                            np.int64)
            self._roots = (ids, roots, maps)
        out = {}
        for m in np.unique(maps).tolist():
            sel = maps == m
            # parts of one map id not joined (yet) by links (a session whose tracking was lost
            # restarts in a frame of its own) have no common frame: the largest part is the map
            r, counts = np.unique(roots[sel], return_counts=True)
            if len(r) > 1:
                sel &= roots == r[np.argmax(counts)]
            out[int(m)] = (ids[sel], nodes["pose"][sel])
        return out

    def grid(self, map_id: int) -> GridImage:
        """The map's grid at its cell size (grid.cell_size), brought up to date."""
        with self._lock:
            t0 = time.perf_counter()
            parts = self._partition()
            if map_id not in parts:
                raise NoMap(f"no map {map_id}" + (f" (maps: {', '.join(map(str, sorted(parts)))})" if parts else
                                                  " (the database has no keyframes)"))
            for gone in set(self._grids) - set(parts):  # joined into an older map
                del self._grids[gone]
            ids, poses = parts[map_id]
            self._load(ids)
            known, good = self._known()
            if not np.isin(ids, known, assume_unique=True).any():
                raise NoMap(f"map {map_id} has no local grids (no keyframe with depth: a stereo map, or "
                            "grid.enabled was false and storage.keep_images too)")
            g = self._grids.setdefault(map_id, GlobalGrid(self.config))
            stats = g.update(ids, poses, self._local, known=known, good=np.isin(ids, good, assume_unique=True))
            self.last_update = {**stats, "ms": (time.perf_counter() - t0) * 1e3, "keyframes": g.keyframes}
            return g.image()

    def keyframes(self, map_id: int) -> tuple[np.ndarray, np.ndarray]:
        """(node ids, their current poses) of a map (NoMap when there is no such map)."""
        with self._lock:
            parts = self._partition()
        if map_id not in parts:
            raise NoMap(f"no map {map_id}")
        return parts[map_id]

    def map_of(self, node_id: int) -> int | None:
        """The map a node is in (after the last look at the links; None for an unknown node)."""
        with self._lock:
            if self._links.refresh(self.store):
                self._roots = None  # parts may have joined: `_partition` finds them again
            root = self._links.find(int(node_id))
            if root not in self._map_of_root:
                nodes = self.store.get_nodes([root])
                if not nodes:
                    return None
                sessions = {s.id: s.map_id for s in self.store.sessions()}
                self._map_of_root[root] = sessions.get(nodes[0].session_id)
            return self._map_of_root[root]

    def global_grid(self, map_id: int) -> GlobalGrid:
        """The map's assembled grid (after `grid(map_id)`)."""
        return self._grids[map_id]

    def _known(self) -> tuple[np.ndarray, np.ndarray]:
        """(sorted ids of the nodes with a local grid, those whose up came from a floor or an
        accelerometer, not the configured mounting), kept until more grids are loaded."""
        if self._known_ids is None or len(self._known_ids[0]) != len(self._local):
            ids = np.array(sorted(self._local), np.int64)
            good = np.array([n for n in ids.tolist() if self._local[n].up_source != "config"],
                            np.int64)
            self._known_ids = (ids, good)
        return self._known_ids

    def _load(self, ids: np.ndarray) -> None:
        known = self._known()[0] if self._local else np.zeros(0, np.int64)
        cand = ids[~np.isin(ids, known, assume_unique=True)]
        need = [n for n in cand.tolist() if n not in self._no_grid]
        if not need:
            return
        for i in range(0, len(need), 5000):
            for n, rec in self.store.local_grids(need[i:i + 5000]).items():
                self._local[n] = StoredLocalGrid(rec)
        missing = [n for n in need if n not in self._local]
        if missing:
            made = self._backfill(missing)
            self._no_grid.update(set(missing) - made)

    def _backfill(self, node_ids: list[int]) -> set[int]:
        """Make and store the local grids of keyframes stored without one (an older database)
        from their stored depth; returns the nodes that got one."""
        from mnemoslam.storage import LocalGridRecord

        from ..memory.keyframes import decode_images

        todo = set(self.store.nodes_without_grid(node_ids))
        if not todo:
            return set()
        t0 = time.perf_counter()
        makers: dict[int, LocalGridMaker] = {}
        sessions = {n.id: n.session_id for n in self.store.get_nodes(sorted(todo))}
        made, records = set(), []
        for n in sorted(todo):
            sid = sessions.get(n)
            if sid is None:
                continue
            if sid not in makers:
                makers[sid] = LocalGridMaker(self.store.calibration(sid).camera, self.config)
            _, depth = decode_images(None, self.store.load_images(n)[1])
            g = makers[sid].make(depth) if depth is not None else None
            if g is None:
                continue
            rec = LocalGridRecord(n, g.cell_size, g.T_cam_local, g.origin_x, g.origin_y, g.encode_cells(),
                                  g.up_source, g.floor_points)
            records.append(rec)
            self._local[n] = StoredLocalGrid(rec)
            made.add(n)
        if not getattr(self.store, "readonly", False):  # (a localization-only service's map is read-only: RAM only)
            self.store.save_local_grids(records)
        log.info("made the local grids of %d stored keyframes in %.1f s", len(made), time.perf_counter() - t0)
        return made


class GridHolder:
    """One MapGrids per open store of the service (a restarted service gets a new one)."""

    def __init__(self, config: GridConfig):
        self.config = config
        self._lock = threading.Lock()
        self._store: GridStore | None = None
        self._grids: MapGrids | None = None

    def get(self, store: GridStore) -> MapGrids:
        with self._lock:
            if self._grids is None or self._store is not store:
                self._store, self._grids = store, MapGrids(store, self.config)
            return self._grids

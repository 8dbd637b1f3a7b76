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
from mnemoslam.storage.connection import ChangeCounter
from mnemoslam.storage.connectivity import MapConnectivity

from ..config import GridConfig
from .assembly import GlobalGrid, GridImage
from .cloud import CloudCache
from .local import LocalGridMaker, StoredLocalGrid

log = logging.getLogger("mnemoslam.grid")


#: s; a map not asked for this long is no longer kept up to date in the background
IDLE_AFTER = 60.0
#: local grids to place or take out above which a request does not wait for the pass (~0.1 s of it)
HEAVY = 1000


class NoMap(LookupError):
    """No such map, or a map without any local grid (the reason is the message)."""


class MapGrids:
    """The store's maps' occupancy grids."""

    def __init__(self, store: GridStore, config: GridConfig):
        self.store, self.config = store, config
        self._lock = threading.Lock()  # the store reads, the links, the local grids
        self._assembly = threading.Lock()  # the GlobalGrids' updates (seconds after a loop closure)
        self._links = MapConnectivity()
        self._grids: dict[int, GlobalGrid] = {}
        self._local: dict[int, StoredLocalGrid] = {}
        self._map_of_root: dict[int, int | None] = {}
        self._no_grid: set[int] = set()  # nodes that have no grid and cannot get one (no depth)
        self._known_ids: tuple[np.ndarray, np.ndarray] | None = None
        self._roots: tuple | None = None  # (node ids, their parts' roots, their map ids) at the last look
        self.last_update: dict = {}
        # the store's change counter (PRAGMA data_version); False: none to be had
        self._counter: ChangeCounter | bool | None = None
        self._counted: dict[int, int] = {}  # map id -> the change counter when its grid was last brought up to date
        self.clouds = CloudCache(max(0, config.cloud_cache_mb) * 2 ** 20)  # GET /maps/{map}/cloud's
        # the background assembler (`latest`): maps asked for, their last grid, the passes
        self._cond = threading.Condition()
        self._asked: dict[int, float] = {}  # map id -> monotonic time of its last request
        self._published: dict[int, GridImage] = {}
        self._failed: dict[int, Exception] = {}
        self._started = self._finished = 0  # background passes begun / ended
        self._wake = self._closed = self._heavy = False
        self._thread: threading.Thread | None = None

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
        """The map's grid at its cell size (grid.cell_size), brought up to date now (the caller
        waits for it: seconds after a loop closure moved a large map; see `latest`)."""
        with self._assembly, self._lock:
            t0 = time.perf_counter()
            version = self._version()
            if version is not None and self._counted.get(map_id) == version and map_id in self._grids:
                # nothing committed to the file since: the same grid (no pose read, ~1 ms)
                g = self._grids[map_id]
                self.last_update = {"added": 0, "moved": 0, "removed": 0, "rebuilt": False, "unchanged": True,
                                    "ms": (time.perf_counter() - t0) * 1e3, "keyframes": g.keyframes}
                return g.image()
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
            self._lock.release()  # the store and the links free for others while it places
            try:
                stats = g.update(ids, poses, self._local, known=known, good=np.isin(ids, good, assume_unique=True),
                                 on_plan=self._on_plan)
            finally:
                self._lock.acquire()
            self.last_update = {**stats, "ms": (time.perf_counter() - t0) * 1e3, "keyframes": g.keyframes}
            if version is not None:
                self._counted[map_id] = version
            return g.image()

    def _version(self) -> int | None:
        """The store file's change counter (None without one: an in-memory store)."""
        if self._counter is None:
            try:
                self._counter = self.store.change_counter()
            except Exception:  # (no file to count the changes of)
                self._counter = False
        if not isinstance(self._counter, ChangeCounter):
            return None
        try:
            return self._counter()
        except Exception:
            return None

    # -- the background assembler -------------------------------------------------------------------
    def latest(self, map_id: int, max_wait: float | None = None) -> tuple[GridImage, bool]:
        """(the map's grid, whether it is up to date) without making the caller pay a large
        re-assembly: with `grid.refresh_interval` > 0 a thread keeps the grids of the maps asked
        for (within the last IDLE_AFTER s) up to date, a pass every refresh_interval s and one
        at each request; the request waits at most `max_wait` s (grid.max_wait) for the pass
        it started, then gets the last grid assembled (False: a loop closure's re-placing is
        still going on). The first request of a map waits for its first assembly. Without
        the thread (refresh_interval 0) this is `grid`."""
        if self.config.refresh_interval <= 0:
            return self.grid(map_id), True
        wait = self.config.max_wait if max_wait is None else float(max_wait)
        with self._cond:
            if self._closed:
                raise NoMap("the service is stopping")
            self._asked[map_id] = time.monotonic()
            want = self._started + 1  # a pass begun after this request
            self._wake = True
            self._cond.notify_all()
            if self._thread is None:
                self._thread = threading.Thread(target=self._run, name="grid-assembly", daemon=True)
                self._thread.start()
            deadline = time.monotonic() + wait
            while self._finished < want and not self._closed:
                left = deadline - time.monotonic()
                if (left <= 0 or self._heavy) and (map_id in self._published or map_id in self._failed):
                    break  # (a pass placing many keyframes: not worth waiting max_wait for)
                self._cond.wait(left if left > 0 else None)
            current = self._finished >= want
            if map_id in self._failed:
                raise self._failed[map_id]
            if map_id not in self._published:
                raise NoMap("the service is stopping")
            return self._published[map_id], current

    def _on_plan(self, n: int) -> None:
        """The update about to place or take out `n` local grids: more than HEAVY and the
        requests waiting for the thread's pass get the last grid at once."""
        if threading.current_thread() is self._thread:
            with self._cond:
                self._heavy = n > HEAVY
                if self._heavy:
                    self._cond.notify_all()

    def published(self, map_id: int) -> GridImage | None:
        """The map's grid last assembled by the background thread (None before the first)."""
        with self._cond:
            return self._published.get(map_id)

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._wake and not self._closed:
                    recent = any(time.monotonic() - t < IDLE_AFTER for t in self._asked.values())
                    if not self._cond.wait(self.config.refresh_interval) and recent:
                        break  # a periodic pass while a planner asks
                if self._closed:
                    return
                self._wake = False
                self._started += 1
                npass, now = self._started, time.monotonic()
                maps = [m for m, t in self._asked.items() if now - t < IDLE_AFTER]
            done: dict[int, GridImage | Exception] = {}
            for m in maps:
                try:
                    done[m] = self.grid(m)
                except NoMap as e:
                    done[m] = e
                except Exception as e:  # pragma: no cover - a bug: the requests see it, the thread lives on
                    log.exception("assembling the grid of map %d", m)
                    done[m] = e
            with self._cond:
                self._heavy = False
                for m, r in done.items():
                    if isinstance(r, Exception):
                        self._failed[m] = r
                        self._published.pop(m, None)
                    else:
                        self._published[m] = r
                        self._failed.pop(m, None)
                self._finished = npass
                self._cond.notify_all()

    def close(self) -> None:
        """End the background thread (a pass under way finishes first)."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()
            t = self._thread
        if t is not None and t is not threading.current_thread():
            t.join(timeout=30)
        with self._assembly:
            if isinstance(self._counter, ChangeCounter):
                self._counter.close()
            self._counter = False

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
                if self._grids is not None:
                    self._grids.close()
                self._store, self._grids = store, MapGrids(store, self.config)
            return self._grids

    def close(self) -> None:
        with self._lock:
            if self._grids is not None:
                self._grids.close()

"""The live web viewer (GET /viewer, service/api/routes/viewer.py): one static page
(service/static/viewer.html: canvas 2D, vanilla JS, no build step) and its live feed, GET
/viewer/events, a server-sent event stream of compact JSON updates built here.

Each client (each event stream) has its own `ViewerFeed`, which remembers what it sent, so an
update carries only what changed since the previous one:

    {"seq": 0, "t": unix time, "reset": true on a stream's first update (or a new store),
     "robots": [{"robot", "state", "session_id", "position", "node_id", "keyframes",
                 "frames_processed", "fps", "map_backlog"}],          # every update
     "sessions": [{"id", "robot", "map_id", "live",                   # the sessions that changed
                   "nodes": the session's map nodes (not merged),
                   "full": true: "points" is the whole trajectory (decimated to
                           `Limits.max_points`) and "links" every shown link (the newest
                           `Limits.max_links`); false: "points" are new nodes to append, no links,
                   "points": [x, y, z, x, y, z, ...] (m, map frame, by node id),
                   "links": [[type, x1, y1, z1, x2, y2, z2], ...] (type named by storage.LINK_NAMES:
                             loop, proximity, ...),
                   "memory": {"stm", "wm", "ltm", "words"} after the latest map update,
                   "frame": the map id of the oldest session links join it to (its own until a
                            link places it in another's frame; when it changed)}],
     "objects": {"total", "items": [{"id", "label", "confidence", "position", "extent",
                                     "observations"}], "labels": [[label, count], ...]}
                 (only when the object index changed; the first `Limits.max_objects` by id),
     "coverage": {"keyframes", "segmented", "skipped"} of the semantic map (when it changed)}

Trajectories are sent whole (decimated) on a stream's first update, then each live session
gets its new nodes appended, and its whole trajectory again when its loop / proximity links
changed (a loop closure corrects old poses) or every `Limits.full_every` seconds (the map
update also moves poses without new links). Ended sessions are sent once, and again only when
their nodes or links changed, or they share a map with a live session (its corrections can
move them). So a map of thousands of nodes costs a few new points per update, and a full
trajectory of at most `max_points` points now and then.

The stream ends when the client goes away, when the server shuts down (`Viewer.close`,
called by `service.api.ApiServer` before uvicorn waits for open responses) or the service
stops, and after `max_age` seconds in any case (the browser's EventSource reconnects and gets
a fresh full update): a server that never calls `close` still shuts down in bounded time.
"""
from __future__ import annotations

import asyncio
import json
import logging
import math
import time
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from fastapi.concurrency import run_in_threadpool

from mnemoslam.storage import LinkType, StoreError

from .semantics.queries import QueryError, Unavailable

log = logging.getLogger("mnemoslam.viewer")

PAGE = Path(__file__).resolve().with_name("static") / "viewer.html"

# the link types drawn, sent by their `label` (storage.LINK_NAMES, as GET /graph names them):
# odometry links are the trajectory's polyline, and path links (between keyframes close in time
# along the own path, hundreds per loop) would only hide it
LINKS = (LinkType.GLOBAL_CLOSURE, LinkType.LOCAL_SPACE, LinkType.USER, LinkType.VIRTUAL, LinkType.MERGED)
ROBOT_KEYS = ("robot", "state", "session_id", "position", "node_id", "keyframes", "frames_processed", "fps",
              "map_backlog")


@dataclass(frozen=True)
class Limits:
    """What one update may carry."""

    max_points: int = 2000  # points of a full trajectory (decimated evenly beyond, the last node kept)
    max_links: int = 2000  # links of a session (its newest)
    max_objects: int = 500  # objects listed (the first by id; "total" says how many there are)
    max_sessions: int = 16  # sessions shown: the live ones and the latest others
    full_every: float = 5.0  # s: a live session's whole trajectory again


@dataclass
class _Sent:
    """What a feed has sent of one session."""

    last_id: int = 0  # its newest node sent
    nodes: int = 0
    links: int = -1  # shown links counted at its last full update
    full_at: float = -math.inf  # monotonic time of its last full update
    live: bool | None = None
    memory_after: int = 0  # the map updates read so far (node id)
    memory: dict | None = None
    first_id: int | None = None  # its first keyframe (merged or not): its frame's representative
    frame: int | None = None  # the frame (map id) last sent


def _xyz(rows: np.ndarray) -> list[float]:
    """(N, 3) positions as a flat list rounded to the millimetre, non-finite rows left out."""
    rows = rows[np.isfinite(rows).all(axis=1)]
    return np.round(rows, 3).reshape(-1).tolist()


def decimate(n: int, keep: int) -> np.ndarray:
    """Indices of `keep` of n items spread evenly, first and last included (all when n <= keep)."""
    if n <= keep:
        return np.arange(n)
    return np.unique(np.linspace(0, n - 1, max(keep, 2)).round().astype(np.int64))


class ViewerFeed:
    """One client's updates (see the module docstring). `objects(store)` gives the app's
    object index (service.semantics.queries.ObjectIndex) or None. `next()` reads the service
    and its store: call it off the event loop."""

    def __init__(self, service, objects: Callable | None = None, limits: Limits = Limits(),
                 clock: Callable[[], float] = time.monotonic):
        self.service, self.objects, self.limits, self.clock = service, objects, limits, clock
        self.seq = 0
        self._store = None
        self._sent: dict[int, _Sent] = {}
        self._sessions: list = []  # the sessions shown (SessionRecord)
        self._listed_at = -math.inf
        self._objects_snapshot = None
        self._coverage: dict | None = None  # the semantic coverage last sent

    def next(self) -> dict | None:
        """The next update; None when the service has stopped (no store)."""
        store = self.service.store
        if store is None:
            return None
        now = self.clock()
        reset = self.seq == 0 or store is not self._store
        if store is not self._store:
            self._store, self._sent, self._listed_at, self._objects_snapshot = store, {}, -math.inf, None
            self._coverage = None
        robots = [{k: r.get(k) for k in ROBOT_KEYS} for r in self.service.robots()]
        live = {r["session_id"] for r in robots if isinstance(r["session_id"], int)}
        out = {"seq": self.seq, "t": time.time(), "reset": reset, "robots": robots,
               "sessions": self._session_updates(store, live, now)}
        objects = self._object_update(store)
        if objects is not None:
            out["objects"] = objects
        coverage = self._coverage_update(store)
        if coverage is not None:
            out["coverage"] = coverage
        self.seq += 1
        return out

    # -- sessions -----------------------------------------------------------------------------
    def _shown(self, store, live: set[int], now: float) -> list:
        known = {s.id for s in self._sessions}
        if live - known or now - self._listed_at >= self.limits.full_every:
            sessions = store.sessions()
            keep = {s.id for s in sessions if s.id in live}
            keep |= {s.id for s in sorted(sessions, key=lambda s: s.id)[-self.limits.max_sessions:]}
            self._sessions = [s for s in sessions if s.id in keep]
            self._listed_at = now
        return self._sessions

    def _session_updates(self, store, live: set[int], now: float) -> list[dict]:
        out = []
        sessions = self._shown(store, live, now)
        live_maps = {s.map_id for s in sessions if s.id in live}
        frames = self._frames(store, sessions)
        for s in sessions:
            sent = self._sent.setdefault(s.id, _Sent())
            is_live = s.id in live
            entry = self._trajectory_update(store, s, sent, is_live, s.map_id in live_maps, now)
            memory = self._memory_update(store, s.id, sent, is_live)
            frame = frames.get(s.id)
            if memory is not None or sent.live != is_live or (frame is not None and frame != sent.frame):
                entry = entry or {}
                if memory is not None:
                    entry["memory"] = memory
                if frame is not None and frame != sent.frame:
                    entry["frame"] = sent.frame = frame
            if entry is not None:
                out.append({"id": s.id, "robot": s.robot, "map_id": s.map_id, "live": is_live, **entry})
            sent.live = is_live
        return out

    def _frames(self, store, sessions) -> dict[int, int]:
        """{session id: the map id of the oldest session that links join it to}: sessions with
        the same one share coordinates (ObjectIndex.maps, storage.connectivity)."""
        if self.objects is None:
            return {}
        firsts = {}
        for s in sessions:
            sent = self._sent.setdefault(s.id, _Sent())
            if sent.first_id is None:
                first = store.nodes(session_id=s.id, limit=1, merged=None)
                sent.first_id = first[0].id if first else None
            if sent.first_id is not None:
                firsts[s.id] = sent.first_id
        if not firsts:
            return {}
        try:
            maps = self.objects(store).maps(list(firsts.values()))
        except (Unavailable, QueryError) as e:
            log.debug("viewer: frames not read: %s", e)
            return {}
        return {} if maps is None else {sid: m for sid, m in zip(firsts, maps) if m is not None}

    def _trajectory_update(self, store, s, sent: _Sent, is_live: bool, map_is_live: bool, now: float) -> dict | None:
        due = now - sent.full_at >= self.limits.full_every
        if not (is_live or due):
            return None
        links = sum(store.count_links(LINKS, session_id=s.id).values())
        full = sent.full_at == -math.inf or links != sent.links
        if not full and due:
            # a live session's poses move with the map update; an ended one's only when its map is live
            full = is_live or map_is_live or store.count_nodes(session_id=s.id, merged=False) != sent.nodes
        if full:
            rows = store.node_positions(s.id)
            keep = decimate(len(rows), self.limits.max_points)
            segments = store.link_segments(LINKS, s.id, limit=self.limits.max_links)
            sent.nodes, sent.links, sent.full_at = len(rows), links, now
            sent.last_id = int(rows[-1, 0]) if len(rows) else 0
            return {"full": True, "nodes": len(rows), "points": _xyz(rows[keep, 1:4]),
                    "links": [[LinkType(t).label, *np.round(np.array(p, float), 3).tolist()]
                              for _, _, t, *p in segments if all(v is not None and math.isfinite(v) for v in p)]}
        if not is_live:
            if due:
                sent.full_at = now  # checked: nothing changed
            return None
        rows = store.node_positions(s.id, sent.last_id)
        if not len(rows):
            return None
        sent.nodes += len(rows)
        sent.last_id = int(rows[-1, 0])
        return {"full": False, "nodes": sent.nodes, "points": _xyz(rows[:, 1:4])}

    def _memory_update(self, store, session_id: int, sent: _Sent, is_live: bool) -> dict | None:
        """STM / WM / LTM sizes and vocabulary words after the session's latest map update, when
        they changed (as GET /metrics reads them: the map update's statistics rows)."""
        if not is_live and sent.live is not None:
            return None
        latest = None
        for node, _ms, stm, wm, ltm, words in store.map_updates(session_id, sent.memory_after):
            sent.memory_after = max(sent.memory_after, node)
            if wm is not None:
                latest = {"stm": stm, "wm": wm, "ltm": ltm, "words": words}
        if latest is None or latest == sent.memory:
            return None
        sent.memory = latest
        return latest

    # -- objects ------------------------------------------------------------------------------
    def _coverage_update(self, store) -> dict | None:
        """The semantic map's coverage ({"keyframes", "segmented", "skipped"}) when it changed."""
        if self.objects is None:
            return None
        try:
            c = store.segmentation_coverage()
        except StoreError as e:
            log.debug("viewer: coverage not read: %s", e)
            return None
        if c == self._coverage:
            return None
        self._coverage = c
        return c

    def _object_update(self, store) -> dict | None:
        if self.objects is None:
            return None
        try:
            index = self.objects(store)
            snapshot = index.snapshot()
            if snapshot is self._objects_snapshot:
                return None
            page = index.find(limit=self.limits.max_objects)
            labels = index.labels()
        except (Unavailable, QueryError) as e:
            log.debug("viewer: objects not read: %s", e)
            return None
        self._objects_snapshot = snapshot
        return {"total": page.total, "labels": [[k, n] for k, n in labels], "items": [
            {"id": o.id, "label": o.label, "confidence": round(float(o.confidence), 3),
             "position": [round(float(v), 3) for v in o.position], "extent": [round(float(v), 3) for v in o.extent],
             "observations": o.observations} for o in page.objects]}


class Viewer:
    """The viewer of one app: its page and its event streams (`events`), which `close` ends."""

    def __init__(self, service, objects: Callable | None = None, interval: float = 0.5, max_age: float = 600.0,
                 limits: Limits = Limits()):
        self.service, self.objects, self.interval = service, objects, interval
        self.max_age, self.limits = max_age, limits
        self.closed = False
        self._page: str | None = None

    def page(self) -> str:
        if self._page is None:
            self._page = PAGE.read_text(encoding="utf-8")
        return self._page

    def close(self) -> None:
        """End every event stream (the server is shutting down)."""
        self.closed = True

    def _stopping(self) -> bool:
        return self.closed or self.service.store is None

    async def events(self, is_disconnected: Callable) -> AsyncIterator[str]:
        """The event stream of one client: an update every `interval` s until it goes away
        (`await is_disconnected()`), the viewer closes, the service stops or `max_age` passes."""
        feed = ViewerFeed(self.service, self.objects, self.limits)
        started = time.monotonic()
        yield "retry: 2000\n\n"  # the browser reconnects after 2 s when the stream ends
        while not self._stopping() and not await is_disconnected():
            t = time.monotonic()
            try:
                update = await run_in_threadpool(feed.next)
            except StoreError as e:  # the store closed under it (service stopping)
                log.debug("viewer: update not built: %s", e)
                update = None
            if update is None:
                return
            yield "data: " + json.dumps(update, separators=(",", ":")) + "\n\n"
            if t - started > self.max_age:
                return
            while not self._stopping() and time.monotonic() - t < self.interval:
                await asyncio.sleep(min(0.1, self.interval))

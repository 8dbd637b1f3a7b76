"""Which keyframes of the map share a frame: the connected components of its links.

Poses are comparable only within one connected piece of the pose graph. A robot's odometry,
loop, proximity and merge links join its keyframes; a new session (another robot now, or the
same robot tomorrow) or a new segment after tracking was lost starts in a frame of its own,
and only a link to the old nodes places it in theirs. Before that, two robots that both
started "at the origin" have objects at the same coordinates that have nothing to do with
each other. The semantic fusion therefore associates a keyframe's segments only with objects
anchored in the keyframe's component (`MapConnectivity.roots`).

Components are kept by union–find over node ids, fed incrementally from the links table
(`MapStore.links_after`: only the rows written since the last look). Links are only ever
added in effect: a link deleted and rewritten (an interrupted map update redone, a local-BA
relink) joins the same nodes again, so components never split here.
"""
from __future__ import annotations

import dataclasses
import threading
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from .records import LinkType


class LinkLog(Protocol):
    """What `MapConnectivity.refresh` reads: the links stored after a links rowid (every role
    whose caller keeps a `MapConnectivity` has it)."""

    def links_after(self, rowid: int = 0) -> tuple[int, np.ndarray]: ...


class MapConnectivity:
    """Union–find over the map's node ids, joined by every link stored so far."""

    def __init__(self) -> None:
        self._parent: dict[int, int] = {}
        self._rowid = 0  # the newest links row seen
        self.joins = 0  # links read so far that joined two parts both known before (maps joined)

    def refresh(self, store: LinkLog) -> int:
        """Join the nodes of the links stored since the last call; returns how many were read."""
        self._rowid, pairs = store.links_after(self._rowid)
        for a, b in pairs.tolist():
            if self.knows(a) and self.knows(b) and self.find(a) != self.find(b):
                self.joins += 1  # two existing parts, not a new keyframe joining its own
            self.union(a, b)
        return len(pairs)

    def find(self, node: int) -> int:
        parent = self._parent
        root = node
        while parent.get(root, root) != root:
            root = parent[root]
        while node != root:  # path compression
            parent[node], node = root, parent.get(node, node)
        return root

    def union(self, a: int, b: int) -> None:
        ra, rb = self.find(a), self.find(b)
        if ra != rb:
            self._parent[max(ra, rb)] = min(ra, rb)  # the older node's root stays: deterministic
            self._parent.setdefault(min(ra, rb), min(ra, rb))

    def knows(self, node: int) -> bool:
        """Whether a link read so far touches `node` (else it is alone, or newer than the last look)."""
        return node in self._parent

    def roots(self, nodes) -> np.ndarray:
        """The component (root id) of each node, int64, in order (found once per distinct node)."""
        u, inv = np.unique(np.asarray(nodes, np.int64), return_inverse=True)
        return np.array([self.find(int(n)) for n in u], np.int64)[inv].reshape(-1)



# -- maps and sessions ---------------------------------------------------------------------------


@dataclass
class SessionJoin:
    """Which map a session is in and, when its keyframes joined an older map, when and how.

    A session's frame is its first keyframe's camera frame: tracking starts at the identity on
    the first frame it tracks, which is the session's first keyframe. Until a link joins that
    keyframe's part of the graph to an older one, the session is its own map (`map` = its own
    map id). `node` is the session's keyframe at the link that joined it (`peer` the other map's
    keyframe, `link` its type), `stamp` that keyframe's stamp. `T_map_session` (`MapIndex.join`)
    is the first keyframe's current pose: the session's frame in the map's frame."""

    session_id: int
    own_map: int  # the session's map id (sessions.map_id: a new one per session)
    map: int  # the map its first keyframe is in now
    first_node: int | None  # None: no keyframe yet
    node: int | None = None  # None: not joined (yet)
    peer: int | None = None
    link: int | None = None
    stamp: float | None = None

    @property
    def joined(self) -> bool:
        return self.node is not None


class MapIndex:
    """Which map each keyframe and each session is in, read incrementally from the store
    (`link_rows`, `node_sessions`, `sessions`: a `MapReader`). A map is a connected part of the
    pose graph named by the map id of the session of its oldest node (as `MapConnectivity`'s
    roots). Replaying the links in the order they were stored, a session joins an older map at
    the first link after which its first keyframe is no longer its part's oldest node.
    Thread-safe."""

    def __init__(self) -> None:
        self._links = MapConnectivity()
        self._rowid = 0
        self._last_node = 0
        self._session_of: dict[int, int] = {}  # node -> session
        self._stamp: dict[int, float] = {}
        self._time: dict[int, float] = {}  # node -> wall time written
        self._first: dict[int, int] = {}  # session -> its first node
        self._first_of: dict[int, int] = {}  # first node -> its session (not joined yet)
        self._merged: set[int] = set()  # nodes rehearsal merged into another
        self._sessions: dict = {}  # session id -> SessionRecord
        self._joins: dict[int, SessionJoin] = {}  # session -> its join (joined ones)
        self._lock = threading.Lock()

    def refresh(self, store) -> list[SessionJoin]:
        """Read the nodes, sessions and links stored since the last call; returns the sessions
        that joined an older map in the links read (oldest link first)."""
        with self._lock:
            rowid, rows = store.link_rows(self._rowid)  # links first: every node they name is read next
            nodes = store.node_sessions(self._last_node)
            if len(nodes["id"]) or not self._sessions:
                self._sessions = {s.id: s for s in store.sessions()}
            for n, s, t, w in zip(nodes["id"].tolist(), nodes["session_id"].tolist(), nodes["stamp"].tolist(),
                                  nodes["time_enter"].tolist()):
                self._session_of[n], self._stamp[n], self._time[n] = s, t, w
                if s not in self._first:
                    self._first[s] = n
                    self._first_of[n] = s
            if len(nodes["id"]):
                self._last_node = int(nodes["id"][-1])
            self._rowid = rowid
            new = []
            merged_type = int(LinkType.MERGED)
            for a, b, t in rows.tolist():
                if t == merged_type:
                    self._merged.add(b)
                ra, rb = self._links.find(a), self._links.find(b)
                if ra == rb:
                    continue
                hi = max(ra, rb)
                s = self._first_of.pop(hi, None)  # a session's first keyframe stops being its part's oldest
                if s is not None:
                    node, peer = (a, b) if ra == hi else (b, a)
                    j = SessionJoin(s, self._sessions[s].map_id if s in self._sessions else -1, -1, hi, node, peer,
                                    t, self._stamp.get(node))
                    self._joins[s] = j
                    new.append(j)
                self._links.union(a, b)
            for j in new:
                j.map = self._current_map(j)
            return new

    def _current_map(self, j: SessionJoin) -> int:
        """The map the session's first keyframe is in now (its own while that is unknown)."""
        m = None if j.first_node is None else self._map_of(j.first_node)
        return j.own_map if m is None else m

    def _map_of(self, node: int) -> int | None:
        root = self._links.find(int(node))
        s = self._session_of.get(root)
        return None if s is None or s not in self._sessions else self._sessions[s].map_id

    def map_of(self, node: int) -> int | None:
        """The map `node` is in (after the last `refresh`; None for a node not read yet)."""
        with self._lock:
            return self._map_of(node)

    def join(self, session_id: int) -> SessionJoin | None:
        """The session's map and join (None for an unknown session), after the last `refresh`."""
        with self._lock:
            s = self._sessions.get(session_id)
            if s is None:
                return None
            first = self._first.get(session_id)
            j = self._joins.get(session_id)
            if j is None:
                return SessionJoin(session_id, s.map_id, s.map_id, first)
            return dataclasses.replace(j, map=self._current_map(j))

    def maps(self) -> dict[int, dict]:
        """{map id: {"sessions": ids, "robots": names, "keyframes": its nodes not merged into
        another, "last_change": wall time of its newest keyframe or session start / end,
        "node_ids": every node of it (int64 array)}} after the last `refresh`: every map that
        has a keyframe (a session joined into an older map is that map's, not one of its own)."""
        with self._lock:
            out: dict[int, dict] = {}
            ids = np.fromiter(self._session_of, np.int64, len(self._session_of))
            if not len(ids):
                return out
            roots = self._links.roots(ids)
            maps_of_root = {r: self._map_of(r) for r in np.unique(roots).tolist()}
            node_map = np.array([maps_of_root[r] for r in roots.tolist()], np.int64)
            for sid, first in self._first.items():
                m = self._map_of(first)
                s = self._sessions.get(sid)
                if m is None or s is None:
                    continue
                e = out.setdefault(m, {"sessions": [], "robots": [], "keyframes": 0, "last_change": 0.0,
                                       "node_ids": np.zeros(0, np.int64)})
                e["sessions"].append(sid)
                if s.robot not in e["robots"]:
                    e["robots"].append(s.robot)
                e["last_change"] = max(e["last_change"], s.started_at, s.ended_at or 0.0)
            for m, e in out.items():
                sel = ids[node_map == m]
                e["node_ids"] = sel
                e["keyframes"] = int(len(sel) - len(self._merged.intersection(sel.tolist())))
                e["last_change"] = max([e["last_change"]] + [self._time[n] for n in sel[-1:].tolist()])
                e["sessions"].sort()
            return out

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

from typing import Protocol

import numpy as np


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


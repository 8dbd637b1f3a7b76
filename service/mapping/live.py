"""The map updates running at the same time on one map (issue 22 item 4: live cross-robot
loop closure).

In the service every robot's `Mapper` lives in one mapping process and they share the map's
store object and vocabulary; offline, several pipelines on one store object do the same. A
robot whose map has not joined another robot's yet searches that robot's keyframes by
appearance as it searches the older maps (`Mapper._relocalize`): the same two agreeing
verified links join them, never coordinates. The map whose component root (its oldest node,
as `storage.connectivity.MapIndex` names maps) is the larger one joins the other's: its
mapper places the other robot's linked keyframes in its graph at that robot's current poses
(anchored, as an older map's) and its frame becomes the other's, so both robots' map→odometry
corrections are in one frame from then on, and the server's `relocalized` event is for it.

`LiveMaps` is the per-store registry of those mappers (shared like the vocabulary,
`Vocabulary.for_store`) with a union–find of which of them joined which. Only synchronous
mappers take part (the mapping process's and offline ones): they run one update at a time,
so a mapper reads another's graph and memory while nothing changes them.
"""
from __future__ import annotations

import threading
import weakref
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from .mapper import Mapper


class LiveMaps:
    """The synchronous mappers of one store object in this process, and which joined which."""

    def __init__(self) -> None:
        self._mappers: list[Mapper] = []
        self._group: dict[int, int] = {}  # id(mapper) -> its group (one frame): a label
        self._lock = threading.Lock()

    @classmethod
    def for_store(cls, store) -> LiveMaps:
        """The one registry of a store object (created by its first mapper)."""
        with _SHARED_LOCK:
            live = _SHARED.get(store)
            if live is None:
                live = _SHARED[store] = cls()
            return live

    def register(self, mapper: Mapper) -> None:
        with self._lock:
            if all(m is not mapper for m in self._mappers):
                self._mappers.append(mapper)
                self._group[id(mapper)] = id(mapper)

    def unregister(self, mapper: Mapper) -> None:
        """A mapper that closed: no longer a candidate for the others (its nodes others placed
        in their graphs stay there, anchored where they were)."""
        with self._lock:
            self._mappers = [m for m in self._mappers if m is not mapper]
            self._group.pop(id(mapper), None)

    def joined(self, a: Mapper, b: Mapper) -> None:
        """`a` joined `b`'s map: their groups are one (one frame from now on)."""
        with self._lock:
            ga, gb = self._group[id(a)], self._group[id(b)]
            for k, g in self._group.items():
                if g == ga:
                    self._group[k] = gb

    def same(self, a: Mapper, b: Mapper) -> bool:
        with self._lock:
            return self._group.get(id(a)) == self._group.get(id(b))

    def peers(self, mapper: Mapper) -> list[Mapper]:
        """The other mappers whose maps `mapper`'s may join: not joined to it yet, with
        keyframes. (Either may find the two links; the newer map, the one with the larger
        root, is the one that joins: `Mapper._join`.)"""
        if mapper.root() is None:
            return []
        with self._lock:
            others = [m for m in self._mappers if self._group[id(m)] != self._group[id(mapper)]]
        return [m for m in others if m.root() is not None]


_SHARED: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # store -> its LiveMaps
_SHARED_LOCK = threading.Lock()

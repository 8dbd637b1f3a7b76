"""RTAB-Map's three memories, as bookkeeping: which keyframes (nodes) are in short-term
memory (STM: the newest `stm_size`, not loop candidates), working memory (WM: loop
candidates, their features and words in RAM) and long-term memory (LTM: in the database
only), and which move between them.

This module decides; it holds no features and does no I/O. Memory (`manager.Memory`) asks it
what to transfer and what to retrieve, moves the data (vocabulary, feature and view caches;
the mapper's loop detector and pose graph are told by the mapper) and tells it what moved.
Moving a node between WM and LTM changes no data.

Transfer (WM → LTM, RTAB-Map's `Memory::forget`): when WM holds more than `max_wm_nodes`
nodes, or more than the time budget allows (`adapt`: a map update that took longer than
`time_threshold_ms`, RTAB-Map's Rtabmap/TimeThr, lowers WM's limit in proportion, by at most
a tenth per update; updates well within it raise it back by one node each), the lowest-weight
nodes go first, the oldest (entered WM first) among equal weights; never the nodes that
entered WM since the last loop closure (up to `recent_wm_ratio` of WM), nodes linked to STM
or to the loop-closure node, nor nodes near the current pose; a node retrieved in the last
`retrieval_immunity` updates goes only when nothing else can (no churn: a node brought back
is not sent out again before it could be used).

Retrieval (LTM → WM): LTM nodes within `retrieval_depth` graph links of the best loop
hypothesis (even one below the acceptance threshold), nearest first (`select_retrievals`),
then those the map places near the new keyframe (memory asks the database's spatial
index), at most `max_retrieved` per update; not a node transferred in the last
`retrieval_immunity` updates (it went out for lack of use).
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Iterable, Iterator, Mapping

import numpy as np


def graph_levels(neighbours: Mapping[int, Iterable[int]], start: int, depth: int) -> Iterator[list[int]]:
    """Breadth-first walk of the graph's adjacency from `start`: the nodes first reached at
    link distance 1, 2, … `depth`, one list per level in the order they were reached; stops
    early at a level that reaches no new node."""
    frontier, seen = [start], {start}
    for _ in range(depth):
        nxt = []
        for a in frontier:
            for b in neighbours.get(a, ()):
                if b not in seen:
                    seen.add(b)
                    nxt.append(b)
        if not nxt:
            return
        yield nxt
        frontier = nxt


@dataclass
class MemorySizes:
    stm: int
    wm: int
    ltm: int


class WorkingMemory:
    def __init__(self, stm_size: int = 10, max_wm_nodes: int = 0, time_threshold_ms: float = 0.0,
                 recent_wm_ratio: float = 0.2, max_retrieved: int = 2, retrieval_depth: int = 2,
                 retrieval_immunity: int = 0):
        self.stm_size = max(0, int(stm_size))
        self.max_wm_nodes = max(0, int(max_wm_nodes))  # 0 = unlimited
        self.time_threshold_ms = float(time_threshold_ms)  # 0 = unlimited
        self.recent_wm_ratio = float(recent_wm_ratio)
        self.max_retrieved = max(0, int(max_retrieved))
        self.retrieval_depth = max(0, int(retrieval_depth))
        self.retrieval_immunity = max(0, int(retrieval_immunity))  # map updates; 0 = none
        self.stm: deque[int] = deque()
        self._wm: dict[int, int] = {}  # node -> order of entry into WM (insertion-ordered: oldest first)
        self.ltm: set[int] = set()
        self.weights: dict[int, int] = {}  # node -> weight (rehearsal raises it); all memories
        self._entries = 0
        self._last_loop_entry = 0  # WM entry counter at the last loop closure
        self._clock = 0  # map updates so far (`tick`)
        self.time_limit: int | None = None  # WM's limit from the time budget (`adapt`); None = none
        self._retrieved_at: dict[int, int] = {}  # node -> update it was last retrieved at
        self._transferred_at: dict[int, int] = {}  # node -> update it was last transferred at

    # -- sizes and membership -------------------------------------------------------------
    @property
    def wm(self) -> list[int]:
        """WM nodes, oldest entry first."""
        return list(self._wm)

    def sizes(self) -> MemorySizes:
        return MemorySizes(len(self.stm), len(self._wm), len(self.ltm))

    def in_wm(self, node: int) -> bool:
        return node in self._wm

    def in_ram(self, node: int) -> bool:
        """STM or WM: its features and words are in RAM."""
        return node in self._wm or node in self.stm

    def __contains__(self, node: int) -> bool:
        return node in self._wm or node in self.ltm or node in self.stm

    # -- life cycle -------------------------------------------------------------------------
    def add(self, node: int, weight: int = 0) -> list[int]:
        """A new keyframe enters STM; returns the nodes that moved from STM to WM."""
        self.stm.append(node)
        self.weights[node] = weight
        moved = []
        while len(self.stm) > self.stm_size:
            n = self.stm.popleft()
            self._enter_wm(n)
            moved.append(n)
        return moved

    def _enter_wm(self, node: int) -> None:
        self._entries += 1
        self._wm[node] = self._entries

    def tick(self) -> None:
        """A map update begins (the clock of retrieval immunity)."""
        self._clock += 1

    def immune(self, node: int) -> bool:
        """Retrieved in the last `retrieval_immunity` updates."""
        at = self._retrieved_at.get(node)
        return at is not None and self._clock - at < self.retrieval_immunity

    def cooling(self, node: int) -> bool:
        """Transferred in the last `retrieval_immunity` updates: not retrieved again yet."""
        at = self._transferred_at.get(node)
        return at is not None and self._clock - at < self.retrieval_immunity

    def loop_closed(self) -> None:
        """A loop closure was accepted: the nodes that enter WM from now on are 'recent'."""
        self._last_loop_entry = self._entries

    def rehearsed(self, survivor: int, merged_weight: int = 0) -> int:
        """A new keyframe (of weight `merged_weight`) was merged into `survivor`, a node of
        any memory (one in LTM stays there: the keyframe was merged with its stored words):
        the survivor's weight grows by it + 1 (RTAB-Map's); the keyframe never enters memory.
        Returns the new weight."""
        if survivor not in self:
            raise ValueError(f"node {survivor} is not in memory")
        self.weights[survivor] = self.weights.get(survivor, 0) + int(merged_weight) + 1
        return self.weights[survivor]

    def adapt(self, update_ms: float) -> None:
        """The time budget (`time_threshold_ms`, 0 = none), once per map update that took
        `update_ms`: over budget, WM's limit drops to its size × budget / update_ms (at least
        one node, at most a tenth of WM at once: one slow update, e.g. a loop closure's
        optimisation, does not empty it); under 0.8 × budget it grows back by one node per
        update, and goes when it reaches max_wm_nodes. RTAB-Map transfers until the update
        fits (Rtabmap/TimeThr); the limit keeps WM where the updates fit."""
        budget = self.time_threshold_ms
        if budget <= 0:
            return
        n = len(self._wm)
        if update_ms > budget and n > 0:
            cap = min(n - 1, max(int(0.9 * n), int(n * budget / update_ms)))
            self.time_limit = max(cap, 0) if self.time_limit is None else min(self.time_limit, max(cap, 0))
        elif update_ms < 0.8 * budget and self.time_limit is not None:
            self.time_limit += 1
            if 0 < self.max_wm_nodes <= self.time_limit:
                self.time_limit = None

    @property
    def limit(self) -> int | None:
        """WM's limit now: max_wm_nodes, or lower while the time budget needs (None: none)."""
        limits = [x for x in (self.max_wm_nodes or None, self.time_limit) if x is not None]
        return min(limits) if limits else None

    def over_limit(self, update_ms: float) -> bool:
        limit = self.limit
        return (limit is not None and len(self._wm) > limit) or \
            (self.time_threshold_ms > 0 and update_ms > self.time_threshold_ms)

    def select_transfers(self, update_ms: float, protected: Iterable[int] = (),
                         preferred: Iterable[int] = ()) -> list[int]:
        """The WM nodes to move to LTM after an update that took `update_ms`: enough to get
        back under the limit (`limit`), at least one node when the time threshold was exceeded;
        lowest weight first, then oldest. `protected` nodes (linked to STM, the loop-closure
        node) never go; `preferred` ones (near the current pose) and those that entered WM
        since the last loop closure (up to recent_wm_ratio of WM) go only when nothing else
        can, and after them the nodes retrieved in the last retrieval_immunity updates, so
        that WM never holds more than its limit."""
        if not self.over_limit(update_ms):
            return []
        n = len(self._wm)
        need = max(n - self.limit, 0) if self.limit is not None else 0
        if self.time_threshold_ms > 0 and update_ms > self.time_threshold_ms:
            need = max(need, 1)
        if need <= 0:
            return []
        keep = set(protected)
        recent = [m for m, e in self._wm.items() if e > self._last_loop_entry]
        soft = set(preferred) | set(recent[-int(self.recent_wm_ratio * n):] if self.recent_wm_ratio > 0 else [])
        ids = np.fromiter((m for m in self._wm if m not in keep), np.int64)
        if not len(ids):
            return []
        weight = np.fromiter((self.weights.get(m, 0) for m in ids.tolist()), np.int64)
        entry = np.fromiter((self._wm[m] for m in ids.tolist()), np.int64)
        kept = np.fromiter((m in soft for m in ids.tolist()), bool, len(ids))
        immune = np.fromiter((self.immune(m) for m in ids.tolist()), bool, len(ids))
        order = np.lexsort((ids, entry, weight, kept, immune))  # the others first; then weight, age, id
        return ids[order[:need]].tolist()

    def transferred(self, nodes: Iterable[int]) -> None:
        for n in nodes:
            if self._wm.pop(n, None) is not None:
                self.ltm.add(n)
                self._retrieved_at.pop(n, None)
                if self.retrieval_immunity:
                    self._transferred_at[n] = self._clock

    def select_retrievals(self, seeds: Iterable[int | None], neighbours: Mapping[int, Iterable[int]]) -> list[int]:
        """LTM nodes within retrieval_depth links of the `seeds` (best hypothesis first, then
        the current node), breadth first (nearest in the graph first), at most max_retrieved;
        not those transferred in the last retrieval_immunity updates."""
        if not self.ltm or self.max_retrieved <= 0:
            return []
        out: list[int] = []
        for seed in seeds:
            if seed is None:
                continue
            for level in graph_levels(neighbours, seed, self.retrieval_depth):
                for m in sorted(level):
                    if m in self.ltm and m not in out and not self.cooling(m):
                        out.append(m)
                        if len(out) >= self.max_retrieved:
                            return out
        return out

    def retrieved(self, nodes: Iterable[int]) -> None:
        for n in nodes:
            if n in self.ltm:
                self.ltm.discard(n)
                self._enter_wm(n)
                self._transferred_at.pop(n, None)
                if self.retrieval_immunity:
                    self._retrieved_at[n] = self._clock

    def restore(self, stm: Iterable[int], wm: Iterable[int], ltm: Iterable[int],
                weights: Mapping[int, int] | None = None) -> None:
        """Memberships of a reopened map (WM in entry order)."""
        self.stm = deque(stm)
        self._wm = {}
        for n in wm:
            self._enter_wm(n)
        self.ltm = set(ltm)
        if weights:
            self.weights.update(weights)

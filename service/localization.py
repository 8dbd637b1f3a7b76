"""Localization only (RTAB-Map's `Mem/IncrementalMemory` false; issue 22 item 3): a robot is
tracked and relocalizes in the stored map by appearance, its poses go out in the map's frame
once it has, and nothing is written to the map.

- `TransientKeyframes` takes the keyframe writer's place: a keyframe gets an id beyond any
  stored one (`TRANSIENT_BASE` + n, growing with time) and is written nowhere; there is no
  database session.
- `TransientMap` is the map update's store (`MapUpdateStore`): reads go to the map, writes
  (links, poses, statistics, words) stay in RAM (the links) or are dropped.
- `Localizer` is the map update (`Mapper`) on it: the map's nodes enter its graph at their
  stored poses with the tight prior (they stay fixed), the robot's keyframes join them only
  through a verified appearance link (the loop closure of a new session: `Memory.same_map`),
  and only the newest `memory.localization_nodes` of them are kept: older ones are
  forgotten (RAM, vocabulary, loop detector) and the graph is rebuilt without them (the map's
  nodes, the kept keyframes at their optimised poses, the links between those), so a robot
  localizing for hours holds as much as one that just started (RTAB-Map keeps an odometry
  cache of `RGBD/MaxOdomCacheSize` nodes the same way). Rehearsal is off (RTAB-Map only bumps
  weights in localization; a merge would change the map). `anchor` is the map's keyframe its
  newest keyframe is linked to, directly or not (None: not relocalized, poses in the robot's
  own frame).
"""
from __future__ import annotations

import dataclasses
import logging
import threading
from collections.abc import Iterable, Mapping
from typing import Callable

import numpy as np

from mnemoslam.client.kernel.frames import Calibration, Frame, PinholeCamera
from mnemoslam.client.kernel.geometry import invert
from mnemoslam.storage import LinkRecord, LinkType, MapUpdateStore, NodeRecord

from .config import LoopConfig, MemoryConfig
from .mapping.graph import PoseGraph
from .mapping.mapper import Mapper
from .mapping.merge_links import MergeLinks
from .memory.keyframes import odometry_information

log = logging.getLogger("mnemoslam.localization")

TRANSIENT_BASE = 1 << 40  # a localizing robot's keyframes: ids beyond any stored node's, growing with time


def transient(node_id: int | None) -> bool:
    """Whether a node id is a localizing robot's keyframe (never stored)."""
    return node_id is not None and int(node_id) >= TRANSIENT_BASE


class TransientKeyframes:
    """The keyframe writer of a localizing robot (`KeyframeWriter`'s interface): ids for its
    keyframes, the odometry link of each to the previous one, nothing written."""

    session_id = None  # no database session

    def __init__(self) -> None:
        self._next = TRANSIENT_BASE
        self.last_node: int | None = None
        self.last_pose: np.ndarray | None = None
        self.last_segment: int | None = None
        self.last_link: tuple | None = None

    def close(self, reason: str = "stopped") -> None:
        """Nothing to end: the robot had no session in the map."""

    def add_keyframe(self, frame: Frame, features, pose: np.ndarray, inliers: int, segment: int,
                     statistics: dict | None = None) -> int:
        link = None
        if self.last_node is not None and segment == self.last_segment:
            assert self.last_pose is not None  # set with last_node
            link = (self.last_node, invert(self.last_pose) @ pose, odometry_information(inliers))
        node_id, self._next = self._next, self._next + 1
        self.last_link = link
        self.last_node, self.last_pose, self.last_segment = node_id, pose, segment
        return node_id


class TransientMap:
    """The stored map as a localizing robot's map update sees it (`MapUpdateStore`): every
    read is the map's, every write stays in RAM or is dropped. `links`: the links the map
    update made, (from, to, type, T_from_to, information), those of forgotten keyframes
    pruned (`Localizer`); `links(...)` is the map's read."""

    def __init__(self, store: MapUpdateStore):
        self.store = store
        self.made: list[tuple[int, int, int, np.ndarray, np.ndarray]] = []
        self._lock = threading.Lock()
        self._to_map: list[tuple[int, int]] = []  # (map node, keyframe) links since `take_map_links`

    def take_map_links(self) -> list[tuple[int, int]]:
        """The links between a map node and one of the robot's keyframes made since the last
        call, (map node, keyframe), oldest first."""
        with self._lock:
            out, self._to_map = self._to_map, []
        return out

    def prune(self, gone: set[int]) -> list[tuple[int, int, int, np.ndarray, np.ndarray]]:
        """Drop the links made to or from the nodes `gone` (forgotten); returns the others."""
        with self._lock:
            self.made = [lk for lk in self.made if lk[0] not in gone and lk[1] not in gone]
            return list(self.made)

    # -- reads: the map's ----------------------------------------------------------------------
    def calibration(self, session_id: int) -> Calibration:
        return self.store.calibration(session_id)

    def get_node(self, node_id: int) -> NodeRecord | None:
        return None if transient(node_id) else self.store.get_node(node_id)

    def get_nodes(self, node_ids: Iterable[int]) -> list[NodeRecord]:
        return self.store.get_nodes([n for n in node_ids if not transient(n)])

    def node_ids(self, ended: bool | None = None, merged: bool | None = False) -> np.ndarray:
        return self.store.node_ids(ended=ended, merged=merged)

    def nodes(self, session_id: int | None = None, robot: str | None = None, bbox=None,
              limit: int | None = 100, offset: int = 0, merged: bool | None = None) -> list[NodeRecord]:
        return self.store.nodes(session_id=session_id, robot=robot, bbox=bbox, limit=limit, offset=offset,
                                merged=merged)

    def unmapped_nodes(self, session_ids: Iterable[int] | None = None,
                       end_reason: str | None = None) -> dict[int, list[int]]:
        return self.store.unmapped_nodes(session_ids=session_ids, end_reason=end_reason)

    def load_features(self, node_id: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
        return self.store.load_features(node_id)  # (UnknownIdError for a forgotten keyframe: not retrieved)

    def load_features_many(self, node_ids: Iterable[int]) -> dict[int, tuple[np.ndarray, np.ndarray, np.ndarray,
                                                                             np.ndarray | None]]:
        return self.store.load_features_many([n for n in node_ids if not transient(n)])

    def load_images(self, node_id: int) -> tuple[bytes | None, bytes | None]:
        return (None, None) if transient(node_id) else self.store.load_images(node_id)

    def links(self, session_id: int | None = None, node_ids: Iterable[int] | None = None,
              type: int | None = None) -> list[LinkRecord]:
        return self.store.links(session_id=session_id, node_ids=node_ids, type=type)

    def link_pairs(self, types: Iterable[int] | None = None) -> np.ndarray:
        return self.store.link_pairs(types)

    def load_words(self, word_ids: Iterable[int] | None = None) -> tuple[np.ndarray, np.ndarray]:
        return self.store.load_words(word_ids)

    def load_vocabulary_state(self) -> dict[str, np.ndarray]:
        return self.store.load_vocabulary_state()

    def next_word_id(self) -> int:
        return self.store.next_word_id()

    # -- writes: none reach the map --------------------------------------------------------------
    def add_link(self, from_id: int, to_id: int, type: int, transform: np.ndarray,
                 information: np.ndarray | None = None, *, replace: bool = False) -> None:
        info = np.eye(6) if information is None else information
        with self._lock:
            if replace:
                self.made = [lk for lk in self.made if (lk[0], lk[1]) != (from_id, to_id)]
            self.made.append((int(from_id), int(to_id), int(type), transform.copy(), info.copy()))
            if transient(from_id) != transient(to_id):
                a, b = (to_id, from_id) if transient(from_id) else (from_id, to_id)
                self._to_map.append((int(a), int(b)))

    def add_links(self, links: Iterable[tuple], *, replace: bool = False) -> None:
        for from_id, to_id, type, transform, information in links:
            self.add_link(from_id, to_id, type, transform, information, replace=replace)

    def merge_node(self, node_id: int, into_id: int, transform: np.ndarray, information: np.ndarray) -> int:
        return 0

    def update_poses(self, poses: Mapping[int, np.ndarray]) -> int:
        return 0

    def set_statistics(self, node_id: int, statistics: dict) -> None:
        return None

    def save_node_words(self, node_id: int, word_ids: np.ndarray, new_word_ids: np.ndarray | None = None,
                        new_descriptors: np.ndarray | None = None) -> None:
        return None


class Localizer(Mapper):
    """The map update of a localizing robot (module docstring). `anchor`: the map's keyframe
    its newest keyframe is linked to (None: not relocalized); `to_map` gives its poses in
    that map's frame once anchored."""

    def __init__(self, camera: PinholeCamera, config: LoopConfig, store: MapUpdateStore,
                 on_event: Callable[[str, dict], None] | None = None, background: bool = False,
                 memory: MemoryConfig | None = None):
        mc = dataclasses.replace(memory if memory is not None else MemoryConfig(), rehearsal=False)
        self.map = TransientMap(store)
        self.keep = max(int(mc.localization_nodes), mc.stm_size + 1)
        self.anchor: int | None = None
        self.forgotten = 0  # keyframes forgotten so far
        self._keyframes: list[tuple[int, int | None, np.ndarray | None, np.ndarray | None]] = []
        self._candidate: int | None = None  # the newest map node a keyframe was linked to
        super().__init__(camera, config, self.map, on_event=on_event, background=background,
                         memory=mc, live=False)

    @property
    def held(self) -> int:
        """The robot's keyframes its graph holds now (at most 2 × `keep`)."""
        return sum(transient(n) for n in self.graph.poses())

    def _update(self, u) -> None:
        super()._update(u)
        self._keyframes.append((u.node_id, u.odom_from, u.transform, u.information))
        for m, _ in self.map.take_map_links():
            self._candidate = m
        c = self._candidate
        anchor = c if c is not None and self.memory.same_map(u.node_id, [c]) else None
        if anchor != self.anchor:
            log.debug("localizer: keyframe %d anchored to map node %s", u.node_id, anchor)
        self.anchor = anchor
        if len(self._keyframes) > 2 * self.keep:
            self._forget()

    def _forget(self) -> None:
        """Forget the oldest keyframes but the newest `keep`: memory, the loop detector, and
        a graph rebuilt from the map's nodes and the kept keyframes at their optimised poses
        (the first kept one fixed there once relocalized, else with a new segment's loose
        prior, so an appearance link can still place it) with the links between them."""
        old, kept = self._keyframes[:-self.keep], self._keyframes[-self.keep:]
        gone = {n for n, *_ in old}
        self.memory.forget(sorted(gone))
        self.detector.forget(sorted(gone))
        poses = self.graph.poses()
        graph = PoseGraph(max_error=self.config.optimize_max_error)
        graph.add_anchored({n: p for n, p in poses.items() if not transient(n)})
        for k, (n, src, t, info) in enumerate(kept):
            if n not in poses:
                continue
            if src is not None and src in graph:
                graph.add_node(n, poses[n], odom_from=src, transform=t, information=info)
            elif k == 0 and self.anchor is not None and self.memory.same_map(n, [self.anchor]):
                graph.add_anchored({n: poses[n]})
            else:
                graph.add_node(n, poses[n])  # (a segment's loose prior)
        for a, b, kind, t, info in self.map.prune(gone):
            if a in graph and b in graph and kind != LinkType.NEIGHBOR:
                graph.add_loop(a, b, t, info, check=False)
        graph.changed_poses()  # (they are where they were: nothing to report)
        self.graph = graph
        self.merge_links = MergeLinks(graph)
        self.loops = [(a, b) for a, b in self.loops if a not in gone and b not in gone]
        self._keyframes = kept
        self.forgotten += len(gone)

"""The map update behind tracking: for each new keyframe, vocabulary → loop hypothesis
(Bayes filter) → geometric verification → pose-graph optimisation (iSAM2) → corrected
poses to storage and a `map corrected` event.

Tracking never waits for it: in the service the mapper runs on its own thread and takes
keyframes from a queue (RTAB-Map's map update runs at its detection rate, ORB-SLAM's loop
closing in parallel to tracking). Offline runs call it synchronously so a run stays
bit-for-bit reproducible. The mapper owns the map→odometry correction that turns the
odometry's poses into map poses."""
from __future__ import annotations

import logging
import queue
import threading
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from client.frames import PinholeCamera
from client.geometry import invert
from storage import LinkType, MapStore

from .config import LoopConfig
from .features import FrameFeatures
from .graph import PoseGraph
from .loop_detection import LoopDetector
from .verification import verify
from .vocabulary import Vocabulary

log = logging.getLogger("mnemoslam.mapping")


@dataclass
class KeyframeUpdate:
    node_id: int
    stamp: float
    odom_pose: np.ndarray  # pose from odometry (odometry frame)
    features: FrameFeatures
    odom_from: int | None  # previous keyframe of the same segment
    transform: np.ndarray | None  # T_from_to of that odometry link
    information: np.ndarray | None


@dataclass
class LoopStatistics:
    """Why a loop was or wasn't closed for one keyframe (kept per node, shown over REST)."""

    node_id: int
    hypothesis: int | None = None
    posterior: float = 0.0
    likelihood_top: list = field(default_factory=list)
    decision: str = "none"  # "none", "rejected: …", "accepted"
    matches: int = 0
    inliers: int = 0
    timings_ms: dict = field(default_factory=dict)


class Mapper:
    def __init__(self, camera: PinholeCamera, config: LoopConfig, store: MapStore | None = None,
                 on_event: Callable[[str, dict], None] | None = None, background: bool = False):
        self.camera = camera
        self.config = config
        self.store = store
        self.on_event = on_event or (lambda kind, data: None)
        # The map's vocabulary: loaded from the store when the map is reopened, shared by every
        # mapper (robot) of that store, persisted with each keyframe.
        self.vocabulary = (Vocabulary.for_store(store, nndr=config.nndr_ratio) if store is not None
                           else Vocabulary(nndr=config.nndr_ratio))
        self.detector = LoopDetector(self.vocabulary, loop_threshold=config.threshold, stm_size=config.stm_size)
        self.graph = PoseGraph(max_error=config.optimize_max_error)
        self._features: dict[int, FrameFeatures] = {}  # working memory's features (bounded later by the memory manager)
        self._order: list[int] = []
        self._stamps: dict[int, float] = {}
        self._neighbours: dict[int, list[int]] = {}
        self._correction = np.eye(4)  # T_map_odom
        self._lock = threading.Lock()
        self.loops: list[tuple[int, int]] = []
        self.statistics: dict[int, LoopStatistics] = {}
        self._queue: queue.Queue | None = None
        if background:
            self._queue = queue.Queue()
            self._thread = threading.Thread(target=self._run, name="mapper", daemon=True)
            self._thread.start()

    # -- tracking side ---------------------------------------------------------------------
    def submit(self, update: KeyframeUpdate) -> None:
        if self._queue is None:
            self._update(update)
        else:
            self._queue.put(update)

    def to_map(self, odom_pose: np.ndarray) -> np.ndarray:
        with self._lock:
            return self._correction @ odom_pose

    def close(self, timeout: float = 30.0) -> None:
        if self._queue is not None:
            self._queue.put(None)
            self._thread.join(timeout)

    def keyframe_poses(self) -> dict[int, np.ndarray]:
        return self.graph.poses()

    # -- map update ------------------------------------------------------------------------
    def _run(self) -> None:
        while True:
            update = self._queue.get()
            if update is None:
                return
            try:
                self._update(update)
            except Exception:  # a failed map update must not stop the mapper
                log.exception("map update of node %d failed", update.node_id)

    def _update(self, u: KeyframeUpdate) -> None:
        t0 = time.perf_counter()
        self.graph.add_node(u.node_id, u.odom_pose, u.odom_from, u.transform, u.information)
        self._remember(u)
        t1 = time.perf_counter()
        words = self.vocabulary.add(u.node_id, u.features.descriptors, store=self.store)  # + its new words, one commit
        t2 = time.perf_counter()
        stm = set(self._order[-self.config.stm_size:])
        candidates = {n for n in self._order if u.stamp - self._stamps[n] >= self.config.min_age} - stm
        with self.vocabulary.lock:  # other robots' mappers add to the same vocabulary
            hyp = self.detector.process(u.node_id, words, self._neighbours, candidates)
        t3 = time.perf_counter()
        stats = LoopStatistics(u.node_id, hyp.best_id, float(hyp.posterior),
                               [(int(i), float(s)) for i, s in hyp.likelihood[:5]])
        stats.decision = "none" if hyp.best_id is None else ("accepted" if hyp.accepted else f"rejected: {hyp.reason}")
        if hyp.accepted:
            self._close_loop(u, hyp.best_id, stats)
        t4 = time.perf_counter()
        stats.timings_ms = {"graph": (t1 - t0) * 1e3, "vocabulary": (t2 - t1) * 1e3,
                            "detection": (t3 - t2) * 1e3, "verification_optimization": (t4 - t3) * 1e3}
        self.statistics[u.node_id] = stats
        if self.store is not None:
            self.store.set_statistics(u.node_id, stats.__dict__)
        with self._lock:
            self._correction = self.graph.pose(u.node_id) @ invert(u.odom_pose)

    def _remember(self, u: KeyframeUpdate) -> None:
        self._features[u.node_id] = u.features
        self._stamps[u.node_id] = u.stamp
        self._order.append(u.node_id)
        self._neighbours.setdefault(u.node_id, [])
        if u.odom_from is not None:
            self._neighbours[u.node_id].append(u.odom_from)
            self._neighbours.setdefault(u.odom_from, []).append(u.node_id)

    def _close_loop(self, u: KeyframeUpdate, candidate: int, stats: LoopStatistics) -> None:
        cand = self._features[candidate]
        v = verify(self.camera, u.features.keypoints, u.features.descriptors, cand.descriptors, cand.points,
                   min_inliers=self.config.min_inliers)
        stats.matches, stats.inliers = v.matches, v.inliers
        if not v.accepted:
            stats.decision = f"rejected: verification {v.reason}"
            return
        outcome = self.graph.add_loop(candidate, u.node_id, v.transform, v.information)
        if not outcome.accepted:
            stats.decision = f"rejected: graph {outcome.reason}"
            return
        stats.decision = "accepted"
        self.loops.append((candidate, u.node_id))
        self._neighbours[u.node_id].append(candidate)
        self._neighbours[candidate].append(u.node_id)
        moved = self.graph.changed_poses()
        if self.store is not None:
            self.store.add_link(candidate, u.node_id, LinkType.GLOBAL_CLOSURE, v.transform, v.information)
            if moved:
                self.store.update_poses(moved)
        self.on_event("loop_closed", {"from": candidate, "to": u.node_id, "inliers": v.inliers})
        if moved:
            self.on_event("map_corrected", {"nodes": len(moved)})

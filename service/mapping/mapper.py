"""The map update behind tracking: for each new keyframe, vocabulary → loop hypothesis
(Bayes filter) → geometric verification → pose-graph optimisation (iSAM2) → corrected
poses to storage and a `map corrected` event.

Tracking never waits for it: in the service the mapper runs on its own thread and takes
keyframes from a queue (RTAB-Map's map update runs at its detection rate, ORB-SLAM's loop
closing in parallel to tracking). Offline runs call it synchronously so a run stays
bit-for-bit reproducible. The mapper owns the map→odometry correction that turns the
odometry's poses into map poses."""
from __future__ import annotations

import collections
import dataclasses
import logging
import queue
import threading
import time
from dataclasses import dataclass, field
from typing import Callable

import cv2
import gtsam
import numpy as np

from client.frames import PinholeCamera
from client.geometry import invert, rotation_angle
from storage import LinkType, MapStore, UnknownIdError

from ..config import LoopConfig, MemoryConfig
from ..memory.long_term import decode_images
from ..memory.working_memory import WorkingMemory
from ..tracking.features import FrameFeatures
from ..tracking.odometry import _match
from .graph import PoseGraph
from .loop_detection import LoopDetector
from .proximity import nearby
from .verification import DenseView, Verification, refine, register_dense, verify
from .vocabulary import Vocabulary

log = logging.getLogger("mnemoslam.mapping")

STATISTICS_KEPT = 1000  # map updates whose LoopStatistics a Mapper keeps in RAM (RAM stays flat on long runs)


@dataclass
class KeyframeUpdate:
    node_id: int
    stamp: float
    odom_pose: np.ndarray  # pose from odometry (odometry frame)
    features: FrameFeatures
    odom_from: int | None  # previous keyframe of the same segment
    transform: np.ndarray | None  # T_from_to of that odometry link
    information: np.ndarray | None

    @classmethod
    def from_store(cls, store: MapStore, node_id: int, images: bool = True) -> "KeyframeUpdate":
        """The update tracking handed over for a stored keyframe, rebuilt from the database:
        its stamp and stored pose (the odometry's until the map update moves it), features
        (without octaves: the map update does not use them), odometry link and, with
        `images`, the depth and grey image decoded from its stored PNG-16 / JPEG (for dense
        refinement; lossy JPEG, millimetre depth)."""
        node = store.get_node(node_id)
        if node is None:
            raise UnknownIdError(f"no node {node_id}")
        keypoints, descriptors, points, _ = store.load_features(node.id)
        depth = grey = None
        if images:
            image, depth = decode_images(*store.load_images(node.id))
            if image is None or depth is None:
                depth = None
            else:
                grey = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image
        links = [l for l in store.links(node_ids=[node.id], type=LinkType.NEIGHBOR) if l.to_id == node.id]
        odom = links[0] if links else None
        features = FrameFeatures(keypoints, descriptors, points, np.zeros(len(keypoints), np.int8), depth, grey)
        return cls(node.id, node.stamp, node.pose, features, odom.from_id if odom else None,
                   odom.transform if odom else None, odom.information if odom else None)


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
    refined: bool = False  # the accepted link was refined by dense registration
    proximity: list = field(default_factory=list)  # [{node, decision, inliers, refined}] spatial candidates
    path: list = field(default_factory=list)  # [{node, decision, inliers, refined}] recent keyframes of its own path
    rehearsal: dict = field(default_factory=dict)  # {node, similarity, inliers, distance, rotation, decision}: the node it was or wasn't merged into
    timings_ms: dict = field(default_factory=dict)
    memory: dict = field(default_factory=dict)  # after the update: stm, wm, ltm sizes, transferred / retrieved ids, words


@dataclass
class Rehearsal:
    """What rehearsal did for one keyframe: the node it merged into (None: it becomes a node),
    and a verified link to a node it did not merge into, (node, verification), which
    proximity detection reuses."""

    survivor: int | None = None
    verified: tuple[int, Verification] | None = None


class Mapper:
    def __init__(self, camera: PinholeCamera, config: LoopConfig, store: MapStore | None = None,
                 on_event: Callable[[str, dict], None] | None = None, background: bool = False,
                 memory: MemoryConfig | None = None, previous_map: bool = True):
        self.camera = camera
        self.config = config
        self.memory_config = mc = memory if memory is not None else MemoryConfig()
        self.store = store
        self.on_event = on_event or (lambda kind, data: None)
        # The map's vocabulary: shared by every mapper (robot) of that store, persisted with each
        # keyframe; on a reopened map with a WM limit it starts without words (those of the nodes
        # in RAM come with them), else it is loaded whole from the store.
        self.vocabulary = (Vocabulary.for_store(store, words=mc.max_wm_nodes <= 0, nndr=config.nndr_ratio)
                           if store is not None else Vocabulary(nndr=config.nndr_ratio))
        self.detector = LoopDetector(self.vocabulary, loop_threshold=config.threshold, stm_size=mc.stm_size)
        self.graph = PoseGraph(max_error=config.optimize_max_error)
        # STM / WM / LTM: which keyframes are loop candidates with features and words in RAM
        self.memory = WorkingMemory(mc.stm_size, mc.max_wm_nodes, mc.time_threshold_ms, mc.recent_wm_ratio,
                                    mc.max_retrieved, mc.retrieval_depth)
        self._features: dict[int, FrameFeatures] = {}  # the features of the keyframes in STM and WM
        # reduced depth + grey of RGB-D keyframes in RAM, for dense link refinement (a retrieved
        # keyframe's are decoded from its stored images when first needed)
        self._views: dict[int, DenseView] = _StoredViews(store, camera, ()) if store is not None else {}
        self._order: list[int] = []
        self._stamps: dict[int, float] = {}
        self._neighbours: dict[int, list[int]] = {}
        self._segment: dict[int, int] = {}  # node -> first node of its odometry segment
        self._loop_nodes: set[int] = set()  # the older end of the last accepted loop closure (kept in WM)
        self._merged: dict[int, tuple[int, np.ndarray]] = {}  # keyframe merged by rehearsal -> (survivor, T_survivor_keyframe)
        self._merge_links: dict[frozenset, _MergeLink] = {}  # node pair -> the one graph link merges between them made
        self._correction = np.eye(4)  # T_map_odom
        self._lock = threading.Lock()
        self.loops: list[tuple[int, int]] = []
        # the statistics of the last STATISTICS_KEPT updates (every update's are in the database)
        self.statistics: collections.OrderedDict[int, LoopStatistics] = collections.OrderedDict()
        self._queue: queue.Queue | None = None
        self.submitted = 0  # keyframe updates handed to the map update ...
        self.mapped = 0  # ... and done (the difference is the backlog)
        if store is not None and previous_map:
            self._load_previous_map()
        if background:
            self._queue = queue.Queue()
            self._thread = threading.Thread(target=self._run, name="mapper", daemon=True)
            self._thread.start()

    @classmethod
    def resume(cls, store: MapStore, session_id: int, config: LoopConfig, camera: PinholeCamera | None = None,
               on_event: Callable[[str, dict], None] | None = None, memory: MemoryConfig | None = None) -> "Mapper":
        """A (synchronous) mapper that continues a stored session's map update, e.g. after
        the service was killed with keyframes still in its backlog. It holds the session's
        mapped keyframes (those with a statistics row) as the interrupted mapper did: the
        graph with their odometry and loop links at their stored poses, their features, their
        dense views (decoded from the stored images when a candidate needs one), the path
        segments and graph neighbours; the map's vocabulary comes from the store as for any
        mapper. Then `submit` the session's unmapped keyframes in id order (see
        `KeyframeUpdate.from_store`) and they close loops to the mapped ones. The loop
        detector's belief starts afresh and `to_map` gives the identity until the first
        update. `camera` defaults to the session's."""
        sid = int(session_id)
        if camera is None:
            camera = store.calibration(sid).camera
        m = cls(camera, config, store, on_event=on_event, memory=memory, previous_map=False)
        unmapped = set(store.unmapped_nodes(session_ids=[sid]).get(sid, ()))
        stored = [n for n in store.nodes(session_id=sid, limit=None) if n.id not in unmapped]  # by id = in time
        nodes = [n for n in stored if n.merged_into is None]
        links = [l for l in store.links(session_id=sid) if l.from_id not in unmapped and l.to_id not in unmapped]
        merges = {l.to_id: l for l in links if l.type == LinkType.MERGED}
        m._merged = {k: (l.from_id, l.transform) for k, l in merges.items()}
        odometry, entries = [], []  # odometry links through merged keyframes: to a node, or (rehearsal) to a survivor
        for l in links:
            if l.type != LinkType.NEIGHBOR:
                continue
            a, ta = m._merged.get(l.from_id, (l.from_id, np.eye(4)))
            b, tb = m._merged.get(l.to_id, (l.to_id, np.eye(4)))
            if l.to_id not in m._merged:
                odometry.append((a, b, ta @ l.transform, l.information))
            elif a != b:
                entries.append((a, b, ta @ l.transform @ invert(tb),
                                _series_information(l.information, merges[l.to_id].information)))
        own = {n.id for n in nodes}
        loops = [(l.from_id, l.to_id, l.transform, l.information) for l in links
                 if l.type in (LinkType.GLOBAL_CLOSURE, LinkType.LOCAL_SPACE, LinkType.LOCAL_TIME)]
        across = [k for k in loops if not (k[0] in own and k[1] in own)]  # to the previous map's nodes
        # odometry from a keyframe merged into the previous map's node starts at that node
        across += [k for k in odometry if k[0] not in own]
        m.graph.restore({n.id: n.pose for n in nodes}, [k for k in odometry if k[0] in own],
                        [k for k in loops if k[0] in own and k[1] in own])
        # the previous map's nodes this session linked to: by loops, odometry or merges
        m._place_previous({n for a, b, _, _ in across + entries for n in (a, b) if n not in own})
        for a, b, t, info in across:
            m.graph.add_loop(a, b, t, info, check=False)  # checked when it was added
        for a, b, t, info in sorted(entries, key=lambda e: e[1]):  # as _rehearse made them (checked then)
            m._link_merge(a, b, t, info, check=False)
        incoming = {b: a for a, b, _, _ in odometry}
        for a, b, _, _ in entries:
            if b not in m._neighbours.setdefault(a, []):
                m._neighbours[a].append(b)
                m._neighbours.setdefault(b, []).append(a)
        mapped = {n.id for n in nodes}
        words = {}
        for n in nodes:
            keypoints, descriptors, points, words[n.id] = store.load_features(n.id)
            m._features[n.id] = FrameFeatures(keypoints, descriptors, points, np.zeros(len(keypoints), np.int8))
            m._stamps[n.id] = n.stamp
            m._order.append(n.id)
            m._neighbours.setdefault(n.id, [])
            src = incoming.get(n.id)
            m._segment[n.id] = n.id if src is None else m._segment.get(src, src)
            if src is not None:
                m._neighbours[n.id].append(src)
                m._neighbours.setdefault(src, []).append(n.id)
        for l in links:
            if l.type in (LinkType.GLOBAL_CLOSURE, LinkType.LOCAL_SPACE):  # as _add_link: path links are not loops
                m.loops.append((l.from_id, l.to_id))
                m._neighbours[l.to_id].append(l.from_id)
                m._neighbours[l.from_id].append(l.to_id)
        if config.refine_dense:
            m._views = _StoredViews(store, camera, mapped)
        m._index_words(words)  # those the vocabulary does not hold (it loads only WM's with a WM limit)
        k = max(len(m._order) - m.memory.stm_size, 0)
        m.memory.restore(stm=m._order[k:], wm=m._order[:k], ltm=(), weights={n.id: n.weight for n in nodes})
        return m

    # -- tracking side ---------------------------------------------------------------------
    def submit(self, update: KeyframeUpdate) -> None:
        self.submitted += 1
        if self._queue is None:
            try:
                self._update(update)
            finally:
                self.mapped += 1
        else:
            self._queue.put(update)

    def to_map(self, odom_pose: np.ndarray) -> np.ndarray:
        with self._lock:
            return self._correction @ odom_pose

    def close(self, timeout: float = 30.0) -> None:
        """Finish the queued updates (background mapper), then write the graph's final poses."""
        if self._queue is not None:
            self._queue.put(None)
            self._thread.join(timeout)
        self.flush_poses()

    @property
    def merged(self) -> int:
        """Keyframes merged into a node by rehearsal (they are not nodes of the map)."""
        return len(self._merged)

    def keyframe_poses(self) -> dict[int, np.ndarray]:
        """Every keyframe's map pose: the graph's nodes, and each merged keyframe where its
        survivor sees it."""
        poses = self.graph.poses()
        poses.update({m: poses[c] @ t for m, (c, t) in self._merged.items() if c in poses})
        return poses

    def flush_poses(self) -> None:
        """Write every pose that moved at all since it was last written (the graph reports only
        moves above its tolerance), and the merged keyframes' poses, so that the database
        holds the graph's final estimate."""
        self._write_moved((0.0, 0.0))
        if self._merged and self.store is not None:
            self.store.update_poses({m: self._pose(m) for m in self._merged})

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
            finally:
                self.mapped += 1

    def _update(self, u: KeyframeUpdate) -> None:
        t0 = time.perf_counter()
        u = self._through_merges(u)
        self._add_view(u)
        stats = LoopStatistics(u.node_id)
        r = self._rehearse(u, stats) if self.memory_config.rehearsal and u.odom_from is not None else Rehearsal()
        t1 = time.perf_counter()
        survivor = r.survivor
        best = survivor if survivor is not None else self._add_keyframe(u, stats, r.verified)
        t2 = time.perf_counter()
        transferred, retrieved = self._manage_memory(u, best, (t2 - t0) * 1e3)
        stats.timings_ms["rehearsal"] = (t1 - t0) * 1e3
        stats.timings_ms["memory"] = (time.perf_counter() - t2) * 1e3
        sizes = self.memory.sizes()
        stats.memory = {"stamp": u.stamp, "stm": sizes.stm, "wm": sizes.wm, "ltm": sizes.ltm,
                        "transferred": transferred, "retrieved": retrieved,
                        "merged": [] if survivor is None else [survivor],
                        "words": len(self.vocabulary), "dormant_words": self.vocabulary.dormant}
        self.statistics[u.node_id] = stats
        while len(self.statistics) > STATISTICS_KEPT:
            self.statistics.popitem(last=False)
        self._publish(u.node_id)
        if self.store is not None:
            self.store.set_statistics(u.node_id, stats.__dict__)
        with self._lock:
            self._correction = self._pose(u.node_id) @ invert(u.odom_pose)

    def _add_keyframe(self, u: KeyframeUpdate, stats: LoopStatistics,
                      verified: tuple[int, Verification] | None = None) -> int | None:
        """The keyframe becomes a node: graph, memory, vocabulary, then loop closure by
        appearance, by space and along its path (`verified`: a link rehearsal verified but did
        not merge). Returns the best loop hypothesis (for retrieval)."""
        t0 = time.perf_counter()
        self.graph.add_node(u.node_id, u.odom_pose, u.odom_from, u.transform, u.information)
        self._remember(u)
        t1 = time.perf_counter()
        words = self.vocabulary.add(u.node_id, u.features.descriptors, store=self.store)  # + its new words, one commit
        t2 = time.perf_counter()
        candidates = {n for n in self.memory.wm if u.stamp - self._stamps[n] >= self.config.min_age}
        with self.vocabulary.lock:  # other robots' mappers add to the same vocabulary
            hyp = self.detector.process(u.node_id, words, self._neighbours, candidates)
        t3 = time.perf_counter()
        stats.hypothesis, stats.posterior = hyp.best_id, float(hyp.posterior)
        stats.likelihood_top = [(int(i), float(s)) for i, s in hyp.likelihood[:5]]
        stats.decision = "none" if hyp.best_id is None else ("accepted" if hyp.accepted else f"rejected: {hyp.reason}")
        if hyp.accepted:
            stats.decision, v = self._close_loop(u, hyp.best_id, LinkType.GLOBAL_CLOSURE)
            if v is not None:
                stats.matches, stats.inliers, stats.refined = v.matches, v.inliers, v.refined
        t4 = time.perf_counter()
        if self.config.proximity_by_space:
            self._close_nearby(u, candidates, stats, verified)
        t5 = time.perf_counter()
        if self.config.proximity_by_time:
            self._link_path(u, candidates, stats)
        t6 = time.perf_counter()
        stats.timings_ms = {"graph": (t1 - t0) * 1e3, "vocabulary": (t2 - t1) * 1e3,
                            "detection": (t3 - t2) * 1e3, "verification_optimization": (t4 - t3) * 1e3,
                            "proximity": (t5 - t4) * 1e3, "path": (t6 - t5) * 1e3}
        return hyp.best_id

    # -- rehearsal ---------------------------------------------------------------------------
    def _through_merges(self, u: KeyframeUpdate) -> KeyframeUpdate:
        """A keyframe whose odometry starts at a merged keyframe starts at its survivor."""
        if u.odom_from not in self._merged or u.transform is None:
            return u
        survivor, t = self._merged[u.odom_from]
        return dataclasses.replace(u, odom_from=survivor, transform=t @ u.transform)

    def _pose(self, node: int) -> np.ndarray:
        """A keyframe's map pose: its node's, or for a merged keyframe where its survivor sees it."""
        if node in self._merged:
            survivor, t = self._merged[node]
            return self.graph.pose(survivor) @ t
        return self.graph.pose(node)

    def _rehearse(self, u: KeyframeUpdate, stats: LoopStatistics) -> Rehearsal:
        """RTAB-Map's rehearsal, against the map rather than the last node only: the
        WM node nearest to where odometry puts the keyframe (within twice the merge distance
        and rotation) is its survivor when the two share `memory.rehearsal_similarity` of
        their visual words, registration puts them within `memory.rehearsal_max_distance` /
        `rehearsal_max_rotation`, and the graph accepts the link from the previous keyframe
        to the survivor (it replaces the odometry link to the keyframe). The keyframe is then
        merged: no node, no words; the survivor's weight grows. Returns the survivor (None: the
        keyframe becomes a node) and what was verified on the way."""
        c = self._rehearsal_candidate(u)
        if c is None:
            return Rehearsal()
        mc = self.memory_config
        t0 = time.perf_counter()
        similarity = self._similarity(u.features.descriptors, c)
        t1 = time.perf_counter()
        r = stats.rehearsal = {"node": c, "similarity": round(similarity, 3), "search_ms": (t1 - t0) * 1e3}
        if similarity < mc.rehearsal_similarity:
            r["decision"] = "rejected: similarity"
            return Rehearsal()
        decision, v = self._register(u, c)
        r["inliers"] = 0 if v is None else v.inliers
        r["verify_ms"] = (time.perf_counter() - t1) * 1e3
        if decision != "ok":
            r["decision"] = decision
            return Rehearsal()
        r["distance"] = float(np.linalg.norm(v.transform[:3, 3]))
        r["rotation"] = float(rotation_angle(v.transform[:3, :3]))
        if r["distance"] > mc.rehearsal_max_distance or r["rotation"] > mc.rehearsal_max_rotation:
            r["decision"] = "rejected: too far"
            return Rehearsal(None, (c, v))
        p = u.odom_from
        if p != c:
            outcome = self._link_merge(p, c, u.transform @ invert(v.transform),
                                       _series_information(u.information, v.information))
            r["graph_ms"] = outcome.duration_ms
            if not outcome.accepted:
                r["decision"] = f"rejected: graph {outcome.reason}"
                return Rehearsal(None, (c, v))
        r["decision"] = "merged"
        r["loop"] = entering = p != c and c not in self._neighbours.get(p, ())  # came back: a loop closure
        self._merge(u, c, v, entering)
        return Rehearsal(c)

    def _link_merge(self, a: int, b: int, transform: np.ndarray, information: np.ndarray, check: str | bool = "link"):
        """The graph link a merge makes between two nodes (T_a_b): the first merge between
        them adds it; a later one replaces it by the running mean of their measurements, its
        information that of one measurement times their count (up to 3), so repeated passes
        refine one link per pair instead of adding one per keyframe (iSAM2 grows ~7 kB per
        link). Returns the graph's outcome."""
        key = frozenset((a, b))
        old = self._merge_links.get(key)
        n = 0
        if old is not None:
            t = transform if old.from_id == a else invert(transform)
            a, b, n = old.from_id, old.to_id, old.count
            step = gtsam.Pose3.Logmap(gtsam.Pose3(invert(old.transform) @ t)) / (n + 1)
            transform = old.transform @ gtsam.Pose3.Expmap(step).matrix()
            information = information * min(n + 1, 3)
            self.graph.remove_loop(a, b, old.transform)
        outcome = self.graph.add_loop(a, b, transform, information, check=check)
        if outcome.accepted:
            self._merge_links[key] = _MergeLink(a, b, transform, information, n + 1)
        elif old is not None:  # the previous link goes back
            self.graph.add_loop(old.from_id, old.to_id, old.transform, old.information, check=False)
        return outcome

    def _rehearsal_candidate(self, u: KeyframeUpdate) -> int | None:
        """The WM node closest to where odometry puts the keyframe, by distance over
        rehearsal_max_distance plus rotation over rehearsal_max_rotation, if that is < 4
        (e.g. both within twice their limit). Not STM: the newest keyframes are the path just
        walked, one keyframe spacing apart (merging a keyframe into the one before replaces
        odometry by a registration: 7-Scenes 4.15 -> 5.43 cm); a revisit finds older ones."""
        mc = self.memory_config
        ram = [n for n in self.memory.wm if n in self.vocabulary]
        if not ram:
            return None
        where = self.graph.pose(u.odom_from) @ u.transform
        poses = np.stack([self.graph.pose(n) for n in ram])
        dist = np.linalg.norm(poses[:, :3, 3] - where[:3, 3], axis=1)
        turn = rotation_angle(np.swapaxes(poses[:, :3, :3], 1, 2) @ where[:3, :3])
        score = dist / mc.rehearsal_max_distance + turn / mc.rehearsal_max_rotation
        k = int(np.argmin(score))
        return ram[k] if score[k] < 4.0 else None

    def _similarity(self, descriptors: np.ndarray, node: int) -> float:
        """Shared words / the larger node's words (RTAB-Map's Signature::compareTo): the
        keyframe's descriptors matched against the node's words only (nearest word within the
        vocabulary's distance and ratio, one descriptor per word), not searched in the whole
        vocabulary: a few hundred by a few hundred Hamming distances instead of a search."""
        with self.vocabulary.lock:
            theirs = self.vocabulary.descriptors(self.vocabulary.node_words(node)[0])
        shared, _ = _match(descriptors, theirs, self.vocabulary.nndr, self.vocabulary.max_distance)
        return len(shared) / max(len(descriptors), len(theirs), 1)

    def _merge(self, u: KeyframeUpdate, survivor: int, v: Verification, entering: bool) -> None:
        """Keyframe `u` merges into `survivor` (RAM, memory weights, database); `entering`:
        the path just came back to the survivor's part of the map (counts as a loop closure)."""
        self._merged[u.node_id] = (survivor, v.transform.copy())
        self._views.pop(u.node_id, None)
        self.memory.rehearsed(survivor)
        p = u.odom_from
        if p != survivor and survivor not in self._neighbours[p]:
            self._neighbours[p].append(survivor)
            self._neighbours[survivor].append(p)
        if entering:
            self.loops.append((survivor, p))
            self._loop_nodes = {survivor}
            self.memory.loop_closed()
        if self.store is not None:
            self.store.merge_node(u.node_id, survivor, v.transform, v.information)
            self.store.update_poses({u.node_id: self._pose(u.node_id)})
        if entering:
            self.on_event("loop_closed", {"from": survivor, "to": p, "inliers": v.inliers, "link": "rehearsal"})

    def _add_view(self, u: KeyframeUpdate) -> None:
        f = u.features
        if self.config.refine_dense and f.depth is not None and f.grey is not None:
            self._views[u.node_id] = DenseView(f.depth, f.grey, self.camera)

    def _remember(self, u: KeyframeUpdate) -> None:
        f = u.features
        self._features[u.node_id] = FrameFeatures(f.keypoints, f.descriptors, f.points, f.octaves)  # no images
        self._stamps[u.node_id] = u.stamp
        self._order.append(u.node_id)
        self.memory.add(u.node_id)
        self._neighbours.setdefault(u.node_id, [])
        self._segment[u.node_id] = u.node_id if u.odom_from is None else self._segment.get(u.odom_from, u.odom_from)
        if u.odom_from is not None:
            self._neighbours[u.node_id].append(u.odom_from)
            self._neighbours.setdefault(u.odom_from, []).append(u.node_id)

    # -- memory management ---------------------------------------------------------------
    def _manage_memory(self, u: KeyframeUpdate, best: int | None, update_ms: float) -> tuple[list[int], list[int]]:
        """Retrieval (LTM → WM) around the best hypothesis and the new keyframe, then transfer
        (WM → LTM) when WM is over its limits. Returns (transferred, retrieved) node ids."""
        mem = self.memory
        retrieved = []
        if self.store is not None and mem.ltm and mem.max_retrieved > 0:
            retrieved = mem.select_retrievals([best], self._neighbours)
            retrieved += [n for n in self._ltm_near(u) if n not in retrieved]
            retrieved = [n for n in retrieved[:mem.max_retrieved] if self._retrieve(n)]
        mem.retrieved(retrieved)
        transferred: list[int] = []
        if self.store is not None and mem.over_limit(update_ms):
            transferred = mem.select_transfers(update_ms, *self._protected(u))
            for n in transferred:
                self._transfer(n)
            mem.transferred(transferred)
        return transferred, retrieved

    def _ltm_near(self, u: KeyframeUpdate) -> list[int]:
        """LTM nodes the map places where the new keyframe is (within loop.proximity_radius,
        looking within proximity_angle of its way), nearest first: one R*Tree query of the
        stored poses (the graph's estimates)."""
        c = self.config
        pose = self._pose(u.node_id)
        r = c.proximity_radius
        box = (tuple(pose[:3, 3] - r), tuple(pose[:3, 3] + r))
        nodes = [n for n in self.store.nodes(bbox=box, limit=None) if n.id in self.memory.ltm]
        if not nodes:
            return []
        return nearby(np.stack([n.pose for n in nodes]), np.array([n.id for n in nodes], np.int64), pose, r,
                      c.proximity_angle, self.memory.max_retrieved).tolist()

    def _protected(self, u: KeyframeUpdate) -> tuple[set[int], set[int]]:
        """(WM nodes that stay in RAM: linked to STM and the last loop closure's; WM nodes that
        go last: those the graph places within memory.local_radius of the new keyframe)."""
        keep = set(self._loop_nodes)
        for s in self.memory.stm:
            keep.update(self._neighbours.get(s, ()))
        wm, near = self.memory.wm, set()
        if wm and self.memory_config.local_radius > 0:
            here = self._pose(u.node_id)[:3, 3]
            centres = np.stack([self.graph.pose(n)[:3, 3] for n in wm])
            close = np.linalg.norm(centres - here, axis=1) <= self.memory_config.local_radius
            near = set(np.asarray(wm)[close].tolist())
        return keep, near

    def _transfer(self, node: int) -> None:
        """WM → LTM: the node's words leave the search structures, its features leave RAM
        (everything stays in the database)."""
        with self.vocabulary.lock:
            self.vocabulary.unload_node(node)
            self.detector.forget([node])
        self._features.pop(node, None)
        self._views.pop(node, None)

    def _retrieve(self, node: int) -> bool:
        """LTM → WM: features and words back from the database (its dense view when first
        needed). False when the node cannot be loaded (it stays in LTM)."""
        try:
            keypoints, descriptors, points, word_ids = self.store.load_features(node)
        except UnknownIdError:
            return False
        self._features[node] = FrameFeatures(keypoints, descriptors, points, np.zeros(len(keypoints), np.int8))
        if node not in self.graph:  # a node of the previous map, in no graph of this mapper yet
            self._place_previous([node])
        if word_ids is not None and node not in self.vocabulary:  # an old node another mapper holds is indexed
            with self.vocabulary.lock:
                missing = self.vocabulary.missing_words(word_ids[word_ids >= 0])
                self.vocabulary.reload_node(node, word_ids, descriptors=self.store.load_words(missing) if len(missing)
                                            else None)
        if isinstance(self._views, _StoredViews):
            self._views.defer(node)
        return True

    # -- start-up on a reopened map -----------------------------------------------------------
    def _load_previous_map(self) -> None:
        """RTAB-Map's start-up on a reopened map (`Memory::loadLastNodes`,
        `Mem/InitWMWithAllNodes` false): the nodes of its ended sessions (the previous map;
        open sessions' are other mappers') go to LTM, ids only, except the newest
        `memory.max_wm_nodes` (all of them with an unlimited WM), which start in WM: their
        features (one query) and words (only their words' descriptors are read), in the
        graph at their stored poses (`_place_previous`). The old nodes' graph adjacency
        (one query, ids only) serves the loop detector's prediction and retrieval; they are
        never "recent" for transfer (the new session's nodes stay first)."""
        store = self.store
        ids = store.node_ids(ended=True)
        if not len(ids):
            return
        k = self.memory.max_wm_nodes
        first_wm = ids[-k:] if 0 < k < len(ids) else ids
        features = store.load_features_many(first_wm.tolist())
        wm = [n for n in first_wm.tolist() if n in features]  # a node without features stays in LTM
        pairs = store.link_pairs((LinkType.NEIGHBOR, LinkType.GLOBAL_CLOSURE, LinkType.LOCAL_SPACE))
        pairs = pairs[np.isin(pairs, ids).all(axis=1)]
        nb = self._neighbours
        for a, b in pairs.tolist():
            nb.setdefault(a, []).append(b)
            nb.setdefault(b, []).append(a)
        self._place_previous(wm)
        for n in wm:
            kp, desc, pts, _ = features[n]
            self._features[n] = FrameFeatures(kp, desc, pts, np.zeros(len(kp), np.int8))
            if self.config.refine_dense and isinstance(self._views, _StoredViews):
                self._views.defer(n)
        self._index_words({n: features[n][3] for n in wm})
        in_ram = set(wm)
        self.memory.restore(stm=(), wm=wm, ltm=[n for n in ids.tolist() if n not in in_ram])  # keeps weights
        self.memory.loop_closed()  # the old nodes are not "recent": they leave WM first

    def _place_previous(self, node_ids) -> None:
        """Nodes of the previous map (not in this mapper's graph) enter it at their stored
        poses, each with the tight prior: that map is already optimised, so it stays where it
        is and anchors the new session (whose first node has the loose segment prior), which a
        loop link to it places in the old map's frame. Their stamps count as older than any
        `loop.min_age`; their weights are the stored ones."""
        records = [r for r in self.store.get_nodes(node_ids) if r.id not in self.graph]
        self.graph.add_anchored({r.id: r.pose for r in records})
        for r in records:
            self._stamps[r.id] = -np.inf  # another session's: always old enough to be a candidate
            self._neighbours.setdefault(r.id, [])
            self.memory.weights[r.id] = r.weight

    def _index_words(self, words: dict) -> None:
        """Index the words of nodes ({node: word id per feature, or None}) the vocabulary
        does not hold yet, the descriptors of its missing words read in one query."""
        with self.vocabulary.lock:
            todo = {n: w for n, w in words.items() if w is not None and n not in self.vocabulary}
            if not todo:
                return
            missing = self.vocabulary.missing_words(np.concatenate([np.asarray(w, np.int64) for w in todo.values()]))
            self.vocabulary.reload_nodes(todo, descriptors=self.store.load_words(missing) if len(missing) else None)

    def _close_nearby(self, u: KeyframeUpdate, candidates: set[int], stats: LoopStatistics,
                      verified: tuple[int, Verification] | None = None) -> None:
        """Proximity detection: verify the nearest older keyframes the graph places around this
        one (looking the same way) and link the first that passes (`verified`: a candidate
        verified already, by rehearsal)."""
        c = self.config
        ids = np.fromiter(sorted(candidates - set(self._neighbours[u.node_id])), np.int64)
        if not len(ids):
            return
        poses = {i: self.graph.pose(i) for i in ids.tolist() + [u.node_id]}  # WM only, not the whole graph
        near = nearby(np.stack([poses[i] for i in ids.tolist()]), ids, poses[u.node_id], c.proximity_radius,
                      c.proximity_angle, c.proximity_max_candidates)
        for k, candidate in enumerate(near.tolist()):
            prior = invert(poses[candidate]) @ poses[u.node_id] if k == 0 and c.proximity_dense else None
            if verified is not None and verified[0] == candidate:
                v = verified[1]
                decision = self._add_link(u, candidate, LinkType.LOCAL_SPACE, v)
            else:
                decision, v = self._close_loop(u, candidate, LinkType.LOCAL_SPACE, prior)
            stats.proximity.append({"node": candidate, "decision": decision,
                                    "inliers": 0 if v is None else v.inliers, "refined": bool(v is not None and v.refined)})
            if decision == "accepted":
                return

    def _link_path(self, u: KeyframeUpdate, candidates: set[int], stats: LoopStatistics) -> None:
        """Proximity by time: register the new keyframe to recent keyframes of its own segment
        (those that are not loop candidates) that the graph places in view of it, the oldest
        first, then the one halfway along the path to it; each that passes becomes a link."""
        c = self.config
        if c.proximity_time_links <= 0:
            return
        segment = self._segment[u.node_id]
        recent = []
        for n in reversed(self._order[:-1]):  # the non-candidates are the newest keyframes
            if n in candidates or not self.memory.in_ram(n):
                break
            if self._segment[n] == segment and n not in self._neighbours[u.node_id]:
                recent.append(n)
        if not recent:
            return
        poses = {i: self.graph.pose(i) for i in recent + [u.node_id]}
        ids = np.array(recent, np.int64)
        near = np.sort(nearby(np.stack([poses[i] for i in recent]), ids, poses[u.node_id], c.proximity_radius,
                              c.proximity_angle, len(ids)))  # oldest first (node ids grow with time)
        chosen = np.unique(near[(np.arange(c.proximity_time_links) * len(near)) // c.proximity_time_links]) \
            if len(near) else near  # the oldest, then evenly towards the newest
        for candidate in chosen.tolist():
            decision, v = self._register(u, candidate)  # PnP: no dense-only links (a few cm off on textureless walls)
            if decision == "ok" and not v.refined and u.node_id in self._views and candidate in self._views:
                decision = "rejected: not refined"  # odometry is better than an unrefined PnP link
            elif decision == "ok":
                decision = self._add_link(u, candidate, LinkType.LOCAL_TIME, v)
            stats.path.append({"node": candidate, "decision": decision,
                               "inliers": 0 if v is None else v.inliers, "refined": bool(v is not None and v.refined)})

    def _register(self, u: KeyframeUpdate, candidate: int,
                  prior: np.ndarray | None = None) -> tuple[str, Verification | None]:
        """Verify a candidate (PnP, then dense refinement). With a `prior` (T_candidate_new
        from the graph) a candidate PnP refuses is also registered densely from it. Returns
        ("ok" or "rejected: why", the verification)."""
        c = self.config
        cand = self._features[candidate]
        v = verify(self.camera, u.features.keypoints, u.features.descriptors, cand.descriptors, cand.points,
                   min_inliers=c.min_inliers)
        dense = u.node_id in self._views and candidate in self._views
        if not v.accepted and prior is not None and dense:
            v = register_dense(self._views[u.node_id], self._views[candidate], prior,
                               min_overlap=c.proximity_dense_min_overlap,
                               max_correction=(c.proximity_max_correction, c.proximity_max_rotation))
            dense = False  # already dense
        if not v.accepted:
            return f"rejected: verification {v.reason}", v
        if dense:
            v = refine(v, self._views[u.node_id], self._views[candidate], min_overlap=c.refine_min_overlap,
                       max_correction=(c.refine_max_correction, c.refine_max_rotation))
        return "ok", v

    def _add_link(self, u: KeyframeUpdate, candidate: int, kind: LinkType, v: Verification) -> str:
        """Add a verified link to the graph (which may refuse it) and store it (the poses it
        moved are written at the end of the update). Returns "accepted" or "rejected: graph why"."""
        outcome = self.graph.add_loop(candidate, u.node_id, v.transform, v.information)
        if not outcome.accepted:
            return f"rejected: graph {outcome.reason}"
        if kind != LinkType.LOCAL_TIME:
            self.loops.append((candidate, u.node_id))
            self._loop_nodes = {candidate}
            self.memory.loop_closed()
            self._neighbours[u.node_id].append(candidate)
            self._neighbours[candidate].append(u.node_id)
        if self.store is not None:
            self.store.add_link(candidate, u.node_id, kind, v.transform, v.information)
        if kind != LinkType.LOCAL_TIME:
            self.on_event("loop_closed", {"from": candidate, "to": u.node_id, "inliers": v.inliers,
                                          "link": "proximity" if kind == LinkType.LOCAL_SPACE else "appearance"})
        return "accepted"

    def _publish(self, node_id: int) -> None:
        """Write the poses the graph moved (and the new keyframe's) to the database; a
        `map_corrected` event when older keyframes moved. Every update, not only after a
        link: iSAM2 keeps refining earlier poses as nodes arrive."""
        moved = self._write_moved()
        if set(moved) - {node_id}:
            self.on_event("map_corrected", {"nodes": len(moved)})

    def _write_moved(self, tolerance: tuple[float, float] | None = None) -> dict[int, np.ndarray]:
        """Write the poses the graph moved by more than `tolerance` (default: the graph's)."""
        moved = self.graph.changed_poses(tolerance)
        if moved and self.store is not None:
            self.store.update_poses(moved)
        return moved

    def _close_loop(self, u: KeyframeUpdate, candidate: int, kind: LinkType,
                    prior: np.ndarray | None = None) -> tuple[str, Verification | None]:
        """Verify a loop candidate and add the link to the graph. Returns the decision
        ("accepted" or "rejected: why") and the verification."""
        decision, v = self._register(u, candidate, prior)
        if decision == "ok":
            decision = self._add_link(u, candidate, kind, v)
        return decision, v


@dataclass
class _MergeLink:
    """The graph link merges made between two nodes: T_from_to (mean of `count` measurements)."""

    from_id: int
    to_id: int
    transform: np.ndarray
    information: np.ndarray
    count: int


def _series_information(a: np.ndarray | None, b: np.ndarray) -> np.ndarray:
    """Information of two relative poses chained (covariances add; frames not rotated: the
    links chained by rehearsal are short)."""
    if a is None:
        return b
    return np.linalg.inv(np.linalg.inv(a) + np.linalg.inv(b))


class _StoredViews(dict):
    """A resumed mapper's dense views ({node: DenseView}): those of the stored keyframes are
    decoded from their stored images when first asked for (`in` or `[]`), so that resuming
    a long session decodes only the keyframes that become loop candidates."""

    def __init__(self, store: MapStore, camera: PinholeCamera, node_ids):
        super().__init__()
        self._store, self._camera, self._stored = store, camera, set(node_ids)

    def defer(self, node_id) -> None:
        """Decode this node's view from the store when it is first asked for."""
        if not super().__contains__(node_id):
            self._stored.add(node_id)

    def pop(self, node_id, default=None):
        self._stored.discard(node_id)
        return super().pop(node_id, default)

    def _load(self, node_id) -> None:
        if node_id not in self._stored:
            return
        self._stored.discard(node_id)
        try:
            image, depth = decode_images(*self._store.load_images(node_id))
        except Exception as e:  # a bad image costs the dense refinement of this keyframe only
            log.warning("node %d: stored images not usable for dense registration: %s", node_id, e)
            return
        if image is not None and depth is not None:
            self[node_id] = DenseView(depth, image, self._camera)

    def __contains__(self, node_id) -> bool:
        self._load(node_id)
        return super().__contains__(node_id)

    def __getitem__(self, node_id):
        self._load(node_id)
        return super().__getitem__(node_id)

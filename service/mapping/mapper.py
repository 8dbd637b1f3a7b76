"""The map update behind tracking: for each new keyframe, vocabulary → loop hypothesis
(Bayes filter) → geometric verification → pose-graph optimisation (iSAM2) → corrected
poses to storage and a `map corrected` event.

Tracking never waits for it: in the service the mapper runs on its own thread and takes
keyframes from a queue (RTAB-Map's map update runs at its detection rate, ORB-SLAM's loop
closing in parallel to tracking). Offline runs call it synchronously so a run stays
bit-for-bit reproducible. The mapper owns the map→odometry correction that turns the
odometry's poses into map poses, the loop detector and the pose graph; memory
(`service.memory.manager.Memory`) owns the keyframes' life cycle (STM / WM / LTM, rehearsal's
merges), the vocabulary and the feature and view caches, and the mapper calls it through its
methods: it reports what the update did, places in its graph the nodes memory brings in (a
previous map's, a resumed session's) and has its detector forget the nodes memory transfers."""
from __future__ import annotations

import collections
import dataclasses
import logging
import queue
import threading
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from mnemoslam.client.kernel.frames import PinholeCamera
from mnemoslam.client.kernel.geometry import invert, nearby, rotation_angle
from mnemoslam.storage import LinkType, MapUpdateStore

from ..config import LoopConfig, MemoryConfig
from ..memory.manager import Memory, Place, series_information
from ..memory.vocabulary import Vocabulary
from ..tracking.features import FrameFeatures
from ..tracking.matching import match_descriptors
from .graph import PoseGraph
from .link_refinement import refine_link
from .live import LiveMaps
from .local_ba import LocalBundleAdjustment
from .loop_detection import LoopDetector
from .merge_links import MergeLinks
from .verification import Verification, refine, register_dense, verify

log = logging.getLogger("mnemoslam.mapping")

RELOCALIZATION_SCORED = 20  # the older maps' best-scoring nodes a relocalization groups into places
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
    # per feature: the tracker's stable local-map point id or -1 (local BA's tracks); None: unknown
    point_ids: np.ndarray | None = None


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
    sigma: list | None = None  # [m, deg] largest standard deviations of the link's estimate (two-view refinement)
    proximity: list = field(default_factory=list)  # [{node, decision, inliers, refined}] spatial candidates
    path: list = field(default_factory=list)  # [{node, decision, inliers, refined}] recent keyframes of its own path
    # [{node, score, decision, inliers, sigma}] older maps' candidates of a keyframe whose map has not joined them
    relocalization: list = field(default_factory=list)
    # {node, similarity, inliers, distance, rotation, decision}: the node it was or wasn't merged into
    rehearsal: dict = field(default_factory=dict)
    timings_ms: dict = field(default_factory=dict)
    memory: dict = field(default_factory=dict)  # after the update: stm, wm, ltm sizes, transferred/retrieved ids, words
    # {keyframes, points, observations, depth_scale, ms}: the local BA that refined its odometry link
    local_ba: dict = field(default_factory=dict)


@dataclass
class Evidence:
    """A relocalization link verified but not added yet: keyframe `node` seen from the older
    map's `candidate` (its verification `v`), and where that puts the keyframe's map in the
    older one, `T_map_own` = candidate's map pose · T_candidate_node · (node's own pose)⁻¹."""

    node: int
    candidate: int
    v: Verification
    T_map_own: np.ndarray
    peer: Mapper | None = None  # the map update running at the same time the candidate is of (None: an older map's)


@dataclass
class Rehearsal:
    """What rehearsal did for one keyframe: the node it merged into (None: it becomes a node),
    and a verified link to a node it did not merge into, (node, verification), which
    proximity detection reuses."""

    survivor: int | None = None
    verified: tuple[int, Verification] | None = None


class Mapper:
    def __init__(self, camera: PinholeCamera, config: LoopConfig, store: MapUpdateStore | None = None,
                 on_event: Callable[[str, dict], None] | None = None, background: bool = False,
                 memory: MemoryConfig | None = None, previous_map: bool = True, live: bool = True):
        self.camera = camera
        self.config = config
        self.memory_config = mc = memory if memory is not None else MemoryConfig()
        self.on_event = on_event or (lambda kind, data: None)
        # STM / WM / LTM: which keyframes are loop candidates, with their features, words and views
        # in RAM, and the map's vocabulary (shared by every mapper of that store)
        self.memory = Memory(mc, config, store, camera)
        self.detector = LoopDetector(self.vocabulary, loop_threshold=config.threshold, stm_size=mc.stm_size)
        self.graph = PoseGraph(max_error=config.optimize_max_error)
        self.merge_links = MergeLinks(self.graph)  # rehearsal's: one graph link per pair of nodes
        self.local_ba = LocalBundleAdjustment(
            camera, config.local_ba_window, config.local_ba_fixed, config.local_ba_iterations,
            config.local_ba_depth_weight, config.local_ba_adaptive_depth, config.local_ba_min_points,
            fuse=config.local_ba_fuse) \
            if config.local_ba else None
        self._correction = np.eye(4)  # T_map_odom
        self._lock = threading.Lock()
        self.loops: list[tuple[int, int]] = []
        # verified loop / proximity links refused as inaccurate (their estimated σ beyond loop.link_max_sigma_*)
        self.links_dropped = 0
        # the statistics of the last STATISTICS_KEPT updates (every update's are in the database)
        self.statistics: collections.OrderedDict[int, LoopStatistics] = collections.OrderedDict()
        # relocalization links verified for the last keyframes (loop.relocalize_window), not added yet
        self._evidence: collections.deque[list[Evidence]] = collections.deque(maxlen=max(config.relocalize_window, 1))
        self._queue: queue.Queue | None = None
        # the map updates running at the same time on this store (other robots', `mapping.live`):
        # a synchronous mapper relocalizes against them too; `_host` is the one whose map this
        # one's joined (its frame is the host's from then on), `_foreign` the host's nodes placed
        # in this graph (anchored where the host had them; the host writes their poses, never this)
        # (`live`: False for a map update that is no robot's now: a resumed session, a localizer)
        self._live = LiveMaps.for_store(store) \
            if live and store is not None and not background and config.relocalize_live else None
        self._host: Mapper | None = None
        self._foreign: set[int] = set()
        if self._live is not None:
            self._live.register(self)
        self.submitted = 0  # keyframe updates handed to the map update ...
        self.mapped = 0  # ... and done (the difference is the backlog)
        if store is not None and previous_map:
            self._place(self.memory.load_previous())  # the previous map's WM nodes, where they are
        if background:
            self._queue = queue.Queue()
            self._thread = threading.Thread(target=self._run, name="mapper", daemon=True)
            self._thread.start()

    @classmethod
    def resume(cls, store: MapUpdateStore, session_id: int, config: LoopConfig, camera: PinholeCamera | None = None,
               on_event: Callable[[str, dict], None] | None = None, memory: MemoryConfig | None = None) -> "Mapper":
        """A (synchronous) mapper that continues a stored session's map update, e.g. after
        the service was killed with keyframes still in its backlog. It holds the session's
        mapped keyframes (those with a statistics row) as the interrupted mapper did
        (`Memory.resume`); the map's vocabulary comes from the store as for any mapper.
        Then `submit` the session's unmapped keyframes in id order (see
        `stored_update`) and they close loops to the mapped ones. The loop
        detector's belief starts afresh and `to_map` gives the identity until the first
        update. `camera` defaults to the session's."""
        if camera is None:
            camera = Memory.session_camera(store, session_id)
        m = cls(camera, config, store, on_event=on_event, memory=memory, previous_map=False, live=False)
        r = m.memory.resume(session_id)
        m.graph.restore(r.poses, r.odometry, r.loops)
        m._place(r.previous)
        for a, b, t, info in r.across:
            m.graph.add_loop(a, b, t, info, check=False)  # checked when it was added
        for a, b, t, info in r.merge_links:  # as rehearsal made them (checked then)
            m.merge_links.add(a, b, t, info, check=False)
        m.loops = r.closures
        return m

    def stored_update(self, node_id: int, images: bool = True) -> KeyframeUpdate:
        """The update tracking handed over for a stored keyframe, rebuilt from the database
        (`Memory.stored_keyframe`): its stamp and stored pose (the odometry's until the map
        update moves it), features, odometry link and, with `images`, the depth and grey image
        decoded from its stored images (for dense refinement)."""
        k = self.memory.stored_keyframe(node_id, images)
        odom = k.odometry
        return KeyframeUpdate(k.node.id, k.node.stamp, k.node.pose, k.features, odom.from_id if odom else None,
                              odom.transform if odom else None, odom.information if odom else None)

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
        if self._live is not None:
            self._live.unregister(self)
        self.flush_poses()

    def root(self) -> int | None:
        """The root (oldest node) of the map its newest keyframe is in, None before the first
        (`mapping.live`: of two robots' maps the one with the larger root joins the other)."""
        newest = self.memory.newest
        return None if newest is None else self.memory.root(newest)

    @property
    def vocabulary(self) -> Vocabulary:
        """The map's vocabulary (memory's), which the loop detector searches."""
        return self.memory.vocabulary

    @property
    def merged(self) -> int:
        """Keyframes merged into a node by rehearsal (they are not nodes of the map)."""
        return len(self.memory.merged)

    def pose(self, node: int) -> np.ndarray:
        """A keyframe's map pose: its node's, or for a merged keyframe where its survivor sees it."""
        merged = self.memory.merged.get(node)
        if merged is not None:
            survivor, t = merged
            return self.graph.pose(survivor) @ t
        return self.graph.pose(node)

    def keyframe_poses(self) -> dict[int, np.ndarray]:
        """Every keyframe's map pose: the graph's nodes, and each merged keyframe where its
        survivor sees it."""
        poses = self.graph.poses()
        poses.update({m: poses[c] @ t for m, (c, t) in self.memory.merged.items() if c in poses})
        return poses

    def retrieve(self, nodes: list[int]) -> list[int]:
        """LTM → WM (`Memory.retrieve`); a node of the previous map enters the graph at its
        stored pose. Returns the nodes retrieved."""
        retrieved, previous = self.memory.retrieve(nodes)
        for node, pose in previous.items():  # one by one, as they were retrieved
            self._place({node: pose})
        return retrieved

    def _place(self, poses: dict[int, np.ndarray]) -> None:
        """Nodes of the previous map enter the graph at their stored poses ({id: 4×4}), each
        with the tight prior: that map is already optimised, so it stays where it is and
        anchors the new session (whose first node has the loose segment prior), which a loop
        link to it places in the old map's frame."""
        self.graph.add_anchored(poses)

    def flush_poses(self) -> None:
        """Write every pose that moved at all since it was last written (the graph reports only
        moves above its tolerance), and the merged keyframes' poses, so that the database
        holds the graph's final estimate."""
        self._write_moved((0.0, 0.0))
        if self.memory.merged:
            self.memory.save_poses({m: self.pose(m) for m in self.memory.merged})

    # -- map update ------------------------------------------------------------------------
    def _run(self) -> None:
        while True:
            assert self._queue is not None  # the background thread runs with its queue
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
        """One keyframe: merged into the node the map has where it was taken (rehearsal), or a
        new node with its loop closures (each optimises the graph); then memory management
        (retrieval, transfer), the update published, and the new map→odometry correction."""
        t0 = time.perf_counter()
        ba = self._bundle_adjust(u)
        if ba is not None:
            u = ba[0]
        u = self.memory.through_merges(u)
        self.memory.add_view(u)
        stats = LoopStatistics(u.node_id)
        if ba is not None:
            stats.local_ba = ba[1]
        r = self._rehearse(u, stats) if self.memory_config.rehearsal and u.odom_from is not None else Rehearsal()
        t1 = time.perf_counter()
        best = r.survivor if r.survivor is not None else self._add_keyframe(u, stats, r.verified)
        t2 = time.perf_counter()
        transferred, retrieved = self._manage_memory(u.node_id, best, (t2 - t0) * 1e3, r.survivor is not None)
        stats.timings_ms["rehearsal"] = (t1 - t0) * 1e3 - stats.local_ba.get("ms", 0.0)
        stats.timings_ms["local_ba"] = stats.local_ba.get("ms", 0.0)
        stats.timings_ms["memory"] = (time.perf_counter() - t2) * 1e3
        stats.memory = self.memory.statistics(u.stamp, transferred, retrieved, r.survivor)
        self._publish(stats)
        with self._lock:
            self._correction = self.pose(u.node_id) @ invert(u.odom_pose)

    def _manage_memory(self, node: int, best: int | None, update_ms: float,
                       merged: bool = False) -> tuple[list[int], list[int]]:
        """After the update of keyframe `node` that took `update_ms` (RTAB-Map's memory
        management): retrieval (LTM → WM) around the best loop hypothesis and the keyframe,
        then transfer (WM → LTM) when WM is over its limits, which the loop detector forgets
        (its belief is this mapper's alone: no lock; the shared vocabulary's words memory
        unloaded under its lock); nothing is retrieved after a keyframe `merged` by rehearsal
        (it found its place). Returns (transferred, retrieved) node ids."""
        retrieved = self.retrieve(self.memory.to_retrieve(node, best, self.pose, merged))
        transferred = self.memory.transfer(node, update_ms, self.pose)
        if transferred:
            self.detector.forget(transferred)
        return transferred, retrieved

    def _add_keyframe(self, u: KeyframeUpdate, stats: LoopStatistics,
                      verified: tuple[int, Verification] | None = None) -> int | None:
        """The keyframe becomes a node: graph, memory, vocabulary, then loop closure by
        appearance, by space and along its path (`verified`: a link rehearsal verified but did
        not merge). Returns the best loop hypothesis (for retrieval)."""
        t0 = time.perf_counter()
        self.graph.add_node(u.node_id, u.odom_pose, u.odom_from, u.transform, u.information)
        self.memory.add(u)
        t1 = time.perf_counter()
        words = self.memory.add_words(u.node_id, u.features.descriptors)  # + its new words, one commit
        t2 = time.perf_counter()
        candidates = self.memory.candidates(u.stamp, self.config.min_age)
        with self.vocabulary.lock:  # other robots' mappers add to the same vocabulary
            hyp = self.detector.process(u.node_id, words, self.memory.neighbours, candidates)
        t3 = time.perf_counter()
        stats.hypothesis, stats.posterior = hyp.best_id, float(hyp.posterior)
        stats.likelihood_top = [(int(i), float(s)) for i, s in hyp.likelihood[:5]]
        stats.decision = "none" if hyp.best_id is None else ("accepted" if hyp.accepted else f"rejected: {hyp.reason}")
        # other robots mapping at the same time whose maps this one's may join (`mapping.live`)
        peers = self._live.peers(self) if self._live is not None and self._host is None and self.config.relocalize \
            else []
        relocalizing = self.config.relocalize and self._host is None and (
            self.memory.relocalizing(u.node_id) or bool(peers))
        hint = None
        if hyp.accepted and relocalizing and hyp.best_id is not None and self.memory.in_older_map(hyp.best_id):
            # into an older map this keyframe's has not joined: verified with the relocalization's
            # candidates, never joined on one link
            hint, stats.decision = hyp.best_id, "relocalization candidate"
        elif hyp.accepted:
            assert hyp.best_id is not None  # an accepted hypothesis has a node
            stats.decision, v = self._close_loop(u, hyp.best_id, LinkType.GLOBAL_CLOSURE)
            if v is not None:
                stats.matches, stats.inliers, stats.refined = v.matches, v.inliers, v.refined
                stats.sigma = _rounded_sigma(v)
        if relocalizing:
            t = time.perf_counter()
            self._relocalize(u, stats, hint, words, peers)
            stats.timings_ms["relocalization"] = (time.perf_counter() - t) * 1e3
        t4 = time.perf_counter()
        if self.config.proximity_by_space:
            self._close_nearby(u, candidates, stats, verified)
        t5 = time.perf_counter()
        if self.config.proximity_by_time:
            self._link_path(u, candidates, stats)
        t6 = time.perf_counter()
        relocalization = stats.timings_ms.get("relocalization", 0.0)  # (a step of its own)
        stats.timings_ms = {**stats.timings_ms, "graph": (t1 - t0) * 1e3, "vocabulary": (t2 - t1) * 1e3,
                            "detection": (t3 - t2) * 1e3,
                            "verification_optimization": (t4 - t3) * 1e3 - relocalization,
                            "proximity": (t5 - t4) * 1e3, "path": (t6 - t5) * 1e3}
        return hyp.best_id

    # -- local bundle adjustment ---------------------------------------------------------------
    def _bundle_adjust(self, u: KeyframeUpdate) -> tuple[KeyframeUpdate, dict] | None:
        """Add the keyframe to the local BA's window and solve it (`loop.local_ba`): the
        keyframe's odometry link becomes the refined relative pose to the keyframe before it
        (same information), and with `loop.local_ba_relink` so do the graph's odometry links
        between the window's older keyframes. A link the BA moves more than
        local_ba_max_correction / _rotation from the tracker's is left as the tracker made it.
        Returns (the update, what the BA did) or None when it is off or did not solve."""
        if self.local_ba is None:
            return None
        t0 = time.perf_counter()
        f = u.features
        ba = self.local_ba
        continues = u.odom_from is not None and bool(ba.keyframes) and ba.keyframes[-1].node_id == u.odom_from
        matched = ba.add(u.node_id, u.odom_pose, f.keypoints, f.descriptors, f.points, f.pixel_sigmas(), f.depth_sigma,
                         u.point_ids, continues)
        res = ba.solve() if continues else None
        if res is None:
            return None
        assert u.odom_from is not None  # solved: the window continued from it
        c = self.config
        links = {}
        kfs = list(ba.keyframes)
        for a, b in zip(kfs[c.local_ba_fixed - 1:-1], kfs[c.local_ba_fixed:]):
            T = invert(res.poses[a.node_id]) @ res.poses[b.node_id]
            correction = invert(invert(a.pose) @ b.pose) @ T  # against the tracker's link
            if (np.linalg.norm(correction[:3, 3]) <= c.local_ba_max_correction
                    and np.degrees(rotation_angle(correction[:3, :3])) <= c.local_ba_max_rotation):
                links[(a.node_id, b.node_id)] = T
        relinked = self.graph.replace_odometry(
            {k: v for k, v in links.items() if k[1] != u.node_id}) if c.local_ba_relink else []
        # the database keeps the links the graph has (a reload, the link report): the window's
        # older links and (below) the keyframe's own, which tracking stored as the tracker's
        stored = [(lk.from_id, lk.to_id, lk.transform, lk.information) for lk in relinked]
        info = {"keyframes": res.keyframes, "matched": matched, "points": res.points,
                "observations": res.observations, "depth_observations": res.depth_observations,
                "depth_scale": round(res.depth_scale, 3), "error_before": res.error_before,
                "error_after": res.error_after, "relinked": len(relinked), "ms": (time.perf_counter() - t0) * 1e3,
                "timings_ms": res.timings_ms}
        T = links.get((u.odom_from, u.node_id))
        if T is not None:
            stored.append((u.odom_from, u.node_id, T, u.information))
            u = dataclasses.replace(u, transform=T)
        for a, b, T_ab, information in stored:
            self.memory.save_link(a, b, LinkType.NEIGHBOR, T_ab, information, replace=True)
        return u, info

    # -- rehearsal ---------------------------------------------------------------------------
    def _rehearse(self, u: KeyframeUpdate, stats: LoopStatistics) -> Rehearsal:
        """RTAB-Map's rehearsal, against the map rather than the last node only: the
        WM node nearest to where odometry puts the keyframe (within twice the merge distance
        and rotation) is its survivor when the two share `memory.rehearsal_similarity` of
        their visual words, registration puts them within `memory.rehearsal_max_distance` /
        `rehearsal_max_rotation`, and the graph accepts the link from the previous keyframe
        to the survivor (it replaces the odometry link to the keyframe). The keyframe is then
        merged: no node, no words; the survivor's weight grows. Returns the survivor (None: the
        keyframe becomes a node) and what was verified on the way."""
        # the caller's condition; an odometry link comes with its transform and information
        assert u.odom_from is not None and u.transform is not None and u.information is not None
        c = self._rehearsal_candidate(u)
        if c is None:
            return Rehearsal()
        mc = self.memory_config
        t0 = time.perf_counter()
        place = self.memory.place(c)
        if place is None:
            return Rehearsal()
        similarity = self._similarity(u.features.descriptors, place.words)
        t1 = time.perf_counter()
        r = stats.rehearsal = {"node": c, "similarity": round(similarity, 3), "search_ms": (t1 - t0) * 1e3}
        if not self.memory.tiers.in_ram(c):
            r["ltm"] = True  # a place in LTM, read from the database (not retrieved)
        if similarity < mc.rehearsal_similarity:
            r["decision"] = "rejected: similarity"
            return Rehearsal()
        decision, v = self._register(u, c, place=place)
        r["inliers"] = 0 if v is None else v.inliers
        r["verify_ms"] = (time.perf_counter() - t1) * 1e3
        if decision != "ok":
            r["decision"] = decision
            return Rehearsal()
        assert v.transform is not None and v.information is not None  # accepted: both set
        r["distance"] = float(np.linalg.norm(v.transform[:3, 3]))
        r["rotation"] = float(rotation_angle(v.transform[:3, :3]))
        if r["distance"] > mc.rehearsal_max_distance or r["rotation"] > mc.rehearsal_max_rotation:
            r["decision"] = "rejected: too far"
            return Rehearsal(None, (c, v))
        p = u.odom_from
        if p != c:
            outcome = self.merge_links.add(p, c, u.transform @ invert(v.transform),
                                           series_information(u.information, v.information))
            r["graph_ms"] = outcome.duration_ms
            if not outcome.accepted:
                r["decision"] = f"rejected: graph {outcome.reason}"
                return Rehearsal(None, (c, v))
        r["decision"] = "merged"
        # came back to c's part of the map?
        r["loop"] = entering = self.memory.merge(u.node_id, c, p, v.transform, v.information)
        self.memory.save_poses({u.node_id: self.pose(u.node_id)})
        if entering:
            self.loops.append((c, p))
            self.on_event("loop_closed", {"from": c, "to": u.node_id, "inliers": v.inliers,
                                          "link": LinkType.MERGED.label})
        return Rehearsal(c)

    def _rehearsal_candidate(self, u: KeyframeUpdate) -> int | None:
        """The WM or LTM node closest to where odometry puts the keyframe, by distance over
        rehearsal_max_distance plus rotation over rehearsal_max_rotation, if that is < 4
        (e.g. both within twice their limit). Not STM: the newest keyframes are the path just
        walked, one keyframe spacing apart (merging a keyframe into the one before replaces
        odometry by a registration: 7-Scenes 4.15 -> 5.43 cm); a revisit finds older ones.
        LTM's nodes there come from the database's spatial index (with working memory
        bounded a revisited place is mostly in LTM: it would become a node again)."""
        mc = self.memory_config
        assert u.odom_from is not None  # _rehearse's condition
        where = self.graph.pose(u.odom_from) @ u.transform
        nodes = [n for n in self.memory.tiers.wm if n in self.vocabulary and n not in self._foreign]
        nodes += self.memory.ltm_near(where, 4 * mc.rehearsal_max_distance)
        # in the keyframe's own map: another map's coordinates coincide with its own by chance
        ram = self.memory.same_map(u.odom_from, nodes)
        if not ram:
            return None
        poses = np.stack([self.graph.pose(n) for n in ram])
        dist = np.linalg.norm(poses[:, :3, 3] - where[:3, 3], axis=1)
        turn = rotation_angle(np.swapaxes(poses[:, :3, :3], 1, 2) @ where[:3, :3])
        score = dist / mc.rehearsal_max_distance + turn / mc.rehearsal_max_rotation
        k = int(np.argmin(score))
        return ram[k] if score[k] < 4.0 else None

    def _similarity(self, descriptors: np.ndarray, theirs: np.ndarray) -> float:
        """Shared words / the larger node's words (RTAB-Map's Signature::compareTo): the
        keyframe's descriptors matched against the node's words only (`theirs`, their
        descriptors: nearest word within the vocabulary's distance and ratio, one descriptor
        per word), not searched in the whole vocabulary: a few hundred by a few hundred
        Hamming distances instead of a search."""
        shared, _ = match_descriptors(descriptors, theirs, self.vocabulary.nndr, self.vocabulary.max_distance)
        return len(shared) / max(len(descriptors), len(theirs), 1)

    def _close_nearby(self, u: KeyframeUpdate, candidates: set[int], stats: LoopStatistics,
                      verified: tuple[int, Verification] | None = None) -> None:
        """Proximity detection (RTAB-Map's RGBD/ProximityBySpace): verify the nearest older
        keyframes the graph places around this one (looking the same way) and link the first
        that passes (`verified`: a candidate verified already, by rehearsal). Appearance fails
        where there is little texture or where the same view comes back from a slightly
        different angle; a keyframe the graph places close to an older one is worth a
        geometric check, the same as for appearance hypotheses, so a wrong guess costs time,
        never a false link."""
        c = self.config
        # in the keyframe's own map only: maps join by appearance (a new session's frame starts at
        # the identity, numerically where the old map's nodes are, and relates to nothing there)
        ids = np.array(sorted(self.memory.same_map(u.node_id, candidates - set(self.memory.neighbours[u.node_id]))),
                       np.int64)
        if not len(ids):
            return
        poses = {i: self.graph.pose(i) for i in ids.tolist() + [u.node_id]}  # WM only, not the whole graph
        near = nearby(np.stack([poses[i] for i in ids.tolist()]), ids, poses[u.node_id], c.proximity_radius,
                      c.proximity_angle, c.proximity_max_candidates)
        for k, candidate in enumerate(near.tolist()):
            prior = invert(poses[candidate]) @ poses[u.node_id] if k == 0 and c.proximity_dense else None
            if verified is not None and verified[0] == candidate:
                decision, v = self._accurate(u, candidate, verified[1])
                if decision == "ok":
                    decision = self._add_link(u, candidate, LinkType.LOCAL_SPACE, v)
            else:
                decision, v = self._close_loop(u, candidate, LinkType.LOCAL_SPACE, prior)
            stats.proximity.append({"node": candidate, "decision": decision,
                                    "inliers": 0 if v is None else v.inliers,
                                    "refined": bool(v is not None and v.refined), "sigma": _rounded_sigma(v)})
            if decision == "accepted":
                return

    # -- relocalization ----------------------------------------------------------------------
    def _relocalize(self, u: KeyframeUpdate, stats: LoopStatistics, hint: int | None = None,
                    words: np.ndarray | None = None, peers: list[Mapper] | None = None) -> None:
        """A keyframe whose map has joined none of the older maps (`Memory.relocalizing`):
        the older maps' nodes that look most like it (`Memory.relocalization_candidates`, and
        `hint`, an appearance hypothesis into one of them) are verified by PnP with
        loop.relocalize_min_inliers and made accurate or dropped (`_accurate`), nodes in LTM
        from their stored data without retrieving them. Each verified link is evidence of
        where this map lies in the older one; the maps join (`_join`) only when two agree:
        two candidates of this keyframe, or this keyframe's and one of the last
        loop.relocalize_window keyframes' of its map, within loop.relocalize_agreement /
        _rotation. One link, however well verified, can be a place that looks like another.

        `peers`: other robots' map updates running at the same time whose maps this one's may
        join (`mapping.live`); their keyframes in RAM are scored with this keyframe's `words`
        in the shared vocabulary and compete with the older maps' by score, verified from the
        peer's RAM at the peer's current poses. Links agree only within one frame (one peer,
        or the older maps)."""
        c = self.config
        found = self.memory.relocalization_candidates(u.features.descriptors, RELOCALIZATION_SCORED) \
            if self.memory.relocalizing(u.node_id) else []
        live: dict[int, Mapper] = {}  # candidate -> the peer it is of
        if peers and words is not None:
            found = found + self._live_candidates(words, peers, live)
            found.sort(key=lambda f: -f[1])  # (stable: the older maps' order among equal scores)
            found = found[:RELOCALIZATION_SCORED]
        scores = {n: s for n, s, _ in found}
        places: list[list[tuple[int, np.ndarray]]] = []  # the candidates by place (in one frame), best first
        for n, _, centre in found:
            for group in places:
                if live.get(group[0][0]) is live.get(n) and \
                        np.linalg.norm(group[0][1] - centre) <= c.relocalize_place_radius:
                    group.append((n, centre))
                    break
            else:
                places.append([(n, centre)])
        order = [n for n, _ in places[0][:c.relocalize_candidates]] if places else []
        order += [p[0][0] for p in places[1:c.relocalize_places]]
        if hint is not None and hint not in order:
            order.insert(0, hint)
        evidence: list[Evidence] = []
        own = self.graph.pose(u.node_id)
        stored = self.memory.stored_poses([n for n in order if n not in self.graph and n not in live])
        for candidate in order:
            peer = live.get(candidate)
            if peer is not None:
                place = peer.memory.place(candidate)  # in its RAM: its features and dense view
            else:
                place = None if self.memory.tiers.in_ram(candidate) else self.memory.place(candidate)
            if place is None and (peer is not None or not self.memory.tiers.in_ram(candidate)):
                decision, v = "rejected: no features", None
            else:
                decision, v = self._register(u, candidate, place=place, min_inliers=c.relocalize_min_inliers)
                dense = u.node_id in self.memory.views and (
                    candidate in self.memory.views if place is None else place.view is not None)
                if decision == "ok" and dense and not v.refined:
                    # RGB-D: the two keyframes' whole depth and images must agree too, not only the
                    # matched features (a repeated poster matches as well as the right one)
                    decision = "rejected: not refined densely"
                if decision == "ok":
                    decision, v = self._accurate(u, candidate, v, None if place is None else place.features)
                if decision == "ok" and peer is not None and place is not None:
                    decision = self._verified_back(u, candidate, place, peer)
            if decision == "ok":
                assert v is not None and v.transform is not None  # verified
                pose: np.ndarray | None = peer.pose(candidate) if peer is not None else \
                    self.graph.pose(candidate) if candidate in self.graph else stored.get(candidate)
                if pose is None:
                    decision = "rejected: no pose"
                else:
                    evidence.append(Evidence(u.node_id, candidate, v, pose @ v.transform @ invert(own), peer))
                    decision = "verified"
            r = {"node": candidate, "score": round(scores.get(candidate, 0.0), 5),
                 "decision": decision, "inliers": 0 if v is None else v.inliers,
                 "sigma": _rounded_sigma(v), "refined": bool(v is not None and v.refined)}
            if peer is not None:
                r["live"] = True  # another robot's keyframe, mapping at the same time
            stats.relocalization.append(r)
        if any(a.peer is b.peer and not self._agree(a, b) for i, a in enumerate(evidence) for b in evidence[i + 1:]):
            # the keyframe verified at two places of the older maps that disagree: a place that looks
            # like another (repeated textures); none of its links is evidence
            for r in stats.relocalization:
                if r["decision"] == "verified":
                    r["decision"] = "ambiguous"
            evidence = []
        earlier = [e for batch in self._evidence for e in batch
                   if self.memory.same_map(u.node_id, [e.node]) and e.node in self.graph
                   and (e.peer is None or e.peer in (peers or []))]
        self._evidence.append(evidence)
        pair = self._agreeing(evidence, earlier)
        if pair is None:
            return
        if self._join(*pair):
            for r in stats.relocalization:
                if r["node"] in (pair[0].candidate, pair[1].candidate) and r["decision"] == "verified":
                    r["decision"] = "joined"
            self._evidence.clear()
            self.memory.release_relocalization()
        else:
            for r in stats.relocalization:
                if r["node"] == pair[0].candidate:
                    r["decision"] = "rejected: graph"

    def _agreeing(self, now: list[Evidence], earlier: list[Evidence]) -> tuple[Evidence, Evidence] | None:
        """The first pair of relocalization links that agree: one of this keyframe's (`now`,
        best first) with another of its own or one of the last keyframes' (`earlier`) to a
        different older node: both put one of the two keyframes at the same place of the
        older map (loop.relocalize_agreement / _rotation). Into a peer's map (another robot
        mapping now) the two links must come from two different keyframes of this map: the
        search runs both ways there, against a map that grows, and one keyframe of `loop`
        facing the hall's identical posters verified two keyframes of `straight` 7 m away,
        both ways and in agreement (the posters' negative control with both mapping at once)."""
        for i, a in enumerate(now):
            for b in now[i + 1:] + earlier[::-1]:
                if b.candidate != a.candidate and b.peer is a.peer and (a.peer is None or a.node != b.node) \
                        and self._agree(a, b):
                    return a, b
        return None

    def _agree(self, a: Evidence, b: Evidence) -> bool:
        """Whether two relocalization links put a's keyframe at the same place of the older map
        (within loop.relocalize_agreement / _rotation)."""
        c = self.config
        own = self.graph.pose(a.node)
        d = invert(a.T_map_own @ own) @ (b.T_map_own @ own)
        return bool(np.linalg.norm(d[:3, 3]) <= c.relocalize_agreement
                    and np.degrees(rotation_angle(d[:3, :3])) <= c.relocalize_agreement_rotation)

    def _join(self, first: Evidence, second: Evidence) -> bool:
        """Join this map to the older one with two agreeing relocalization links: their older
        nodes retrieved into WM (and the graph, at their stored poses), the new keyframe's link
        added first (it places the map: the segment's loose prior gives way), then the other,
        which the graph checks; if it refuses it, the first goes too and nothing is joined.
        Into a peer's map (another robot mapping now, `mapping.live`): its two nodes enter
        this graph anchored at the peer's current poses (`_adopt`), and on success this map
        update's frame is the peer's (`_host`) and it stops relocalizing."""
        peer = first.peer
        if peer is not None and (peer.root() or 0) > (self.root() or 0):
            return peer._joined_by(self, first, second)  # the newer map joins: the peer's
        if peer is not None:
            self._adopt(peer, [first.candidate, second.candidate])
            self.graph.loosen_first()  # this map's frame gives way to the peer's
        else:
            self.retrieve([e.candidate for e in (first, second) if not self.memory.tiers.in_ram(e.candidate)])
        if first.candidate not in self.graph or second.candidate not in self.graph:
            return False
        if not self._add_join_links(first, second):
            return False
        if peer is not None:
            assert self._live is not None  # a peer comes from the registry
            self._live.joined(self, peer)
            self._host = peer
            log.info("relocalized: keyframe %d joined the map of a robot mapping at the same time through %d "
                     "and %d (keyframe %d)", first.node, first.candidate, second.candidate, second.node)
            return True
        log.info("relocalized: keyframe %d joined the older map through %d and %d (keyframe %d)",
                 first.node, first.candidate, second.candidate, second.node)
        return True

    def _add_join_links(self, first: Evidence, second: Evidence) -> bool:
        """A join's two links into the graph, which checks each (if it refuses one, neither
        stays); then into the database in one transaction (a kill between two writes would
        leave the map joined by one link) and memory. Whether they were added."""
        links: list[tuple[int, int, np.ndarray]] = []
        for e in (first, second):
            assert e.v.transform is not None and e.v.information is not None  # verified
            outcome = self.graph.add_loop(e.candidate, e.node, e.v.transform, e.v.information)
            if not outcome.accepted:
                for a, b, t in links:
                    self.graph.remove_loop(a, b, t)
                return False
            links.append((e.candidate, e.node, e.v.transform))
        self.memory.save_links([(e.candidate, e.node, LinkType.GLOBAL_CLOSURE, e.v.transform, e.v.information)
                                for e in (first, second)])
        for e in (first, second):
            self._record_link(e.node, e.candidate, LinkType.GLOBAL_CLOSURE, e.v, stored=True)
        return True

    def _joined_by(self, host: Mapper, first: Evidence, second: Evidence) -> bool:
        """The host (another robot's map update, running now, whose map is older) verified two
        agreeing links from its keyframes to this map's nodes: this map joins the host's.
        The host's keyframes enter this graph anchored at its poses (`_adopt`), the links are
        added here (the graph may refuse them, then nothing is joined), the poses they moved
        are written and this map update's frame is the host's from then on."""
        self._adopt(host, [first.node, second.node])
        if first.node not in self.graph or second.node not in self.graph:
            return False
        self.graph.loosen_first()  # this map's frame gives way to the host's
        if not self._add_join_links(first, second):
            return False
        assert self._live is not None  # a host comes from the registry
        self._live.joined(self, host)
        self._host = host
        self._evidence.clear()
        self.memory.release_relocalization()
        moved = self._write_moved()
        if moved:
            self.on_event("map_corrected", {"nodes": len(moved)})  # (docs/service.md: the nodes moved)
        log.info("relocalized: the map of a robot mapping at the same time found this map's keyframes %d and %d "
                 "from its keyframes %d and %d: this map joined it", first.candidate, second.candidate,
                 first.node, second.node)
        return True

    def _verified_back(self, u: KeyframeUpdate, candidate: int, place: Place, peer: Mapper) -> str:
        """A live candidate verified the other way too: the peer's keyframe registered to this
        one (PnP, and for RGB-D the dense refinement must succeed), as the peer's map update
        would verify it. Registration is not symmetric: the dense check from one side passed
        a poster 7 m away that the other side refuses (the posters' negative control with
        both robots mapping at once). Returns "ok" or "rejected: back …"."""
        c = self.config
        f = place.features
        v = verify(peer.camera, f.keypoints, f.descriptors, u.features.descriptors, u.features.points,
                   min_inliers=c.relocalize_min_inliers)
        if not v.accepted:
            return f"rejected: back verification {v.reason}"
        mine = self.memory.views.get(u.node_id)
        if place.view is not None and mine is not None:
            v = refine(v, place.view, mine, min_overlap=c.refine_min_overlap,
                       max_correction=(c.refine_max_correction, c.refine_max_rotation))
            if not v.refined:
                return "rejected: back not refined densely"
        return "ok"

    def _live_candidates(self, words: np.ndarray, peers: list[Mapper],
                         live: dict[int, Mapper]) -> list[tuple[int, float, np.ndarray]]:
        """The peers' keyframes in RAM that look most like a keyframe with these `words`
        (tf-idf in the shared vocabulary, as the loop detector's likelihood), best first, as
        `Memory.relocalization_candidates` gives the older maps': (node, score > 0, its camera
        centre in the peer's map). Fills `live` (node -> its peer)."""
        of = {n: p for p in peers for n in p.memory.own_in_ram()}
        if not of:
            return []
        with self.vocabulary.lock:
            best = self.vocabulary.most_alike(words, np.array(sorted(of), np.int64), RELOCALIZATION_SCORED)
        live.update((n, of[n]) for n, _ in best)
        return [(n, score, of[n].pose(n)[:3, 3].copy()) for n, score in best]

    def _adopt(self, peer: Mapper, nodes: list[int]) -> None:
        """A peer's nodes (another robot's map update running now) enter this map update: its
        memory (`Memory.adopt`) and this graph, anchored at the peer's current poses with the
        tight prior, as an older map's are (`_place`). This mapper never writes their poses."""
        root = peer.root()
        assert root is not None  # a peer has keyframes
        for n in nodes:
            if n in self.graph or not self.memory.adopt(n, peer.memory, root):
                continue
            self._place({n: peer.pose(n)})
            self._foreign.add(n)

    def _link_path(self, u: KeyframeUpdate, candidates: set[int], stats: LoopStatistics) -> None:
        """Proximity by time: register the new keyframe to recent keyframes of its own segment
        (those that are not loop candidates) that the graph places in view of it, the oldest
        first, then the one halfway along the path to it; each that passes becomes a link."""
        c = self.config
        if c.proximity_time_links <= 0:
            return
        recent = self.memory.recent_path(u.node_id, candidates)
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
            if decision == "ok" and not v.refined and u.node_id in self.memory.views and candidate in self.memory.views:
                decision = "rejected: not refined"  # odometry is better than an unrefined PnP link
            elif decision == "ok":
                decision = self._add_link(u, candidate, LinkType.LOCAL_TIME, v)
            stats.path.append({"node": candidate, "decision": decision,
                               "inliers": 0 if v is None else v.inliers, "refined": bool(v is not None and v.refined)})

    def _register(self, u: KeyframeUpdate, candidate: int, prior: np.ndarray | None = None,
                  place=None, min_inliers: int | None = None) -> tuple[str, Verification]:
        """Verify a candidate (PnP, then dense refinement). With a `prior` (T_candidate_new
        from the graph) a candidate PnP refuses is also registered densely from it. `place`:
        the candidate's data (`Memory.place`) when it is not in RAM. Returns ("ok" or
        "rejected: why", the verification)."""
        c = self.config
        cand = self.memory.features[candidate] if place is None else place.features
        v = verify(self.camera, u.features.keypoints, u.features.descriptors, cand.descriptors, cand.points,
                   min_inliers=c.min_inliers if min_inliers is None else min_inliers)
        views = self.memory.views
        if place is not None:
            views = {u.node_id: views[u.node_id]} if u.node_id in views and place.view is not None else {}
            if views:
                views[candidate] = place.view
        dense = u.node_id in views and candidate in views
        if not v.accepted and prior is not None and dense:
            v = register_dense(views[u.node_id], views[candidate], prior,
                               min_overlap=c.proximity_dense_min_overlap,
                               max_correction=(c.proximity_max_correction, c.proximity_max_rotation))
            dense = False  # already dense
        if not v.accepted:
            return f"rejected: verification {v.reason}", v
        if dense:
            v = refine(v, views[u.node_id], views[candidate], min_overlap=c.refine_min_overlap,
                       max_correction=(c.refine_max_correction, c.refine_max_rotation))
        return "ok", v

    def _accurate(self, u: KeyframeUpdate, candidate: int, v: Verification,
                  features: FrameFeatures | None = None) -> tuple[str, Verification]:
        """A loop / proximity link as accurate as both keyframes' features make it, or none:
        two-view reprojection refinement from the verified transform (`link_refinement`);
        the link is refused ("rejected: inaccurate …", counted in `links_dropped`) when its
        σ is beyond loop.link_max_sigma_*. Its information is the verification's noise model
        (σ × link_refine_sigma_factor where it takes the refined transform, as much more
        accurate as it measured), loosened where the refinement's covariance is larger: the
        refinement's own σ is 5-20x below real links' errors, so it never makes a link more
        confident (issue 29). A dense refinement that passed its check keeps its transform
        (it explains the PnP inliers and uses thousands of points). Links registered densely
        without features (no inliers) keep their dense estimate. Each part switches alone
        (loop.link_refine_transform / _information / _drop)."""
        c = self.config
        if not c.link_refine or not v.inliers:
            return "ok", v
        assert v.transform is not None and v.information is not None  # accepted: both set
        e = refine_link(self.camera, u.features, self.memory.features[candidate] if features is None else features,
                        v.transform,
                        depth_noise=c.link_depth_noise, min_inliers=c.min_inliers,
                        max_sigma=(c.link_max_sigma_translation, c.link_max_sigma_rotation))
        if not e.ok and c.link_refine_drop:
            self.links_dropped += 1
            why = e.reason if e.covariance is None else \
                f"σ {e.sigma_translation * 100:.2f} cm / {e.sigma_rotation:.2f} deg"
            return f"rejected: inaccurate ({why})", v
        if e.covariance is None:  # not refined, not dropped: the verified link as it is
            return "ok", v
        if c.link_refine_drop and c.link_max_disagreement > 0:
            assert e.transform is not None  # refined
            d = invert(v.transform) @ e.transform
            moved, turned = float(np.linalg.norm(d[:3, 3])), float(np.degrees(rotation_angle(d[:3, :3])))
            if moved > c.link_max_disagreement or turned > c.link_max_disagreement_rotation:
                self.links_dropped += 1
                return f"rejected: inaccurate (refinement moved it {moved * 100:.2f} cm / {turned:.2f} deg)", v
        refined = c.link_refine_transform and not v.refined
        T = e.transform if refined else v.transform
        info = v.information / c.link_refine_sigma_factor ** 2 if refined else v.information
        if c.link_refine_information:
            info = e.information(info)
        return "ok", dataclasses.replace(v, transform=T, information=info,
                                         sigma=(e.sigma_translation, e.sigma_rotation))

    def _add_link(self, u: KeyframeUpdate, candidate: int, kind: LinkType, v: Verification) -> str:
        """Add a verified link to the graph (which may refuse it) and store it (the poses it
        moved are written at the end of the update). Returns "accepted" or "rejected: graph why"."""
        assert v.transform is not None and v.information is not None  # accepted: both set
        outcome = self.graph.add_loop(candidate, u.node_id, v.transform, v.information)
        if not outcome.accepted:
            return f"rejected: graph {outcome.reason}"
        self._record_link(u.node_id, candidate, kind, v)
        return "accepted"

    def _record_link(self, node: int, candidate: int, kind: LinkType, v: Verification, stored: bool = False) -> None:
        """A link the graph accepted: memory, the database (unless `stored` already), a
        `loop_closed` event (not for path links)."""
        assert v.transform is not None and v.information is not None  # accepted: both set
        if kind != LinkType.LOCAL_TIME:
            self.loops.append((candidate, node))
            self.memory.loop_closed(candidate)
            self.memory.link(node, candidate)
        if not stored:
            self.memory.save_link(candidate, node, kind, v.transform, v.information)
        if kind != LinkType.LOCAL_TIME:
            self.on_event("loop_closed", {"from": candidate, "to": node, "inliers": v.inliers, "link": kind.label})

    def _publish(self, stats: LoopStatistics) -> None:
        """Keep the update's statistics; write the poses the graph moved (and the new
        keyframe's), then the statistics to the database; a `map_corrected` event when older
        keyframes moved. Every update, not only after a link: iSAM2 keeps refining earlier
        poses as nodes arrive."""
        self.statistics[stats.node_id] = stats
        while len(self.statistics) > STATISTICS_KEPT:
            self.statistics.popitem(last=False)
        moved = self._write_moved()
        if set(moved) - {stats.node_id}:
            self.on_event("map_corrected", {"nodes": len(moved)})
        self.memory.save_statistics(stats.node_id, stats.__dict__)

    def _write_moved(self, tolerance: tuple[float, float] | None = None) -> dict[int, np.ndarray]:
        """Write the poses the graph moved by more than `tolerance` (default: the graph's)."""
        moved = self.graph.changed_poses(tolerance)
        if self._foreign:  # another robot's nodes: its map update writes them
            moved = {k: v for k, v in moved.items() if k not in self._foreign}
        self.memory.save_poses(moved)
        return moved

    def _close_loop(self, u: KeyframeUpdate, candidate: int, kind: LinkType,
                    prior: np.ndarray | None = None) -> tuple[str, Verification]:
        """Verify a loop candidate, make the link accurate or drop it (`_accurate`) and add it
        to the graph. Returns the decision ("accepted" or "rejected: why") and the verification."""
        decision, v = self._register(u, candidate, prior)
        if decision == "ok":
            decision, v = self._accurate(u, candidate, v)
        if decision == "ok":
            decision = self._add_link(u, candidate, kind, v)
        return decision, v


def _rounded_sigma(v: Verification | None) -> list | None:
    """A link's [m, deg] σ (two-view refinement) as the statistics record it."""
    return None if v is None or v.sigma is None else [round(x, 5) for x in v.sigma]

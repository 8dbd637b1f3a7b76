"""The node life cycle of one map update (`Mapper`), RTAB-Map's `Memory`: a new keyframe
enters STM (`add`) or is merged into a node by rehearsal (`merge`); after each update
`manage` moves nodes between WM and LTM as `WorkingMemory` decides, telling the vocabulary,
the loop detector, the pose graph and the views cache what leaves and enters RAM (LTM is
the database: a move writes nothing). `load_previous` starts WM on a reopened map, `resume`
rebuilds an interrupted session's memory."""
from __future__ import annotations

import dataclasses
import logging
import time

import gtsam
import numpy as np

from client.frames import PinholeCamera
from client.geometry import invert, nearby, rotation_angle
from storage import LinkType, MapStore, UnknownIdError

from ..config import LoopConfig, MemoryConfig
from ..mapping.graph import LoopOutcome, PoseGraph
from ..mapping.loop_detection import LoopDetector
from ..tracking.features import FrameFeatures
from .views import DenseView, StoredViews
from .vocabulary import Vocabulary
from .working_memory import WorkingMemory

log = logging.getLogger("mnemoslam.memory")


class MemoryManager:
    """`tiers`: which node is in STM, WM or LTM, and their weights; `features` and `views`:
    the features and dense views of the nodes in RAM; `neighbours`: graph adjacency of every
    node it knows, LTM included (loop prediction, retrieval); `merged`: keyframe merged by
    rehearsal -> (survivor, T_survivor_keyframe). The map update reads these and reports what
    it did (`add`, `add_view`, `link`, `loop_closed`, `merge`); only the manager changes them."""

    def __init__(self, config: MemoryConfig, loop: LoopConfig, store: MapStore | None, camera: PinholeCamera,
                 graph: PoseGraph, vocabulary: Vocabulary, detector: LoopDetector):
        self.config, self.loop_config, self.store, self.camera = config, loop, store, camera
        self.graph, self.vocabulary, self.detector = graph, vocabulary, detector
        self.tiers = WorkingMemory(config.stm_size, config.max_wm_nodes, config.time_threshold_ms,
                                   config.recent_wm_ratio, config.max_retrieved, config.retrieval_depth)
        self.features: dict[int, FrameFeatures] = {}  # the features of the keyframes in STM and WM
        # reduced depth + grey of RGB-D keyframes in RAM, for dense link refinement (a retrieved
        # or stored keyframe's are decoded from its stored images when first needed)
        self.views: dict[int, DenseView] = StoredViews(store, camera) if store is not None else {}
        self.neighbours: dict[int, list[int]] = {}
        self.merged: dict[int, tuple[int, np.ndarray]] = {}
        self._order: list[int] = []
        self._stamps: dict[int, float] = {}
        self._segment: dict[int, int] = {}  # node -> first node of its odometry segment
        self._loop_nodes: set[int] = set()  # the older end of the last accepted loop closure (kept in WM)
        self._merge_links: dict[frozenset, _MergeLink] = {}  # node pair -> the one graph link merges between them made

    # -- the map update's nodes --------------------------------------------------------------
    def add(self, u) -> None:
        """A new keyframe (`KeyframeUpdate`) enters STM: its features (no images), stamp,
        path segment and odometry link."""
        f = u.features
        self.features[u.node_id] = FrameFeatures(f.keypoints, f.descriptors, f.points, f.octaves)  # no images
        self._stamps[u.node_id] = u.stamp
        self._order.append(u.node_id)
        self.tiers.add(u.node_id)
        self.neighbours.setdefault(u.node_id, [])
        self._segment[u.node_id] = u.node_id if u.odom_from is None else self._segment.get(u.odom_from, u.odom_from)
        if u.odom_from is not None:
            self.link(u.node_id, u.odom_from)

    def add_view(self, u) -> None:
        """The dense view of a new keyframe with depth (for dense refinement, `loop.refine_dense`)."""
        f = u.features
        if self.loop_config.refine_dense and f.depth is not None and f.grey is not None:
            self.views[u.node_id] = DenseView(f.depth, f.grey, self.camera)

    def link(self, a: int, b: int) -> None:
        """Nodes `a` and `b` are linked in the graph (odometry, loop closure, rehearsal)."""
        self.neighbours.setdefault(a, []).append(b)
        self.neighbours.setdefault(b, []).append(a)

    def loop_closed(self, node: int) -> None:
        """A loop closure to `node` was accepted: it stays in WM, and the nodes that enter WM
        from now on are recent."""
        self._loop_nodes = {node}
        self.tiers.loop_closed()

    def candidates(self, stamp: float, min_age: float) -> set[int]:
        """Loop candidates of a keyframe taken at `stamp`: WM nodes at least `min_age` s older."""
        return {n for n in self.tiers.wm if stamp - self._stamps[n] >= min_age}

    def recent_path(self, node: int, candidates: set[int]) -> list[int]:
        """The keyframes of `node`'s path segment just before it (the newest, in RAM, back to
        the first loop candidate), not linked to it, newest first."""
        segment, recent = self._segment[node], []
        for n in reversed(self._order[:-1]):  # the non-candidates are the newest keyframes
            if n in candidates or not self.tiers.in_ram(n):
                break
            if self._segment[n] == segment and n not in self.neighbours[node]:
                recent.append(n)
        return recent

    def statistics(self, stamp: float, transferred: list[int], retrieved: list[int], survivor: int | None) -> dict:
        """The memory part of an update's statistics."""
        sizes = self.tiers.sizes()
        return {"stamp": stamp, "stm": sizes.stm, "wm": sizes.wm, "ltm": sizes.ltm,
                "transferred": transferred, "retrieved": retrieved, "merged": [] if survivor is None else [survivor],
                "words": len(self.vocabulary), "dormant_words": self.vocabulary.dormant}

    # -- rehearsal's merges ----------------------------------------------------------------------
    def pose(self, node: int) -> np.ndarray:
        """A keyframe's map pose: its node's, or for a merged keyframe where its survivor sees it."""
        if node in self.merged:
            survivor, t = self.merged[node]
            return self.graph.pose(survivor) @ t
        return self.graph.pose(node)

    def keyframe_poses(self) -> dict[int, np.ndarray]:
        """Every keyframe's map pose: the graph's nodes, and each merged keyframe where its
        survivor sees it."""
        poses = self.graph.poses()
        poses.update({m: poses[c] @ t for m, (c, t) in self.merged.items() if c in poses})
        return poses

    def through_merges(self, u):
        """A keyframe (`KeyframeUpdate`) whose odometry starts at a merged keyframe starts at
        its survivor."""
        if u.odom_from not in self.merged or u.transform is None:
            return u
        survivor, t = self.merged[u.odom_from]
        return dataclasses.replace(u, odom_from=survivor, transform=t @ u.transform)

    def link_merge(self, a: int, b: int, transform: np.ndarray, information: np.ndarray, check: str | bool = "link"):
        """The graph link a merge makes between two nodes (T_a_b): the first merge between
        them adds it; a later one replaces it by the running mean of their measurements, its
        information that of one measurement times their count (up to 3), so repeated passes
        refine one link per pair instead of adding one per keyframe (iSAM2 grows ~7 kB per
        link). A mean that moved less than the graph's `move_tolerance` from the link in the
        graph, at the same information, is kept in the mean only when the measurement itself
        fits the current estimate (`graph.max_error`): no optimisation for what would move no
        pose the map reports. Returns the graph's outcome."""
        t0 = time.perf_counter()
        key = frozenset((a, b))
        old = self._merge_links.get(key)
        n = 0
        if old is not None:
            t = transform if old.from_id == a else invert(transform)
            a, b, n = old.from_id, old.to_id, old.count
            one = information
            step = gtsam.Pose3.Logmap(gtsam.Pose3(invert(old.transform) @ t)) / (n + 1)
            transform = old.transform @ gtsam.Pose3.Expmap(step).matrix()
            information = information * min(n + 1, 3)
            if n >= 3 and self._within_tolerance(old.in_graph, transform):
                err = self.graph.link_error(a, b, t, one)
                if not check or self.graph.max_error <= 0 or err <= self.graph.max_error:
                    self._merge_links[key] = _MergeLink(a, b, transform, old.information, n + 1, old.in_graph)
                    return LoopOutcome(True, "accepted (the link moved within tolerance: kept)", err, err, err,
                                       duration_ms=(time.perf_counter() - t0) * 1e3)
        # (one optimisation replaces the previous link; a refused one leaves it in place)
        outcome = self.graph.add_loop(a, b, transform, information, check=check,
                                      replace=None if old is None else old.in_graph)
        if outcome.accepted:
            self._merge_links[key] = _MergeLink(a, b, transform, information, n + 1, transform)
        return outcome

    def _within_tolerance(self, a: np.ndarray, b: np.ndarray) -> bool:
        tol_t, tol_r = self.graph.move_tolerance
        d = invert(a) @ b
        return float(np.linalg.norm(d[:3, 3])) < tol_t and rotation_angle(d[:3, :3]) < tol_r

    def merge(self, node: int, survivor: int, previous: int, transform: np.ndarray, information: np.ndarray) -> bool:
        """Keyframe `node` (odometry from `previous`) merged into `survivor`, T_survivor_node
        = `transform` (RAM, weights, database). Returns True when the path just came back to
        the survivor's part of the map (counts as a loop closure)."""
        entering = previous != survivor and survivor not in self.neighbours.get(previous, ())
        self.merged[node] = (survivor, transform.copy())
        self.views.pop(node, None)
        self.tiers.rehearsed(survivor)
        if entering:
            self.link(previous, survivor)
            self.loop_closed(survivor)
        if self.store is not None:
            self.store.merge_node(node, survivor, transform, information)
            self.store.update_poses({node: self.pose(node)})
        return entering

    # -- transfer and retrieval --------------------------------------------------------------
    def manage(self, node: int, best: int | None, update_ms: float) -> tuple[list[int], list[int]]:
        """After the update of keyframe `node` that took `update_ms`: retrieval (LTM → WM)
        around the best loop hypothesis and the keyframe, then transfer (WM → LTM) when WM is
        over its limits. Returns (transferred, retrieved) node ids."""
        tiers = self.tiers
        retrieved = []
        if self.store is not None and tiers.ltm and tiers.max_retrieved > 0:
            retrieved = tiers.select_retrievals([best], self.neighbours)
            retrieved += [n for n in self._ltm_near(node) if n not in retrieved]
            retrieved = self.retrieve(retrieved[:tiers.max_retrieved])
        transferred: list[int] = []
        if self.store is not None and tiers.over_limit(update_ms):
            transferred = tiers.select_transfers(update_ms, *self._protected(node))
            for n in transferred:
                self._transfer(n)
            tiers.transferred(transferred)
        return transferred, retrieved

    def retrieve(self, nodes: list[int]) -> list[int]:
        """LTM → WM: features and words back from the database (dense views when first
        needed). Returns the nodes retrieved (one that cannot be loaded stays in LTM)."""
        nodes = [n for n in nodes if self._retrieve(n)]
        self.tiers.retrieved(nodes)
        return nodes

    def _ltm_near(self, node: int) -> list[int]:
        """LTM nodes the map places where keyframe `node` is (within loop.proximity_radius,
        looking within proximity_angle of its way), nearest first: one R*Tree query of the
        stored poses (the graph's estimates)."""
        c = self.loop_config
        pose = self.pose(node)
        r = c.proximity_radius
        box = (tuple(pose[:3, 3] - r), tuple(pose[:3, 3] + r))
        # the map's nodes only: keyframes merged by rehearsal keep their rows (and their place in
        # the R*Tree), and a patrolled place holds ever more of them
        nodes = [n for n in self.store.nodes(bbox=box, limit=None, merged=False) if n.id in self.tiers.ltm]
        if not nodes:
            return []
        return nearby(np.stack([n.pose for n in nodes]), np.array([n.id for n in nodes], np.int64), pose, r,
                      c.proximity_angle, self.tiers.max_retrieved).tolist()

    def _protected(self, node: int) -> tuple[set[int], set[int]]:
        """(WM nodes that stay in RAM: linked to STM and the last loop closure's; WM nodes that
        go last: those the graph places within memory.local_radius of keyframe `node`)."""
        keep = set(self._loop_nodes)
        for s in self.tiers.stm:
            keep.update(self.neighbours.get(s, ()))
        wm, near = self.tiers.wm, set()
        if wm and self.config.local_radius > 0:
            here = self.pose(node)[:3, 3]
            centres = np.stack([self.graph.pose(n)[:3, 3] for n in wm])
            close = np.linalg.norm(centres - here, axis=1) <= self.config.local_radius
            near = set(np.asarray(wm)[close].tolist())
        return keep, near

    def _transfer(self, node: int) -> None:
        """WM → LTM: the node's words leave the search structures, its features leave RAM
        (everything stays in the database)."""
        with self.vocabulary.lock:
            self.vocabulary.unload_node(node)
            self.detector.forget([node])
        self.features.pop(node, None)
        self.views.pop(node, None)

    def _retrieve(self, node: int) -> bool:
        try:
            keypoints, descriptors, points, word_ids = self.store.load_features(node)
        except UnknownIdError:
            return False
        self.features[node] = FrameFeatures(keypoints, descriptors, points, np.zeros(len(keypoints), np.int8))
        if node not in self.graph:  # a node of the previous map, in no graph of this mapper yet
            self._place_previous([node])
        if word_ids is not None and node not in self.vocabulary:  # an old node another mapper holds is indexed
            with self.vocabulary.lock:
                missing = self.vocabulary.missing_words(word_ids[word_ids >= 0])
                self.vocabulary.reload_node(node, word_ids, descriptors=self.store.load_words(missing) if len(missing)
                                            else None)
        if isinstance(self.views, StoredViews):
            self.views.defer(node)
        return True

    # -- start-up ----------------------------------------------------------------------------
    def load_previous(self) -> None:
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
        k = self.tiers.max_wm_nodes
        first_wm = ids[-k:] if 0 < k < len(ids) else ids
        features = store.load_features_many(first_wm.tolist())
        wm = [n for n in first_wm.tolist() if n in features]  # a node without features stays in LTM
        pairs = store.link_pairs((LinkType.NEIGHBOR, LinkType.GLOBAL_CLOSURE, LinkType.LOCAL_SPACE))
        pairs = pairs[np.isin(pairs, ids).all(axis=1)]
        for a, b in pairs.tolist():
            self.link(a, b)
        self._place_previous(wm)
        for n in wm:
            kp, desc, pts, _ = features[n]
            self.features[n] = FrameFeatures(kp, desc, pts, np.zeros(len(kp), np.int8))
            if self.loop_config.refine_dense and isinstance(self.views, StoredViews):
                self.views.defer(n)
        self._index_words({n: features[n][3] for n in wm})
        in_ram = set(wm)
        self.tiers.restore(stm=(), wm=wm, ltm=[n for n in ids.tolist() if n not in in_ram])  # keeps weights
        self.tiers.loop_closed()  # the old nodes are not "recent": they leave WM first

    def resume(self, session_id: int) -> list[tuple[int, int]]:
        """A stored session's interrupted map update (`Mapper.resume`): its mapped keyframes in
        STM and WM, in the graph with their links at their stored poses (merges fused as
        rehearsal made them), their features, words, views (decoded when first needed), path
        segments and adjacency. Returns its loop closures (appearance and proximity links)."""
        store, sid = self.store, int(session_id)
        unmapped = set(store.unmapped_nodes(session_ids=[sid]).get(sid, ()))
        stored = [n for n in store.nodes(session_id=sid, limit=None) if n.id not in unmapped]  # by id = in time
        nodes = [n for n in stored if n.merged_into is None]
        links = [lk for lk in store.links(session_id=sid) if lk.from_id not in unmapped and lk.to_id not in unmapped]
        merges = {lk.to_id: lk for lk in links if lk.type == LinkType.MERGED}
        self.merged = {k: (lk.from_id, lk.transform) for k, lk in merges.items()}
        odometry, entries = [], []  # odometry links through merged keyframes: to a node, or (rehearsal) to a survivor
        for lk in links:
            if lk.type != LinkType.NEIGHBOR:
                continue
            a, ta = self.merged.get(lk.from_id, (lk.from_id, np.eye(4)))
            b, tb = self.merged.get(lk.to_id, (lk.to_id, np.eye(4)))
            if lk.to_id not in self.merged:
                odometry.append((a, b, ta @ lk.transform, lk.information))
            elif a != b:
                entries.append((a, b, ta @ lk.transform @ invert(tb),
                                series_information(lk.information, merges[lk.to_id].information)))
        own = {n.id for n in nodes}
        loops = [(lk.from_id, lk.to_id, lk.transform, lk.information) for lk in links
                 if lk.type in (LinkType.GLOBAL_CLOSURE, LinkType.LOCAL_SPACE, LinkType.LOCAL_TIME)]
        across = [k for k in loops if not (k[0] in own and k[1] in own)]  # to the previous map's nodes
        # odometry from a keyframe merged into the previous map's node starts at that node
        across += [k for k in odometry if k[0] not in own]
        self.graph.restore({n.id: n.pose for n in nodes}, [k for k in odometry if k[0] in own],
                           [k for k in loops if k[0] in own and k[1] in own])
        # the previous map's nodes this session linked to: by loops, odometry or merges
        self._place_previous({n for a, b, _, _ in across + entries for n in (a, b) if n not in own})
        for a, b, t, info in across:
            self.graph.add_loop(a, b, t, info, check=False)  # checked when it was added
        for a, b, t, info in sorted(entries, key=lambda e: e[1]):  # as rehearsal made them (checked then)
            self.link_merge(a, b, t, info, check=False)
        incoming = {b: a for a, b, _, _ in odometry}
        for a, b, _, _ in entries:
            if b not in self.neighbours.setdefault(a, []):
                self.link(a, b)
        words = {}
        for n in nodes:
            keypoints, descriptors, points, words[n.id] = store.load_features(n.id)
            self.features[n.id] = FrameFeatures(keypoints, descriptors, points, np.zeros(len(keypoints), np.int8))
            self._stamps[n.id] = n.stamp
            self._order.append(n.id)
            self.neighbours.setdefault(n.id, [])
            src = incoming.get(n.id)
            self._segment[n.id] = n.id if src is None else self._segment.get(src, src)
            if src is not None:
                self.link(n.id, src)
        closures = []
        for lk in links:
            # as the map update: path links are not loops
            if lk.type in (LinkType.GLOBAL_CLOSURE, LinkType.LOCAL_SPACE):
                closures.append((lk.from_id, lk.to_id))
                self.link(lk.to_id, lk.from_id)
        if self.loop_config.refine_dense:
            for n in own:
                self.views.defer(n)
        self._index_words(words)  # those the vocabulary does not hold (it loads only WM's with a WM limit)
        k = max(len(self._order) - self.tiers.stm_size, 0)
        self.tiers.restore(stm=self._order[k:], wm=self._order[:k], ltm=(), weights={n.id: n.weight for n in nodes})
        return closures

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
            self.neighbours.setdefault(r.id, [])
            self.tiers.weights[r.id] = r.weight

    def _index_words(self, words: dict) -> None:
        """Index the words of nodes ({node: word id per feature, or None}) the vocabulary
        does not hold yet, the descriptors of its missing words read in one query."""
        with self.vocabulary.lock:
            todo = {n: w for n, w in words.items() if w is not None and n not in self.vocabulary}
            if not todo:
                return
            missing = self.vocabulary.missing_words(np.concatenate([np.asarray(w, np.int64) for w in todo.values()]))
            self.vocabulary.reload_nodes(todo, descriptors=self.store.load_words(missing) if len(missing) else None)


@dataclasses.dataclass
class _MergeLink:
    """The graph link merges made between two nodes: T_from_to (mean of `count` measurements)
    and the information of the link in the graph."""

    from_id: int
    to_id: int
    transform: np.ndarray
    information: np.ndarray
    count: int
    in_graph: np.ndarray  # T_from_to of the link in the graph (the mean when it was last put there)


def series_information(a: np.ndarray | None, b: np.ndarray) -> np.ndarray:
    """Information of two relative poses chained (covariances add; frames not rotated: the
    links chained by rehearsal are short)."""
    if a is None:
        return b
    return np.linalg.inv(np.linalg.inv(a) + np.linalg.inv(b))

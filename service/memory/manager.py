"""The node life cycle of one map update (`Mapper`), RTAB-Map's `Memory`: a new keyframe
enters STM (`add`) and its words the vocabulary (`add_words`), or it is merged into a node by
rehearsal (`merge`); after each update the mapper asks what to retrieve (`to_retrieve`),
retrieves it (`retrieve`) and transfers what `WorkingMemory` decides (`transfer`): features,
words and dense views leave and enter RAM (LTM is the database: a move writes nothing).
`load_previous` starts WM on a reopened map, `resume` rebuilds an interrupted session's memory.

Memory owns the map's tiers, its vocabulary (shared by every mapper of the store), the
feature and dense-view caches and the node life-cycle writes to the store; it knows nothing
of the pose graph or the loop detector. Where it needs map poses the mapper passes them
(`NodePoses`); the graph nodes it finds (a previous map's, a resumed session's) it returns
for the mapper to put in its graph, and it returns the nodes it transferred for the loop
detector to forget."""
from __future__ import annotations

import collections
import dataclasses
from types import MappingProxyType
from typing import Callable, Mapping

import cv2
import numpy as np

from mnemoslam.client.kernel.frames import PinholeCamera
from mnemoslam.client.kernel.geometry import invert, nearby
from mnemoslam.storage import LinkRecord, LinkType, MapUpdateStore, NodeRecord, UnknownIdError
from mnemoslam.storage.connectivity import MapConnectivity

from ..config import LoopConfig, MemoryConfig
from ..tracking.features import FrameFeatures
from .keyframes import decode_images
from .views import DenseView, StoredViews
from .vocabulary import Vocabulary
from .working_memory import WorkingMemory

PLACES_KEPT = 8  # LTM nodes whose data rehearsal read are kept for the next keyframes


@dataclasses.dataclass
class Place:
    """A node as rehearsal compares a keyframe with it: features, its words' descriptors,
    dense view (None: none)."""

    features: FrameFeatures
    words: np.ndarray
    view: DenseView | None


NodePoses = Callable[[int], np.ndarray]  # a keyframe's map pose (4×4), as the mapper's graph places it
Link = tuple[int, int, np.ndarray, np.ndarray]  # (from, to, T_from_to, information)


@dataclasses.dataclass
class ResumedSession:
    """What `Memory.resume` found of a stored session for the mapper's graph: its nodes at their
    stored poses with the links between them (odometry through merged keyframes, loop and
    path links), the previous map's nodes it linked to (at their stored poses) and those links,
    rehearsal's links (in the order the merges made them) and its loop closures."""

    poses: dict[int, np.ndarray]
    odometry: list[Link]
    loops: list[Link]
    previous: dict[int, np.ndarray]
    across: list[Link]
    merge_links: list[Link]
    closures: list[tuple[int, int]]


@dataclasses.dataclass
class StoredKeyframe:
    """A keyframe as tracking stored it (`Memory.stored_keyframe`): its node (stamp, stored
    pose), features (no octaves; with its depth and grey image when asked for) and the
    odometry link to it (None: the first of a segment)."""

    node: NodeRecord
    features: FrameFeatures
    odometry: LinkRecord | None


class Memory:
    """`tiers`: which node is in STM, WM or LTM, and their weights; `features` and `views`:
    the features and dense views of the nodes in RAM; `neighbours`: graph adjacency of every
    node it knows, LTM included (loop prediction, retrieval); `merged`: keyframe merged by
    rehearsal -> (survivor, T_survivor_keyframe); `vocabulary`: the map's visual words. The
    map update reads these (read-only views) and reports what it did (`add`, `add_words`,
    `add_view`, `link`, `loop_closed`, `merge`); only memory changes them."""

    def __init__(self, config: MemoryConfig, loop: LoopConfig, store: MapUpdateStore | None,
                 camera: PinholeCamera):
        self.config, self.loop_config, self.store, self.camera = config, loop, store, camera
        # The map's vocabulary: shared by every mapper (robot) of that store, persisted with each
        # keyframe; on a reopened map with a WM limit it starts without words (those of the nodes
        # in RAM come with them), else it is loaded whole from the store.
        self._vocabulary = (Vocabulary.for_store(store, words=config.max_wm_nodes <= 0, nndr=loop.nndr_ratio)
                            if store is not None else Vocabulary(nndr=loop.nndr_ratio))
        self._tiers = WorkingMemory(config.stm_size, config.max_wm_nodes, config.time_threshold_ms,
                                    config.recent_wm_ratio, config.max_retrieved, config.retrieval_depth,
                                    config.retrieval_immunity)
        self._features: dict[int, FrameFeatures] = {}  # the features of the keyframes in STM and WM
        # reduced depth + grey of RGB-D keyframes in RAM, for dense link refinement (a retrieved
        # or stored keyframe's are decoded from its stored images when first needed)
        self._views: dict[int, DenseView] = StoredViews(store, camera) if store is not None else {}
        self._neighbours: dict[int, list[int]] = {}
        self._maps = MapConnectivity()  # the graph's connected parts (`same_map`), fed by `link`
        self._merged: dict[int, tuple[int, np.ndarray]] = {}
        self._order: list[int] = []
        # node -> stamp, of every node of this map update: those it added, resumed or placed
        # from the previous map (exactly the mapper's graph nodes)
        self._stamps: dict[int, float] = {}
        self._segment: dict[int, int] = {}  # node -> first node of its odometry segment
        self._loop_nodes: set[int] = set()  # the older end of the last accepted loop closure (kept in WM)
        # LTM nodes rehearsal read from the database (features, word descriptors, dense view),
        # the last few: consecutive keyframes of a revisit meet the same places
        self._places: collections.OrderedDict[int, Place] = collections.OrderedDict()
        self.places_read = 0  # LTM nodes read for rehearsal (not retrieved: they stay in LTM)
        # the older maps' nodes (ended sessions' at start-up, `load_previous`): a keyframe whose
        # map has joined none of them relocalizes against them (`relocalization_candidates`),
        # through an index of their words read from the store when first needed
        self._older = np.zeros(0, np.int64)
        self._older_index: Vocabulary | None = None
        self._older_centres: dict[int, np.ndarray] = {}
        self._older_indexed = np.zeros(0, np.int64)  # the older nodes the index has words of, ascending

    # -- what the map update reads -----------------------------------------------------------
    @property
    def vocabulary(self) -> Vocabulary:
        """The map's vocabulary (hold its `lock` to read it: other robots' mappers add to it)."""
        return self._vocabulary

    @property
    def tiers(self) -> WorkingMemory:
        return self._tiers

    @property
    def features(self) -> Mapping[int, FrameFeatures]:
        return MappingProxyType(self._features)

    @property
    def views(self) -> Mapping[int, DenseView]:
        return MappingProxyType(self._views)

    @property
    def neighbours(self) -> Mapping[int, list[int]]:
        return MappingProxyType(self._neighbours)

    @property
    def merged(self) -> Mapping[int, tuple[int, np.ndarray]]:
        return MappingProxyType(self._merged)

    # -- the map update's nodes --------------------------------------------------------------
    def add(self, u) -> None:
        """A new keyframe (`KeyframeUpdate`) enters STM: its features (no images), stamp,
        path segment and odometry link."""
        f = u.features
        self._features[u.node_id] = FrameFeatures(f.keypoints, f.descriptors, f.points, f.octaves)  # no images
        self._stamps[u.node_id] = u.stamp
        self._order.append(u.node_id)
        self._tiers.add(u.node_id)
        self._neighbours.setdefault(u.node_id, [])
        self._segment[u.node_id] = u.node_id if u.odom_from is None else self._segment.get(u.odom_from, u.odom_from)
        if u.odom_from is not None:
            self.link(u.node_id, u.odom_from)

    def add_words(self, node: int, descriptors: np.ndarray) -> np.ndarray:
        """A new node's descriptors quantised into the vocabulary (new words made), its word ids
        and new words committed to the store in one transaction. Returns its word ids."""
        return self._vocabulary.add(node, descriptors, store=self.store)

    def add_view(self, u) -> None:
        """The dense view of a new keyframe with depth (for dense refinement, `loop.refine_dense`)."""
        f = u.features
        if self.loop_config.refine_dense and f.depth is not None and f.grey is not None:
            self._views[u.node_id] = DenseView(f.depth, f.grey, self.camera)

    def link(self, a: int, b: int) -> None:
        """Nodes `a` and `b` are linked in the graph (odometry, loop closure, rehearsal): one
        map from now on."""
        self._neighbours.setdefault(a, []).append(b)
        self._neighbours.setdefault(b, []).append(a)
        self._maps.union(a, b)

    def same_map(self, node: int, nodes) -> list[int]:
        """Those of `nodes` that links join to `node` (directly or not): the nodes whose map
        coordinates mean something to it. A new session or a segment after tracking was lost
        starts a map of its own, whose coordinates coincide numerically with the others' but
        relate to nothing there until an appearance link joins it (RTAB-Map bounds proximity
        by graph depth for the same reason)."""
        here = self._maps.find(node)
        return [n for n in nodes if self._maps.find(n) == here]

    # -- relocalization against the older maps -----------------------------------------------
    def in_older_map(self, node: int) -> bool:
        """Whether links join `node` to a node of the older maps (those of the sessions that had
        ended when this map update started): always for their own nodes; for this update's,
        once its map joined one of them. (Union-find keeps a part's smallest id as its root, and
        the older maps' ids are all below this update's own.)"""
        return bool(len(self._older)) and self._maps.find(node) <= int(self._older[-1])

    def relocalizing(self, node: int) -> bool:
        """Whether keyframe `node` is to be searched for in the older maps: there are some, and
        its map has joined none of them yet."""
        return bool(len(self._older)) and not self.in_older_map(node)

    def relocalization_candidates(self, descriptors: np.ndarray, k: int) -> list[tuple[int, float, np.ndarray]]:
        """The `k` older maps' nodes that look most like a keyframe with these descriptors,
        best first, (node, tf-idf score > 0, its camera centre in the map as stored): its
        descriptors quantised in the older maps' words and the tf-idf likelihood over their
        nodes, in working memory or long-term memory alike (ORB-SLAM3's Atlas searches every
        map's keyframe database; RTAB-Map's likelihood only WM). The index (their words and
        word ids, read from the store when first needed: the older maps do not change) is
        dropped once this map update's map joined them (`release_relocalization`)."""
        if not len(self._older) or k <= 0:
            return []
        if self._older_index is None:
            assert self.store is not None  # older maps: the mapper has a store
            self._older_index = Vocabulary.of_nodes(self.store, self._older.tolist(), nndr=self.loop_config.nndr_ratio)
            self._older_centres = {r.id: r.pose[:3, 3].copy() for r in self.store.get_nodes(self._older.tolist())}
            self._older_indexed = np.array([n for n in self._older.tolist() if n in self._older_index], np.int64)
        index = self._older_index
        return [(n, score, self._older_centres[n])
                for n, score in index.most_alike(index.query(descriptors), self._older_indexed, k)]

    def root(self, node: int) -> int:
        """The root of the map (connected part) `node` is in: its oldest node this memory
        knows to be linked to it (union–find keeps the smallest id)."""
        return self._maps.find(node)

    @property
    def newest(self) -> int | None:
        """The newest keyframe this map update added (or resumed); None before the first."""
        return self._order[-1] if self._order else None

    def own_in_ram(self) -> list[int]:
        """The keyframes this map update added (or resumed) that are in RAM with their words
        indexed, ascending: what another robot's map update may relocalize against while this
        one runs (`Mapper._relocalize`, `mapping.live`)."""
        with self._vocabulary.lock:
            return sorted(n for n in self._order if self._tiers.in_ram(n) and n in self._vocabulary)

    def adopt(self, node: int, other: Memory, root: int) -> bool:
        """A keyframe of another map update running at the same time (another robot's,
        `mapping.live`) enters this one's WM, as a retrieved node of an older map does: its
        features and dense view (the other memory's, shared), its words already in the shared
        vocabulary, a stamp older than any loop.min_age; it is in the map of the other's `root`
        (so this map is that map once a link joins them). Returns False when the other memory
        no longer holds its features (nothing changes)."""
        if node in self._stamps:
            return True
        f = other._features.get(node)
        if f is None:
            return False
        self._features[node] = f
        if node in other._views:
            self._views[node] = other._views[node]
        self._stamps[node] = -np.inf
        self._neighbours.setdefault(node, [])
        self._tiers.weights[node] = other._tiers.weights.get(node, 0)
        self._tiers.ltm.add(node)
        self._tiers.retrieved([node])
        self._maps.union(node, root)
        return True

    def release_relocalization(self) -> None:
        """The map joined an older one: the older maps' word index leaves RAM."""
        self._older_index, self._older_centres, self._older_indexed = None, {}, np.zeros(0, np.int64)

    def stored_poses(self, nodes) -> dict[int, np.ndarray]:
        """The stored map poses of nodes ({id: 4×4}; the older maps' are their final ones)."""
        if self.store is None:
            return {}
        return {r.id: r.pose for r in self.store.get_nodes(list(nodes))}

    def loop_closed(self, node: int) -> None:
        """A loop closure to `node` was accepted: it stays in WM, and the nodes that enter WM
        from now on are recent."""
        self._loop_nodes = {node}
        self._tiers.loop_closed()

    def candidates(self, stamp: float, min_age: float) -> set[int]:
        """Loop candidates of a keyframe taken at `stamp`: WM nodes at least `min_age` s older."""
        return {n for n in self._tiers.wm if stamp - self._stamps[n] >= min_age}

    def recent_path(self, node: int, candidates: set[int]) -> list[int]:
        """The keyframes of `node`'s path segment just before it (the newest, in RAM, back to
        the first loop candidate), not linked to it, newest first."""
        segment, recent = self._segment[node], []
        for n in reversed(self._order[:-1]):  # the non-candidates are the newest keyframes
            if n in candidates or not self._tiers.in_ram(n):
                break
            if self._segment[n] == segment and n not in self._neighbours[node]:
                recent.append(n)
        return recent

    def statistics(self, stamp: float, transferred: list[int], retrieved: list[int], survivor: int | None) -> dict:
        """The memory part of an update's statistics."""
        sizes = self._tiers.sizes()
        return {"stamp": stamp, "stm": sizes.stm, "wm": sizes.wm, "ltm": sizes.ltm,
                "transferred": transferred, "retrieved": retrieved, "merged": [] if survivor is None else [survivor],
                "words": len(self._vocabulary), "dormant_words": self._vocabulary.dormant,
                "wm_limit": self._tiers.limit}

    # -- rehearsal's merges ----------------------------------------------------------------------
    def through_merges(self, u):
        """A keyframe (`KeyframeUpdate`) whose odometry starts at a merged keyframe starts at
        its survivor."""
        if u.odom_from not in self._merged or u.transform is None:
            return u
        survivor, t = self._merged[u.odom_from]
        return dataclasses.replace(u, odom_from=survivor, transform=t @ u.transform)

    def merge(self, node: int, survivor: int, previous: int, transform: np.ndarray, information: np.ndarray) -> bool:
        """Keyframe `node` (odometry from `previous`) merged into `survivor`, T_survivor_node
        = `transform` (RAM, weights, database; the mapper writes its map pose). Returns True
        when the path just came back to the survivor's part of the map (counts as a loop
        closure)."""
        entering = previous != survivor and survivor not in self._neighbours.get(previous, ())
        self._merged[node] = (survivor, transform.copy())
        self._views.pop(node, None)
        self._tiers.rehearsed(survivor)
        if entering:
            self.link(previous, survivor)
            self.loop_closed(survivor)
        if self.store is not None:
            self.store.merge_node(node, survivor, transform, information)
        return entering

    # -- rehearsal against long-term memory --------------------------------------------------
    def ltm_near(self, where: np.ndarray, radius: float) -> list[int]:
        """LTM nodes of this map update (its graph's) the database places within `radius` of
        the camera at `where` (4×4): one R*Tree query of the stored poses. Rehearsal's
        candidates beside WM's: a revisit whose place went to LTM merges into it there."""
        if self.store is None or not self._tiers.ltm:
            return []
        c = where[:3, 3]
        box = (tuple(c - radius), tuple(c + radius))
        return [n.id for n in self.store.nodes(bbox=box, limit=None, merged=False)
                if n.id in self._tiers.ltm and n.id in self._stamps]

    def place(self, node: int) -> "Place | None":
        """What rehearsal compares a keyframe with, of a node in any memory: its features,
        its words' descriptors and its dense view (None without one). A node in RAM gives
        its own; an LTM node's are read from the database (kept for the next few keyframes)
        and it stays in LTM. None when the node has no stored features."""
        if self._tiers.in_ram(node):
            with self._vocabulary.lock:
                words = self._vocabulary.descriptors(self._vocabulary.node_words(node)[0])
            return Place(self._features[node], words, self._views[node] if node in self._views else None)
        p = self._places.get(node)
        if p is not None:
            self._places.move_to_end(node)
            return p
        assert self.store is not None  # not in RAM: an LTM node, and only a map with a store has LTM
        try:
            keypoints, descriptors, points, word_ids = self.store.load_features(node)
        except UnknownIdError:
            return None
        features = FrameFeatures(keypoints, descriptors, points, np.zeros(len(keypoints), np.int8))
        if word_ids is None:
            words = descriptors
        else:
            w = np.unique(word_ids[word_ids >= 0])
            with self._vocabulary.lock:
                missing = self._vocabulary.missing_words(w)
                held = w[~np.isin(w, missing)]
                words = self._vocabulary.descriptors(held)
            if len(missing):
                words = np.concatenate([words, self.store.load_words(missing)[1]])
        view = None
        if self.loop_config.refine_dense:
            try:
                image, depth = decode_images(*self.store.load_images(node))
                if image is not None and depth is not None:
                    view = DenseView(depth, image, self.camera)
            except Exception:  # a bad image costs this merge's dense refinement only
                view = None
        p = self._places[node] = Place(features, words, view)
        self.places_read += 1
        while len(self._places) > PLACES_KEPT:
            self._places.popitem(last=False)
        return p

    # -- transfer and retrieval --------------------------------------------------------------
    def to_retrieve(self, node: int, best: int | None, pose: NodePoses, merged: bool = False) -> list[int]:
        """After the update of keyframe `node`: the LTM nodes to bring back to WM, those
        around the best loop hypothesis, then those the map places near the keyframe (at most
        `memory.max_retrieved`). None after a keyframe `merged` into a node: it found its
        place (rehearsal compares with LTM's places where they are, without retrieving them)."""
        tiers = self._tiers
        tiers.tick()
        if self.store is None or not tiers.ltm or tiers.max_retrieved <= 0 or merged:
            return []
        retrieved = tiers.select_retrievals([best], self._neighbours)
        retrieved += [n for n in self._ltm_near(node, pose) if n not in retrieved and not tiers.cooling(n)]
        return retrieved[:tiers.max_retrieved]

    def retrieve(self, nodes: list[int]) -> tuple[list[int], dict[int, np.ndarray]]:
        """LTM → WM: features and words back from the database (dense views when first
        needed). Returns the nodes retrieved (one that cannot be loaded stays in LTM), and
        those of them that are the previous map's and in no graph of this map update yet, at
        their stored poses, in that order (the mapper places them, see `_place_previous`)."""
        retrieved, placed = [], {}
        for n in nodes:
            self._places.pop(n, None)  # in RAM from now on
            if self._retrieve(n):
                retrieved.append(n)
                if n not in self._stamps:  # a node of the previous map, not in this map update yet
                    placed.update(self._place_previous([n]))
        self._tiers.retrieved(retrieved)
        return retrieved, placed

    def transfer(self, node: int, update_ms: float, pose: NodePoses) -> list[int]:
        """After the update of keyframe `node` that took `update_ms`: WM's limit follows the
        time budget (`WorkingMemory.adapt`), then WM → LTM when WM is over its limits
        (`WorkingMemory.select_transfers`). Returns the nodes transferred (the mapper's loop
        detector forgets them)."""
        tiers = self._tiers
        tiers.adapt(update_ms)
        if self.store is None or not tiers.over_limit(update_ms):
            return []
        transferred = tiers.select_transfers(update_ms, *self._protected(node, pose))
        for n in transferred:
            self._transfer(n)
        tiers.transferred(transferred)
        return transferred

    def forget(self, nodes) -> None:
        """Nodes leave this map update for good, nothing written (a localizing robot's oldest
        keyframes, which were never stored): their features, dense views and words (those no
        other node has) leave RAM; their ids stay in LTM's list, so nothing links to them anew
        (retrieval finds no stored features for them)."""
        nodes = [int(n) for n in nodes]
        with self._vocabulary.lock:
            for n in nodes:
                self._vocabulary.remove_node(n)
        for n in nodes:
            self._features.pop(n, None)
            self._views.pop(n, None)
            self._places.pop(n, None)
        self._tiers.transferred(nodes)

    def _ltm_near(self, node: int, pose: NodePoses) -> list[int]:
        """LTM nodes the map places where keyframe `node` is (within loop.proximity_radius,
        looking within proximity_angle of its way), nearest first: one R*Tree query of the
        stored poses (the graph's estimates)."""
        c = self.loop_config
        here = pose(node)
        r = c.proximity_radius
        box = (tuple(here[:3, 3] - r), tuple(here[:3, 3] + r))
        assert self.store is not None  # to_retrieve asks only with a store
        # the map's nodes only: keyframes merged by rehearsal keep their rows (and their place in
        # the R*Tree), and a patrolled place holds ever more of them
        # (another map's too: brought back, they are candidates for an appearance link, never for
        # proximity; see same_map)
        nodes = [n for n in self.store.nodes(bbox=box, limit=None, merged=False) if n.id in self._tiers.ltm]
        if not nodes:
            return []
        return nearby(np.stack([n.pose for n in nodes]), np.array([n.id for n in nodes], np.int64), here, r,
                      c.proximity_angle, self._tiers.max_retrieved).tolist()

    def _protected(self, node: int, pose: NodePoses) -> tuple[set[int], set[int]]:
        """(WM nodes that stay in RAM: linked to STM and the last loop closure's; WM nodes that
        go last: those the map places within memory.local_radius of keyframe `node`)."""
        keep = set(self._loop_nodes)
        for s in self._tiers.stm:
            keep.update(self._neighbours.get(s, ()))
        wm, near = self._tiers.wm, set()
        if wm and self.config.local_radius > 0:
            here = pose(node)[:3, 3]
            centres = np.stack([pose(n)[:3, 3] for n in wm])
            close = np.linalg.norm(centres - here, axis=1) <= self.config.local_radius
            near = set(np.asarray(wm)[close].tolist())
        return keep, near

    def _transfer(self, node: int) -> None:
        """WM → LTM: the node's words leave the vocabulary's search structures (under its lock:
        other robots' mappers share it), its features and view leave RAM (everything stays in
        the database)."""
        with self._vocabulary.lock:
            self._vocabulary.unload_node(node)
        self._features.pop(node, None)
        self._views.pop(node, None)

    def _retrieve(self, node: int) -> bool:
        assert self.store is not None  # retrieve: LTM nodes, and only a map with a store has LTM
        try:
            keypoints, descriptors, points, word_ids = self.store.load_features(node)
        except UnknownIdError:
            return False
        self._features[node] = FrameFeatures(keypoints, descriptors, points, np.zeros(len(keypoints), np.int8))
        if word_ids is not None and node not in self._vocabulary:  # an old node another mapper holds is indexed
            with self._vocabulary.lock:
                missing = self._vocabulary.missing_words(word_ids[word_ids >= 0])
                self._vocabulary.reload_node(node, word_ids, descriptors=self.store.load_words(missing)
                                             if len(missing) else None)
        if isinstance(self._views, StoredViews):
            self._views.defer(node)
        return True

    # -- start-up ----------------------------------------------------------------------------
    def load_previous(self) -> dict[int, np.ndarray]:
        """RTAB-Map's start-up on a reopened map (`Memory::loadLastNodes`,
        `Mem/InitWMWithAllNodes` false): the nodes of its ended sessions (the previous map;
        open sessions' are other mappers') go to LTM, ids only, except the newest
        `memory.max_wm_nodes` (all of them with an unlimited WM), which start in WM: their
        features (one query) and words (only their words' descriptors are read). The old
        nodes' graph adjacency (one query, ids only) serves the loop detector's prediction and
        retrieval; they are never "recent" for transfer (the new session's nodes stay first).
        Returns WM's nodes at their stored poses, for the mapper's graph (`_place_previous`)."""
        store = self.store
        assert store is not None  # a reopened map: the mapper has a store
        ids = store.node_ids(ended=True)
        if not len(ids):
            return {}
        self._older = np.sort(np.asarray(ids, np.int64))
        k = self._tiers.max_wm_nodes
        first_wm = ids[-k:] if 0 < k < len(ids) else ids
        features = store.load_features_many(first_wm.tolist())
        wm = [n for n in first_wm.tolist() if n in features]  # a node without features stays in LTM
        pairs = store.link_pairs((LinkType.NEIGHBOR, LinkType.GLOBAL_CLOSURE, LinkType.LOCAL_SPACE))
        pairs = pairs[np.isin(pairs, ids).all(axis=1)]
        for a, b in pairs.tolist():
            self.link(a, b)
        placed = self._place_previous(wm)
        for n in wm:
            kp, desc, pts, _ = features[n]
            self._features[n] = FrameFeatures(kp, desc, pts, np.zeros(len(kp), np.int8))
            if self.loop_config.refine_dense and isinstance(self._views, StoredViews):
                self._views.defer(n)
        self._index_words({n: features[n][3] for n in wm})
        in_ram = set(wm)
        self._tiers.restore(stm=(), wm=wm, ltm=[n for n in ids.tolist() if n not in in_ram])  # keeps weights
        self._tiers.loop_closed()  # the old nodes are not "recent": they leave WM first
        return placed

    def resume(self, session_id: int) -> ResumedSession:
        """A stored session's interrupted map update (`Mapper.resume`): its mapped keyframes in
        STM and WM (merges as rehearsal made them) with their features, words, views (decoded
        when first needed), path segments and adjacency. Returns what the mapper's graph needs
        of it: nodes and links at their stored poses, and its loop closures (appearance and
        proximity links)."""
        store, sid = self.store, int(session_id)
        assert store is not None  # a stored session: the mapper has a store
        unmapped = set(store.unmapped_nodes(session_ids=[sid]).get(sid, ()))
        stored = [n for n in store.nodes(session_id=sid, limit=None) if n.id not in unmapped]  # by id = in time
        nodes = [n for n in stored if n.merged_into is None]
        links = [lk for lk in store.links(session_id=sid) if lk.from_id not in unmapped and lk.to_id not in unmapped]
        merges = {lk.to_id: lk for lk in links if lk.type == LinkType.MERGED}
        self._merged = {k: (lk.from_id, lk.transform) for k, lk in merges.items()}
        odometry, entries = [], []  # odometry links through merged keyframes: to a node, or (rehearsal) to a survivor
        for lk in links:
            if lk.type != LinkType.NEIGHBOR:
                continue
            a, ta = self._merged.get(lk.from_id, (lk.from_id, np.eye(4)))
            b, tb = self._merged.get(lk.to_id, (lk.to_id, np.eye(4)))
            if lk.to_id not in self._merged:
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
        # the previous map's nodes this session linked to: by loops, odometry or merges
        previous = self._place_previous({n for a, b, _, _ in across + entries for n in (a, b) if n not in own})
        incoming = {b: a for a, b, _, _ in odometry}
        for a, b, _, _ in entries:
            if b not in self._neighbours.setdefault(a, []):
                self.link(a, b)
        words = {}
        for n in nodes:
            keypoints, descriptors, points, words[n.id] = store.load_features(n.id)
            self._features[n.id] = FrameFeatures(keypoints, descriptors, points, np.zeros(len(keypoints), np.int8))
            self._stamps[n.id] = n.stamp
            self._order.append(n.id)
            self._neighbours.setdefault(n.id, [])
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
            assert isinstance(self._views, StoredViews)  # a store's views
            for node_id in own:
                self._views.defer(node_id)
        self._index_words(words)  # those the vocabulary does not hold (it loads only WM's with a WM limit)
        k = max(len(self._order) - self._tiers.stm_size, 0)
        self._tiers.restore(stm=self._order[k:], wm=self._order[:k], ltm=(), weights={n.id: n.weight for n in nodes})
        return ResumedSession(
            poses={n.id: n.pose for n in nodes}, odometry=[k for k in odometry if k[0] in own],
            loops=[k for k in loops if k[0] in own and k[1] in own], previous=previous, across=across,
            merge_links=sorted(entries, key=lambda e: e[1]),  # as rehearsal made them
            closures=closures)

    def _place_previous(self, node_ids) -> dict[int, np.ndarray]:
        """Nodes of the previous map enter this map update (those not in it yet): their
        stamps count as older than any `loop.min_age`, their weights are the stored ones.
        Returns them at their stored poses: the mapper's graph places them there, each with
        the tight prior (that map is already optimised, so it stays where it is and anchors
        the new session, which a loop link to it places in the old map's frame)."""
        assert self.store is not None  # previous map's nodes: the mapper has a store
        records = [r for r in self.store.get_nodes(node_ids) if r.id not in self._stamps]
        for r in records:
            self._stamps[r.id] = -np.inf  # another session's: always old enough to be a candidate
            self._neighbours.setdefault(r.id, [])
            self._tiers.weights[r.id] = r.weight
        return {r.id: r.pose for r in records}

    def _index_words(self, words: dict) -> None:
        """Index the words of nodes ({node: word id per feature, or None}) the vocabulary
        does not hold yet, the descriptors of its missing words read in one query."""
        with self._vocabulary.lock:
            todo = {n: w for n, w in words.items() if w is not None and n not in self._vocabulary}
            if not todo:
                return
            missing = self._vocabulary.missing_words(np.concatenate([np.asarray(w, np.int64) for w in todo.values()]))
            assert self.store is not None  # stored nodes' words: the mapper has a store
            self._vocabulary.reload_nodes(todo, descriptors=self.store.load_words(missing) if len(missing) else None)

    # -- the map update's other reads and writes (memory is its one way to the store) ------------
    @staticmethod
    def session_camera(store: MapUpdateStore, session_id: int) -> PinholeCamera:
        """The camera of a stored session (for a map update resumed on it)."""
        return store.calibration(int(session_id)).camera

    def stored_keyframe(self, node_id: int, images: bool = True) -> StoredKeyframe:
        """A keyframe as tracking stored it, read back from the database: its node, features
        (without octaves: the map update does not use them), odometry link and, with `images`,
        the depth and grey image decoded from its stored PNG-16 / JPEG (for dense refinement;
        lossy JPEG, millimetre depth). UnknownIdError for an unknown node."""
        store = self.store
        assert store is not None  # a stored keyframe: the mapper has a store
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
        links = [lk for lk in store.links(node_ids=[node.id], type=LinkType.NEIGHBOR) if lk.to_id == node.id]
        features = FrameFeatures(keypoints, descriptors, points, np.zeros(len(keypoints), np.int8), depth, grey)
        return StoredKeyframe(node, features, links[0] if links else None)

    def save_link(self, from_id: int, to_id: int, kind: LinkType, transform: np.ndarray, information: np.ndarray,
                  *, replace: bool = False) -> None:
        """Store a link the map update put in its graph (loop, proximity, path; with `replace`,
        an odometry link local BA refined)."""
        if self.store is not None:
            self.store.add_link(from_id, to_id, kind, transform, information, replace=replace)

    def save_links(self, links: list[tuple]) -> None:
        """Store links the map update put in its graph together, (from, to, type, transform,
        information) each: all or none (a join's two links)."""
        if self.store is not None and links:
            self.store.add_links(links)

    def save_poses(self, poses: Mapping[int, np.ndarray]) -> None:
        """Store keyframes' map poses ({node: 4×4}) as the graph places them."""
        if self.store is not None and poses:
            self.store.update_poses(poses)

    def save_statistics(self, node: int, statistics: dict) -> None:
        """Store an update's statistics: its last write for the keyframe (a keyframe without them
        has had no map update, `MapStore.unmapped_nodes`)."""
        if self.store is not None:
            self.store.set_statistics(node, statistics)


def series_information(a: np.ndarray | None, b: np.ndarray) -> np.ndarray:
    """Information of two relative poses chained (covariances add; frames not rotated: the
    links chained by rehearsal are short)."""
    if a is None:
        return b
    return np.linalg.inv(np.linalg.inv(a) + np.linalg.inv(b))

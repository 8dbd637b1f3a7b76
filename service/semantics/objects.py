"""From labelled pixels to 3-D objects with Bayesian class histograms.

`extract_segments` turns one keyframe's label image + depth into segments: the labelled
pixels with valid depth (every `stride`-th, vectorised), split at depth discontinuities
(of the median-filtered depth: boundary pixels that carry the background's depth go too),
grouped into
connected components per class (OpenCV), back-projected into the camera frame and clipped
to their 2nd–98th percentile box; small or huge segments and "stuff" classes (walls,
floors: `semantics.ignore`) are dropped. Segments of dynamic classes (people, cars:
`semantics.dynamic`) are left out of the map altogether: they make no object and vote in none
(`ObjectFusion.fuse` counts them in `dynamic_segments`).

`ObjectFusion` keeps the objects. Each is anchored to the keyframe that first saw it: its
surface is a set of voxels in that keyframe's camera frame, so when loop closure moves the
keyframe the object moves with it, and its centroid (stored in the anchor frame) and
extent come from the voxels. A new segment is associated with an existing object by 3-D
overlap regardless of class (the share of the segment's voxels the object already holds,
best candidate above `min_overlap`), so that a wrong label updates the right object's
histogram instead of making a new object; otherwise it starts a new object. The histogram
update is the Bayesian one of Kimera / SemanticFusion: the observed class has likelihood
p, each of the K − 1 others (1 − p) / (K − 1); posterior ∝ prior × likelihood, normalised
and floored at `min_probability`. One wrong frame multiplies the wrong class by
p (K − 1) / (1 − p) relative to the right one, and so does every right frame: the label is
the class with the most evidence, and a single wrong frame cannot flip a label that two or
more frames agree on.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np

from mnemoslam.client.kernel.frames import PinholeCamera
from mnemoslam.storage.records import MAX_OBJECT_KEYFRAMES, ObjectRecord

from ..config import SemanticsConfig

_OFF = 1 << 20  # voxel index offset for packing (±2^20 voxels per axis)


@dataclass
class Segment:
    """One connected region of one class in a keyframe: its points in the camera frame."""

    class_id: int
    points: np.ndarray  # (n, 3) float64, camera frame
    pixels: int  # full-resolution pixels it stands for (n × stride²)
    stuff: bool = False  # an ignored class: votes in the histograms of objects it covers, makes none


def extract_segments(labels: np.ndarray, depth: np.ndarray, camera: PinholeCamera, config: SemanticsConfig,
                     ignore: np.ndarray) -> list[Segment]:
    """The segments of a keyframe. `ignore[c]` True = class c never makes objects: its
    segments come with `stuff` set (they only vote in objects they cover); `ignore[-1]` is
    for ids outside the class table (dropped)."""
    s = max(1, int(config.stride))
    if labels.shape[:2] != depth.shape[:2]:
        labels = cv2.resize(labels, (depth.shape[1], depth.shape[0]), interpolation=cv2.INTER_NEAREST)
    lab = labels[::s, ::s].astype(np.int64)
    d = np.asarray(depth[::s, ::s], np.float64)
    ok = np.isfinite(d) & (d > config.min_depth) & (d < config.max_depth)
    d = np.where(ok, d, 0.0)
    # depth edges on a median-filtered depth: far depth is noisy (σ grows as z²) and would
    # cut a distant object into crumbs
    ds = cv2.medianBlur(d.astype(np.float32), 5).astype(np.float64)
    jump = config.depth_jump * ds
    edge = np.zeros_like(ok)
    dx = np.abs(np.diff(ds, axis=1)) > jump[:, :-1]
    dy = np.abs(np.diff(ds, axis=0)) > jump[:-1, :]
    edge[:, :-1] |= dx
    edge[:, 1:] |= dx
    edge[:-1, :] |= dy
    edge[1:, :] |= dy
    lab = np.where(lab < len(ignore) - 1, lab, len(ignore) - 1)  # ids outside the table: the last (ignored) entry
    keep = ok & ~edge
    min_n = max(4, int(np.ceil(config.min_pixels / (s * s))))
    out: list[Segment] = []
    for c in np.unique(lab[keep]):
        if c == len(ignore) - 1:
            continue
        stuff = bool(ignore[c])
        mask = ((lab == c) & keep).astype(np.uint8)
        n, cc, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=4)
        big = np.flatnonzero(stats[1:, cv2.CC_STAT_AREA] >= min_n) + 1
        if not len(big):
            continue
        ys, xs = np.nonzero(np.isin(cc, big))
        comp = cc[ys, xs]
        z = d[ys, xs]
        if camera.distorted:  # the undistorted ray of each raw pixel
            r = camera.pixel_rays()[np.minimum(ys * s, camera.height - 1), np.minimum(xs * s, camera.width - 1)]
            pts = np.stack([r[:, 0] * z, r[:, 1] * z, z], axis=1)
        else:
            pts = np.stack([(xs * s - camera.cx) * z / camera.fx, (ys * s - camera.cy) * z / camera.fy, z], axis=1)
        order = np.argsort(comp, kind="stable")
        bounds = np.searchsorted(comp[order], big)
        ends = np.append(bounds[1:], len(order))
        for b, e in zip(bounds, ends):
            p = pts[order[b:e]]
            lo, hi = np.percentile(p, [2, 98], axis=0)
            p = p[np.all((p >= lo - 0.05) & (p <= hi + 0.05), axis=1)]
            if len(p) < min_n or (not stuff and np.ptp(p, axis=0).max() > config.max_extent):
                continue
            out.append(Segment(int(c), p, len(p) * s * s, stuff))
    return out


def _pack(keys: np.ndarray) -> np.ndarray:
    k = keys.astype(np.int64) + _OFF
    return (k[:, 0] << 42) | (k[:, 1] << 21) | k[:, 2]


def _unpack(packed: np.ndarray) -> np.ndarray:
    m = (1 << 21) - 1
    return np.stack([(packed >> 42) & m, (packed >> 21) & m, packed & m], axis=1) - _OFF


def bayes_update(hist: np.ndarray, observed: int, p: float, floor: float) -> np.ndarray:
    """Posterior of a class histogram after one observation of class `observed`: likelihood
    p for it, (1 − p) / (K − 1) for every other class, normalised, floored at `floor`."""
    k = len(hist)
    like = np.full(k, (1.0 - p) / max(1, k - 1))
    like[observed] = p
    post = hist * like
    post /= post.sum()
    post = np.maximum(post, floor)
    return post / post.sum()


@dataclass(eq=False)
class FusedObject:
    """An object being fused: its surface voxels in the anchor keyframe's camera frame."""

    node_id: int  # anchor keyframe
    histogram: np.ndarray  # (K,) float64 posterior
    voxels: np.ndarray  # (M,) int64 packed voxel indices, sorted
    counts: np.ndarray  # (M,) hits per voxel
    observations: int = 0
    keyframes: list = field(default_factory=list)
    id: int | None = None  # its row in the map database, once stored
    dirty: bool = True
    centroid: np.ndarray | None = None  # (3,) anchor frame, set by `summarise`
    radius: float = 0.0
    size: float = 0.0  # largest side of its voxels' box (anchor axes)

    @property
    def class_id(self) -> int:
        return int(np.argmax(self.histogram))


class ObjectFusion:
    """The objects of one map, fused keyframe by keyframe (see the module docstring). Not
    thread-safe: one thread (the semantic worker) calls it."""

    def __init__(self, classes: Sequence[str], config: SemanticsConfig):
        self.classes = tuple(classes)
        self.config = config
        self.objects: list[FusedObject] = []
        self.deleted: list[int] = []  # stored ids of objects merged into others (the worker deletes them)
        ignored, dynamic = set(config.ignore), set(config.dynamic)
        self.ignore = np.array([n in ignored for n in self.classes] + [True])  # last: out-of-table ids
        self.dynamic = np.array([n in dynamic for n in self.classes] + [False])  # things that move: never objects
        self.dynamic_segments = 0  # dynamic-class segments in the last keyframe fused (left out)
        self.prior = np.full(len(self.classes), 1.0 / len(self.classes))

    # -- state -------------------------------------------------------------------------------
    def load(self, records: Sequence[ObjectRecord]) -> None:
        """Continue from stored objects (a map reopened): each becomes one voxel at its
        centroid with its extent's corners, so new keyframes can associate with it."""
        v = self.config.voxel
        for r in records:
            if len(r.histogram) != len(self.classes):
                continue  # another class table's objects
            ext = np.asarray(r.extent) / 2
            corners = np.asarray(r.centroid) + np.array([[sx, sy, sz] for sx in (-1, 0, 1) for sy in (-1, 0, 1)
                                                          for sz in (-1, 0, 1)]) * ext
            packed = np.unique(_pack(np.floor(corners / v)))
            o = FusedObject(r.node_id, np.asarray(r.histogram, np.float64), packed, np.full(len(packed), 2),
                            r.observations, list(r.keyframes), r.id, dirty=False)
            self._summarise(o)
            self.objects.append(o)

    def anchors(self) -> set[int]:
        return {o.node_id for o in self.objects}

    def forget(self, object_id: int) -> None:
        """Drop the stored object `object_id` (an operator deleted it), if held."""
        self.objects = [o for o in self.objects if o.id != object_id]

    # -- fusion ------------------------------------------------------------------------------
    def fuse(self, node_id: int, pose: np.ndarray, labels: np.ndarray, depth: np.ndarray, camera: PinholeCamera,
             anchor_poses: Mapping[int, np.ndarray]) -> int:
        """Fuse one keyframe (camera-to-map `pose`, its label image and depth) into the objects.
        `anchor_poses`: the current map poses of the objects' anchors (missing ones are not
        candidates for association). Returns the number of segments fused; segments of a dynamic
        class (`semantics.dynamic`) are not fused, only counted in `dynamic_segments`."""
        segments = extract_segments(labels, depth, camera, self.config, self.ignore)
        moving = self.dynamic[[s.class_id for s in segments]] if segments else np.zeros(0, bool)
        self.dynamic_segments = int(moving.sum())
        segments = [s for s, m in zip(segments, moving) if not m]
        if not segments:
            return 0
        cand = [o for o in self.objects if o.node_id in anchor_poses]
        if cand:
            A = np.stack([anchor_poses[o.node_id] for o in cand])
            centres = np.einsum("nij,nj->ni", A[:, :3, :3], np.stack([o.centroid for o in cand])) + A[:, :3, 3]
            radii = np.array([o.radius for o in cand])
        seen: dict[int, set] = {}
        touched: list[FusedObject] = []
        anchor_poses = {**anchor_poses, node_id: pose}
        p, floor, v = self.config.label_probability, self.config.min_probability, self.config.voxel
        for seg in segments:
            world = seg.points @ pose[:3, :3].T + pose[:3, 3]
            if seg.stuff:
                if cand:
                    self._stuff_votes(seg, world, cand, A, centres, radii, seen, touched)
                continue
            best, best_overlap = None, self.config.min_overlap
            if cand:
                c = world.mean(axis=0)
                r = np.linalg.norm(world - c, axis=1).max()
                for i in np.flatnonzero(np.linalg.norm(centres - c, axis=1) <= radii + r + v):
                    o = cand[i]
                    Ta = A[i]
                    local = (world - Ta[:3, 3]) @ Ta[:3, :3]  # into the anchor frame
                    keys = np.unique(_pack(np.floor(local / v)))
                    hits = np.isin(keys, o.voxels, assume_unique=True)
                    overlap = hits.mean()
                    if hits.sum() < self.config.min_object_share * len(o.voxels):
                        continue  # a small part of a much larger object: (likely) another thing on it
                    if overlap > best_overlap or (overlap == best_overlap and best is not None
                                                  and o.class_id == seg.class_id != best.class_id):
                        best, best_overlap, best_local = o, overlap, local
            if best is None:
                best = FusedObject(node_id, self.prior.copy(), np.zeros(0, np.int64), np.zeros(0, np.int64))
                best_local = seg.points
                self.objects.append(best)
            self._add_voxels(best, best_local)
            classes = seen.setdefault(id(best), set())
            if seg.class_id not in classes:  # one vote per class per keyframe
                classes.add(seg.class_id)
                best.histogram = bayes_update(best.histogram, seg.class_id, p, floor)
            if not best.keyframes or best.keyframes[-1] != node_id:
                best.observations += 1
                best.keyframes = (best.keyframes + [node_id])[-MAX_OBJECT_KEYFRAMES:]
            best.dirty = True
            if all(t is not best for t in touched):
                touched.append(best)
        for o in touched:
            self._summarise(o)
        self._merge_duplicates(touched, anchor_poses)
        return len(segments)

    def _stuff_votes(self, seg, world, cand, A, centres, radii, seen, touched) -> None:
        """A wall / floor / … segment that covers most of an object's voxels, or lies mostly
        inside it (`stuff_cover`), is a vote for that class in its histogram: a region a corrupted
        frame made an object of turns back into wall, and is no longer reported."""
        v = self.config.voxel
        c = world.mean(axis=0)
        r = np.linalg.norm(world - c, axis=1).max()
        for i in np.flatnonzero(np.linalg.norm(centres - c, axis=1) <= radii + r + v):
            o = cand[i]
            keys = np.unique(_pack(np.floor((world - A[i][:3, 3]) @ A[i][:3, :3] / v)))
            # most of the object is this wall, or most of this floor is the object (a floor-sized "object")
            if (np.isin(o.voxels, keys, assume_unique=True).mean() < self.config.stuff_cover
                    and np.isin(keys, o.voxels, assume_unique=True).mean() < self.config.stuff_cover):
                continue
            classes = seen.setdefault(id(o), set())
            if seg.class_id not in classes:
                classes.add(seg.class_id)
                o.histogram = bayes_update(o.histogram, seg.class_id, self.config.label_probability,
                                           self.config.min_probability)
                o.dirty = True
                if all(t is not o for t in touched):
                    touched.append(o)

    def merge_duplicates(self, anchor_poses: Mapping[int, np.ndarray]) -> None:
        """Merge the duplicates among the objects anchored at `anchor_poses`' nodes (after two
        parts of the map were joined: each made its own object of a thing both saw)."""
        self._merge_duplicates([o for o in self.objects if o.node_id in anchor_poses], anchor_poses)

    def _merge_duplicates(self, touched: list[FusedObject], anchor_poses: Mapping[int, np.ndarray]) -> None:
        """Merge an object into another that holds most of its voxels (one thing seen from two
        sides first became two objects): histograms multiply (independent evidence over a
        uniform prior), voxels, observations and keyframes join; the older object stays."""
        v = self.config.voxel
        for o in touched:
            if o not in self.objects or o.node_id not in anchor_poses:
                continue
            To = anchor_poses[o.node_id]
            wo = To[:3, :3] @ o.centroid + To[:3, 3]
            near = [x for x in self.objects if x is not o and x.node_id in anchor_poses]
            if not near:
                continue
            A = np.stack([anchor_poses[x.node_id] for x in near])
            centres = np.einsum("nij,nj->ni", A[:, :3, :3], np.stack([x.centroid for x in near])) + A[:, :3, 3]
            radii = np.array([x.radius for x in near])
            for i in np.flatnonzero(np.linalg.norm(centres - wo, axis=1) <= radii + o.radius):
                other = near[i]
                if other not in self.objects:  # merged meanwhile
                    continue
                Ta = A[i]
                pts = ((_unpack(o.voxels) + 0.5) * v) @ To[:3, :3].T + To[:3, 3]
                local = (pts - Ta[:3, 3]) @ Ta[:3, :3]
                keys = np.unique(_pack(np.floor(local / v)))
                shared = np.isin(keys, other.voxels, assume_unique=True).sum()
                if shared < self.config.merge_overlap * min(len(keys), len(other.voxels)):
                    continue
                keep, gone = (other, o) if self.objects.index(other) < self.objects.index(o) else (o, other)
                Tk, Tg = anchor_poses[keep.node_id], anchor_poses[gone.node_id]
                pts = ((_unpack(gone.voxels) + 0.5) * v) @ Tg[:3, :3].T + Tg[:3, 3]
                self._add_voxels(keep, (pts - Tk[:3, 3]) @ Tk[:3, :3], gone.counts)
                h = keep.histogram * gone.histogram
                h = np.maximum(h / h.sum(), self.config.min_probability)
                keep.histogram = h / h.sum()
                kfs = sorted(set(keep.keyframes) | set(gone.keyframes))
                keep.observations += gone.observations - len(set(keep.keyframes) & set(gone.keyframes))
                keep.keyframes = kfs[-MAX_OBJECT_KEYFRAMES:]
                keep.dirty = True
                self._summarise(keep)
                self.objects.remove(gone)
                if gone.id is not None:
                    self.deleted.append(gone.id)
                if gone is o:
                    break

    def _add_voxels(self, o: FusedObject, local: np.ndarray, counts: np.ndarray | None = None) -> None:
        """Add points (anchor frame) to an object's voxels: one hit per voxel, or `counts`
        hits per point (merging another object's voxels)."""
        packed = _pack(np.floor(local / self.config.voxel))
        if counts is None:
            packed = np.unique(packed)
            counts = np.ones(len(packed))
        u, inv = np.unique(np.concatenate([o.voxels, packed]), return_inverse=True)
        o.voxels = u
        o.counts = np.bincount(inv, weights=np.concatenate([o.counts, counts])).astype(np.int64)

    def _summarise(self, o: FusedObject) -> None:
        centres = (_unpack(o.voxels) + 0.5) * self.config.voxel
        support = o.counts >= 2
        if o.observations >= 3 and support.sum() >= 8:  # voxels seen once: mostly boundary noise
            centres = centres[support]
        o.centroid = centres.mean(axis=0)
        o.size = float(np.ptp(centres, axis=0).max()) if len(centres) else 0.0
        o.radius = float(np.linalg.norm(centres - o.centroid, axis=1).max()) + self.config.voxel

    # -- output ------------------------------------------------------------------------------
    def confirmed(self) -> list[FusedObject]:
        """The objects to report: seen in `min_observations` keyframes, labelled as a thing, no
        larger than `max_extent`."""
        return [o for o in self.objects if o.observations >= self.config.min_observations and self._thing(o)]

    def retired(self) -> list[FusedObject]:
        """Stored objects that are no longer things: labelled as an ignored or dynamic class now,
        or grown larger than `max_extent` (the store should drop them)."""
        return [o for o in self.objects if o.id is not None and not self._thing(o)]

    def _thing(self, o: FusedObject) -> bool:
        """Reported: not stuff, not a dynamic class (a person stored before the class was listed
        as dynamic is retired), no larger than `max_extent`."""
        return not self.ignore[o.class_id] and not self.dynamic[o.class_id] and o.size <= self.config.max_extent

    def record(self, o: FusedObject, anchor_pose: np.ndarray | None) -> ObjectRecord:
        """The stored form of an object (extent along the map axes from the anchor's pose)."""
        v = self.config.voxel
        centres = (_unpack(o.voxels) + 0.5) * v
        support = o.counts >= 2
        if o.observations >= 3 and support.sum() >= 8:
            centres = centres[support]
        R = np.eye(3) if anchor_pose is None else anchor_pose[:3, :3]
        world = centres @ R.T
        lo, hi = np.percentile(world, [2, 98], axis=0) if len(world) > 20 else (world.min(0), world.max(0))
        c = o.class_id
        return ObjectRecord(o.id, o.node_id, c, self.classes[c], float(o.histogram[c]),
                            o.histogram.astype(np.float32), o.centroid.copy(), hi - lo + v, o.observations,
                            np.array(o.keyframes, np.int64))

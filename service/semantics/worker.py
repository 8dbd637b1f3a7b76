"""The semantic worker: fuses keyframes into objects off the tracking thread.

The pipeline hands each keyframe (`SemanticKeyframe`: node id, map pose, image, depth,
the camera's labels or None, camera) to `SemanticWorker.submit`, which only enqueues it
(bounded queue). The worker's thread takes the camera's labels, or segments the image with
the model (`source: auto` takes the labels where a frame carries them), fuses it
(`objects.ObjectFusion`) with the anchors' current poses read from the map database, writes
the confirmed objects that changed (`MapStore.save_objects`) and records the keyframe as
segmented (`MapStore.mark_segmented`). Dynamic classes (`semantics.dynamic`: people, cars)
make no objects; the keyframes that showed one are counted (`dynamic`). Errors are logged
and counted, never raised into tracking.

Coverage: a keyframe that finds the queue full is not lost. It waits in the store
(`deferred`), and whenever the queue is empty the worker back-fills the newest map keyframe
not segmented yet from its stored images with the model (`semantics.backfill`): the
deferred ones, and those of a map made while semantics were off. While robots map (a
keyframe came within `idle_after` seconds) it takes only their live keyframes and rests
after each so as to be busy at most `max_duty` of the time; once they are slow or idle it
back-fills without rest. The map's coverage (keyframes
segmented / keyframes) is `MapStore.segmentation_coverage`.

Tracking first: in the service the worker shares the process (and its GIL) and the cores
with every robot's tracking, which must keep its camera's rate (a robot's frame queue holds
1 s of frames; beyond it frames are dropped). The service gives the worker a probe,
`tracking_busy(margin)`: true while a robot's frame queue holds more than
`semantics.yield_queue` frames or (with `margin`) its tracking used more than 1 -
`semantics.min_slack` of the last second. The worker starts a step (a model run; a fusion,
which is Python and holds the GIL; a back-fill) only while the probe is false, else waits
(counted: `waits`, `wait_s`); keyframes handed over meanwhile find the queue full and wait in
the store for the back-fill. A keyframe that waited `semantics.max_wait` seconds for the
margin goes on without it (the queue still decides), so a robot whose tracking is always
busy still gets a live keyframe segmented every few seconds. `source: auto`'s model
is loaded when the worker starts (`semantics.preload`), not on the first keyframe.

Without `background` (offline runs) `submit` does the work at once, so runs are
reproducible.

One worker serves one map: the service hands every robot's keyframes to the same worker, so
the robots' objects are one set (a door two robots see is one door). A keyframe is compared
only with objects anchored in its own connected part of the map
(`storage.connectivity.MapConnectivity`): robots, sessions and segments not yet joined by a link have
unrelated frames."""
from __future__ import annotations

import collections
import logging
import os
import queue
import threading
import time
from dataclasses import dataclass
from typing import Callable

import cv2
import numpy as np

from mnemoslam.client.kernel.frames import PinholeCamera
from mnemoslam.storage import SemanticStore
from mnemoslam.storage.connectivity import MapConnectivity

from ..config import SemanticsConfig
from ..memory.keyframes import decode_images
from .objects import ObjectFusion
from .segmentation import CameraLabels, Segmenter

log = logging.getLogger("mnemoslam.semantics")


@dataclass
class SemanticKeyframe:
    node_id: int
    pose: np.ndarray  # 4×4 camera-to-map
    image: np.ndarray | None  # H×W×3 BGR or H×W grey (mnemoslam.client.kernel.frames' convention)
    depth: np.ndarray | None  # H×W float32 metres
    labels: np.ndarray | None  # H×W class ids from the camera, or None
    camera: PinholeCamera
    label_names: tuple | None = None  # the camera's class table, when not the configured one
    robot: str = ""  # whose keyframe (the per-robot counts in `stats`)
    backfill: bool = False  # read back from the store by the back-fill (not handed over live)


_STOP = object()
MERGE_AFTER_JOIN = 10.0  # s after a join of two parts of the map (or after the last link read since) that the
# worker merges twin objects in them, at each keyframe and each look (a count of looks ran out in a
# second of fast back-fill while the map update, behind tracking, had not yet written the joined
# robot's corrected poses: twins stayed)
WAITING_LABELS = 512  # deferred keyframes whose camera labels wait in RAM for the back-fill (~5-50 kB each)
WAIT_POLL = 0.02  # s between two looks at the tracking probe while tracking is busy


class SemanticWorker:
    """Segments (model source) and fuses keyframes into objects, and stores them."""

    def __init__(self, store: SemanticStore, segmenter: Segmenter, config: SemanticsConfig, *, background: bool = True,
                 tracking_busy: Callable[[bool], bool] | None = None):
        self.store = store
        self.segmenter = segmenter
        self.config = config
        self.classes = tuple(segmenter.classes)
        self.fusion = ObjectFusion(self.classes, config)
        self.fusion.load(store.objects())
        self.connectivity = MapConnectivity()
        self.processed = self.dropped = self.errors = self.skipped = 0
        self.deferred = 0  # keyframes that found the queue full: left to the back-fill
        self.backfilled = 0  # keyframes segmented by the back-fill (of `processed`)
        self.backfills = bool(config.backfill) and background
        self._model = not isinstance(segmenter, CameraLabels)  # the back-fill of unlabelled keyframes needs it
        self._queued: set[int] = set()  # node ids in the queue (the back-fill leaves them)
        # deferred keyframes' camera labels (not stored): node id -> (PNG, label names, camera, robot)
        self._waiting: collections.OrderedDict[int, tuple] = collections.OrderedDict()
        self._cameras: dict[int, PinholeCamera] = {}  # session id -> camera (back-fill)
        self._last_keyframe = -float("inf")  # time.monotonic() of the last keyframe handed over
        self._merge_until = -float("inf")  # time.monotonic() until which twin objects are merged after a join
        self.dynamic = 0  # keyframes processed that showed a dynamic-class thing (left out of the map)
        self._per_robot: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)
        self.last_error: str | None = None
        self.seconds = 0.0
        self.waits = 0  # steps (model run, fusion) that waited for tracking (`tracking_busy`)
        self.wait_s = 0.0  # ... and the seconds they waited
        # the service's probe: tracking_busy(margin) is True while a robot's tracking needs the
        # cores (its frame queue, and with `margin` its frame-time margin, see the module's
        # doc); None: never wait (offline runs)
        self.tracking_busy = tracking_busy
        self._closing = threading.Event()  # close(): the queued keyframes are done without waiting
        self._queue: queue.Queue | None = None
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()  # fusion state vs `flush` from another thread
        if background:
            self._queue = queue.Queue(maxsize=max(1, int(config.queue_size)))
            self._thread = threading.Thread(target=self._loop, daemon=True, name="mnemoslam-semantics")
            self._thread.start()

    @property
    def source(self) -> str:
        """The configured source: "camera", "model" or "auto" (camera labels, else the model)."""
        if isinstance(self.segmenter, CameraLabels):
            return "camera"
        return "auto" if self.config.source == "auto" else "model"

    def submit(self, kf: SemanticKeyframe) -> bool:
        """Hand a keyframe over; False when the queue was full (then it waits in the store for
        the back-fill: `deferred`, or is `dropped` when there is no back-fill)."""
        self._last_keyframe = time.monotonic()
        if self._queue is None:
            self._process(kf)
            return True
        try:
            self._queued.add(kf.node_id)
            self._queue.put_nowait(kf)
            return True
        except queue.Full:
            self._queued.discard(kf.node_id)
            self._count(kf, "deferred" if self._defer(kf) else "dropped")
            return False

    def _defer(self, kf: SemanticKeyframe) -> bool:
        """Leave a keyframe that found the queue full to the back-fill: its images are in the
        store; the camera's labels (not stored) wait here, lossless PNG (a few kB), at most
        `WAITING_LABELS` of them. False when the back-fill cannot take it."""
        if not self.backfills:
            return False
        if kf.labels is None or self.config.source == "model":
            return self._model
        if len(self._waiting) >= WAITING_LABELS:
            return False
        ok, png = cv2.imencode(".png", kf.labels)
        if not ok:
            return False
        self._waiting[kf.node_id] = (png.tobytes(), kf.label_names, kf.camera, kf.robot)
        return True

    def close(self, timeout: float = 60.0) -> None:
        """Finish the queued keyframes and write the objects (idempotent)."""
        self._closing.set()
        if self._thread is not None:
            self._queue.put(_STOP)
            self._thread.join(timeout)
            self._thread = None
        self.flush()

    def delete(self, object_id: int) -> int:
        """Drop a stored object from the fusion and the map at once (an operator's correction:
        a chair moved away, a wrong label). A thing still in view comes back as a new object.
        Returns the rows deleted (0: no such object)."""
        with self._lock:
            self.fusion.forget(int(object_id))
            return self.store.delete_objects([int(object_id)])

    def stats(self, robot: str | None = None) -> dict:
        """Keyframes processed, dropped, failed and skipped, and those processed that showed a
        dynamic-class thing (a person: `dynamic`, not mapped) (of `robot`'s keyframes when
        given, else of all), and the map's objects."""
        keys = ("processed", "dropped", "deferred", "backfilled", "errors", "skipped", "dynamic", "waits", "wait_s")
        counts = self._per_robot.get(robot, collections.Counter()) if robot is not None else {
            k: getattr(self, k) for k in keys}
        out = {k: counts.get(k, 0) for k in keys}
        out["wait_s"] = round(out["wait_s"], 2)
        return {**out, "objects": len(self.fusion.confirmed()), "last_error": self.last_error,
                "ms_per_keyframe": 1e3 * self.seconds / self.processed if self.processed else None}

    def _count(self, kf: SemanticKeyframe, what: str, n: float = 1) -> None:
        setattr(self, what, getattr(self, what) + n)
        self._per_robot[kf.robot][what] += n

    def _busy(self, margin: bool = True) -> bool:
        """The probe: does a robot's tracking need the cores now (its queue, and with `margin`
        its frame-time margin)? (False without a probe, and once closing; a probe that fails
        counts as not busy.)"""
        probe = self.tracking_busy
        if probe is None or self._closing.is_set():
            return False
        try:
            return bool(probe(margin))
        except Exception as e:  # (a session ending under it)
            log.debug("semantics: tracking probe: %s", e)
            return False

    def _yield_to_tracking(self, kf: SemanticKeyframe, waited: float = 0.0) -> float:
        """Wait while tracking needs the cores (`tracking_busy`) before a step of `kf`, which
        already waited `waited` seconds; past `semantics.max_wait` the margin no longer
        counts, only the queues. Returns the seconds `kf` has waited."""
        bound = float(self.config.max_wait)
        margin = not (bound > 0 and waited >= bound)
        if not self._busy(margin):
            return waited
        t = time.perf_counter()
        while self._busy(margin):
            time.sleep(WAIT_POLL)
            if margin and bound > 0 and waited + time.perf_counter() - t >= bound:
                margin = False
        dt = time.perf_counter() - t
        self._count(kf, "waits")
        self._count(kf, "wait_s", dt)
        return waited + dt

    # -- the worker's thread ----------------------------------------------------------------
    def _loop(self) -> None:
        if self.config.nice:  # below tracking's CPU priority (Linux: nice is per thread)
            try:
                os.setpriority(os.PRIO_PROCESS, threading.get_native_id(),
                               os.getpriority(os.PRIO_PROCESS, threading.get_native_id()) + int(self.config.nice))
            except (AttributeError, OSError) as e:  # pragma: no cover - not Linux
                log.info("semantic worker keeps its priority: %s", e)
        if self.config.preload and callable(getattr(self.segmenter, "load", None)):
            try:  # source auto's model now, before robots stream (it costs tracking a stall on a first keyframe)
                t = time.perf_counter()
                self.segmenter.load()
                log.info("semantics: model %s loaded in %.2f s", self.segmenter.name, time.perf_counter() - t)
            except Exception as e:  # said again, and counted, on each keyframe that needs it
                log.warning("semantics: %s", e)
        duty = min(1.0, max(0.05, float(self.config.max_duty)))
        backfilling = False  # the last look found a keyframe to back-fill: look again at once
        while True:
            try:
                kf = self._queue.get(block=not backfilling, timeout=0.5)
            except queue.Empty:  # the back-fill: only while no robot maps (slow or idle), tracking keeps the cores
                self._merge_joined()  # (and twins of parts joined after their last keyframe)
                if not self.backfills:
                    continue
                idle = time.monotonic() - self._last_keyframe >= float(self.config.idle_after)
                kf = self._next_backfill() if idle and not self._busy() else None
                backfilling = kf is not None
                if kf is None:
                    continue
            if kf is _STOP:
                return
            self._queued.discard(kf.node_id)
            t = time.perf_counter()
            self._process(kf)
            mapping = time.monotonic() - self._last_keyframe < float(self.config.idle_after)
            if duty < 1.0 and mapping:  # rest in proportion: busy at most `max_duty` of the time (a stop waits)
                time.sleep((time.perf_counter() - t) * (1.0 / duty - 1.0))

    def _read_links(self, fusing: bool) -> float:
        """The links stored since the last look (under `_lock`); opens the twin-merge window
        (MERGE_AFTER_JOIN from now) when they joined parts of the map, or while links come within
        it, or, for a keyframe being fused (`fusing`), once any join was seen: a keyframe fused,
        or a pose corrected, after a window the links alone kept open left twins when the worker
        ran behind the map update. Returns now (time.monotonic)."""
        joins = self.connectivity.joins
        read = self.connectivity.refresh(self.store)
        now = time.monotonic()
        joined = self.connectivity.joins > joins or (fusing and self.connectivity.joins > 0)
        if joined or (read and now < self._merge_until):
            self._merge_until = now + MERGE_AFTER_JOIN
        return now

    def _merge_joined(self) -> None:
        """Between keyframes: when links stored since the last look joined parts of the map
        (robots mapping at the same time: the map update, behind tracking, may join them after
        their last keyframe was fused), the twin objects of every part are merged, and written.
        Again at each look while the map update stores links, and for MERGE_AFTER_JOIN seconds
        after its last: the map update runs behind tracking, so the keyframes the joining robot made
        after the joining one get their poses in the joined map's frame only as it catches up."""
        try:
            with self._lock:
                now = self._read_links(fusing=False)
                if now >= self._merge_until:
                    return
                anchors = np.array(sorted(self.fusion.anchors()), np.int64)
                if not len(anchors):
                    return
                roots = self.connectivity.roots(anchors)
                poses = {n.id: n.pose for n in self.store.get_nodes(anchors.tolist())}
                for root in np.unique(roots).tolist():
                    part = anchors[roots == root].tolist()
                    if len(part) > 1:
                        self.fusion.merge_duplicates({n: poses[n] for n in part if n in poses})
            self.flush()
        except Exception as e:  # the store closing under a stopping service: the next look tries again
            log.debug("semantics: merge after a join: %s", e)

    def _next_backfill(self) -> SemanticKeyframe | None:
        """The next keyframe to back-fill, read back from the store (pose, images): the newest
        deferred one with the camera's labels, else (with a model) the newest map keyframe not
        segmented yet and not queued. A keyframe whose images cannot be decoded is recorded
        as skipped."""
        try:
            labels = None
            if self._waiting:
                node_id, labels = self._waiting.popitem(last=True)
            elif self._model:
                busy = self._queued | set(self._waiting)
                ids = [n for n in self.store.unsegmented_nodes(limit=len(busy) + 4) if n not in busy]
                if not ids:
                    return None
                node_id = ids[0]
            else:
                return None
            nodes = self.store.get_nodes([node_id])
            if not nodes:
                return None  # deleted meanwhile
            node = nodes[0]
            try:
                image, depth = decode_images(*self.store.load_images(node.id))
            except ValueError as e:
                log.warning("semantics: keyframe %d's stored images are not usable: %s", node.id, e)
                self.store.mark_segmented([node.id], "camera" if labels else "model", "skipped")
                return None
            if labels is not None:
                png, names, camera, robot = labels
                return SemanticKeyframe(node.id, node.pose, image, depth,
                                        cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED), camera,
                                        names, robot, backfill=True)
            if node.session_id not in self._cameras:
                self._cameras[node.session_id] = self.store.calibration(node.session_id).camera
            return SemanticKeyframe(node.id, node.pose, image, depth, None, self._cameras[node.session_id],
                                    robot=node.robot, backfill=True)
        except Exception as e:  # the store closing under a stopping service, a deleted node: try again later
            log.debug("semantics: back-fill: %s", e)
            return None

    def _process(self, kf: SemanticKeyframe) -> None:
        t = time.perf_counter()
        source = "camera" if kf.labels is not None and self.config.source != "model" else "model"
        try:
            waited = 0.0
            if kf.depth is not None and (kf.labels is None or self.config.source == "model"):
                waited = self._yield_to_tracking(kf)  # the model run
            labels = self._labels(kf) if kf.depth is not None else None  # (no depth: no model run for nothing)
            if labels is None or kf.depth is None:
                self._count(kf, "skipped")
                # nothing to segment, ever (no depth, no image); an unlabelled keyframe without a
                # model stays unsegmented: a model configured later back-fills it
                if kf.depth is None or kf.image is None or not isinstance(self.segmenter, CameraLabels):
                    self.store.mark_segmented([kf.node_id], source, "skipped")
                return
            self._yield_to_tracking(kf, waited)  # the fusion (Python: it holds the GIL tracking needs)
            with self._lock:
                self._read_links(fusing=True)  # the links stored since the last keyframe
                anchors = np.array(sorted(self.fusion.anchors()), np.int64)
                anchors = anchors[self.connectivity.roots(anchors) == self.connectivity.find(kf.node_id)].tolist()
                poses = {n.id: n.pose for n in self.store.get_nodes(anchors)} if anchors else {}
                self.fusion.fuse(kf.node_id, kf.pose, labels, kf.depth, kf.camera, poses)
                moving = self.fusion.dynamic_segments
                if time.monotonic() < self._merge_until:
                    # (over the next keyframes too: the join's corrected poses reach the store after its link)
                    self.fusion.merge_duplicates(poses)
            self.flush()
            self.store.mark_segmented([kf.node_id], source, "fused")
            self._count(kf, "processed")
            if kf.backfill:
                self._count(kf, "backfilled")
            if moving:
                self._count(kf, "dynamic")
        except Exception as e:  # never into tracking: log, count, go on
            self._count(kf, "errors")
            self.last_error = f"{type(e).__name__}: {e}"
            log.exception("semantics: keyframe %d failed", kf.node_id)
            if kf.backfill:  # the back-fill does not try it again (a live one gets one more try)
                try:
                    self.store.mark_segmented([kf.node_id], source, "skipped")
                except Exception:  # pragma: no cover - the store is closing
                    pass
        finally:
            self.seconds += time.perf_counter() - t

    def _labels(self, kf: SemanticKeyframe) -> np.ndarray | None:
        if kf.labels is not None and self.config.source != "model":  # the camera's labels (camera, auto)
            if kf.label_names and tuple(kf.label_names) != self.classes:  # the camera's table -> ours, by name
                index = {n: i for i, n in enumerate(self.classes)}
                lut = np.array([index.get(n, len(self.classes)) for n in kf.label_names] + [len(self.classes)],
                               np.int64)
                return lut[np.minimum(kf.labels.astype(np.int64), len(lut) - 1)]
            return kf.labels
        if kf.image is None or isinstance(self.segmenter, CameraLabels):
            return None
        # frames are BGR (or grey), the project's convention; the models take RGB
        rgb = cv2.cvtColor(kf.image, cv2.COLOR_BGR2RGB if kf.image.ndim == 3 else cv2.COLOR_GRAY2RGB)
        return self.segmenter.segment(rgb, kf.depth)

    def flush(self) -> None:
        """Write the confirmed objects that changed since they were last written."""
        with self._lock:
            for o in self.fusion.retired():  # now labelled wall, floor, …: no longer an object
                self.fusion.deleted.append(o.id)
                o.id = None
            if self.fusion.deleted:  # merged into other objects, or retired
                self.store.delete_objects(self.fusion.deleted)
                self.fusion.deleted.clear()
            todo = [o for o in self.fusion.confirmed() if o.dirty]
            if not todo:
                return
            anchors = {n.id: n.pose for n in self.store.get_nodes({o.node_id for o in todo})}
            todo = [o for o in todo if o.node_id in anchors]  # (an anchor deleted meanwhile: not stored)
            ids = self.store.save_objects([self.fusion.record(o, anchors[o.node_id]) for o in todo])
            for o, i in zip(todo, ids):
                o.id, o.dirty = i, False

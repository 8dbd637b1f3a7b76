"""The semantic worker: fuses keyframes into objects off the tracking thread.

The pipeline hands each keyframe (`SemanticKeyframe`: node id, map pose, image, depth,
the camera's labels or None, camera) to `SemanticWorker.submit`, which only enqueues it
(bounded queue; when full the keyframe is dropped and counted). The worker's thread
segments it when the source is a model, fuses it (`objects.ObjectFusion`) with the anchors'
current poses read from the map database, and writes the confirmed objects that changed
(`MapStore.save_objects`). Dynamic classes (`semantics.dynamic`: people, cars) make no
objects; the keyframes that showed one are counted (`dynamic`). Errors are logged and
counted, never raised into tracking.
Without `background` (offline runs) `submit` does the work at once, so runs are
reproducible.

One worker serves one map: the service hands every robot's keyframes to the same worker, so
the robots' objects are one set (a door two robots see is one door). A keyframe is compared
only with objects anchored in its own connected part of the map
(`connectivity.MapConnectivity`): robots, sessions and segments not yet joined by a link have
unrelated frames."""
from __future__ import annotations

import collections
import logging
import os
import queue
import threading
import time
from dataclasses import dataclass

import cv2
import numpy as np

from client.frames import PinholeCamera

from ..config import SemanticsConfig
from .connectivity import MapConnectivity
from .objects import ObjectFusion
from .segmentation import CameraLabels, Segmenter

log = logging.getLogger("mnemoslam.semantics")


@dataclass
class SemanticKeyframe:
    node_id: int
    pose: np.ndarray  # 4×4 camera-to-map
    image: np.ndarray | None  # H×W×3 BGR or H×W grey (client.frames' convention)
    depth: np.ndarray | None  # H×W float32 metres
    labels: np.ndarray | None  # H×W class ids from the camera, or None
    camera: PinholeCamera
    label_names: tuple | None = None  # the camera's class table, when not the configured one
    robot: str = ""  # whose keyframe (the per-robot counts in `stats`)


_STOP = object()


class SemanticWorker:
    """Segments (model source) and fuses keyframes into objects, and stores them."""

    def __init__(self, store, segmenter: Segmenter, config: SemanticsConfig, *, background: bool = True):
        self.store = store
        self.segmenter = segmenter
        self.config = config
        self.classes = tuple(segmenter.classes)
        self.fusion = ObjectFusion(self.classes, config)
        self.fusion.load(store.objects())
        self.connectivity = MapConnectivity()
        self.processed = self.dropped = self.errors = self.skipped = 0
        self.dynamic = 0  # keyframes processed that showed a dynamic-class thing (left out of the map)
        self._per_robot: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)
        self.last_error: str | None = None
        self.seconds = 0.0
        self._queue: queue.Queue | None = None
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()  # fusion state vs `flush` from another thread
        if background:
            self._queue = queue.Queue(maxsize=max(1, int(config.queue_size)))
            self._thread = threading.Thread(target=self._loop, daemon=True, name="mnemoslam-semantics")
            self._thread.start()

    @property
    def source(self) -> str:
        return "camera" if isinstance(self.segmenter, CameraLabels) else "model"

    def submit(self, kf: SemanticKeyframe) -> bool:
        """Hand a keyframe over; False when it was dropped (queue full)."""
        if self._queue is None:
            self._process(kf)
            return True
        try:
            self._queue.put_nowait(kf)
            return True
        except queue.Full:
            self._count(kf, "dropped")
            return False

    def close(self, timeout: float = 60.0) -> None:
        """Finish the queued keyframes and write the objects (idempotent)."""
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
        counts = self._per_robot.get(robot, collections.Counter()) if robot is not None else {
            "processed": self.processed, "dropped": self.dropped, "errors": self.errors, "skipped": self.skipped,
            "dynamic": self.dynamic}
        out = {k: counts.get(k, 0) for k in ("processed", "dropped", "errors", "skipped", "dynamic")}
        return {**out, "objects": len(self.fusion.confirmed()), "last_error": self.last_error,
                "ms_per_keyframe": 1e3 * self.seconds / self.processed if self.processed else None}

    def _count(self, kf: SemanticKeyframe, what: str) -> None:
        setattr(self, what, getattr(self, what) + 1)
        self._per_robot[kf.robot][what] += 1

    # -- the worker's thread ----------------------------------------------------------------
    def _loop(self) -> None:
        if self.config.nice:  # below tracking's CPU priority (Linux: nice is per thread)
            try:
                os.setpriority(os.PRIO_PROCESS, threading.get_native_id(),
                               os.getpriority(os.PRIO_PROCESS, threading.get_native_id()) + int(self.config.nice))
            except (AttributeError, OSError) as e:  # pragma: no cover - not Linux
                log.info("semantic worker keeps its priority: %s", e)
        duty = min(1.0, max(0.05, float(self.config.max_duty)))
        while True:
            kf = self._queue.get()
            if kf is _STOP:
                return
            t = time.perf_counter()
            self._process(kf)
            if duty < 1.0:  # rest in proportion: busy at most `max_duty` of the time (a stop waits for it)
                time.sleep((time.perf_counter() - t) * (1.0 / duty - 1.0))

    def _process(self, kf: SemanticKeyframe) -> None:
        t = time.perf_counter()
        try:
            labels = self._labels(kf)
            if labels is None or kf.depth is None:
                self._count(kf, "skipped")
                return
            with self._lock:
                self.connectivity.refresh(self.store)  # the links stored since the last keyframe
                anchors = np.array(sorted(self.fusion.anchors()), np.int64)
                anchors = anchors[self.connectivity.roots(anchors) == self.connectivity.find(kf.node_id)].tolist()
                poses = {n.id: n.pose for n in self.store.get_nodes(anchors)} if anchors else {}
                self.fusion.fuse(kf.node_id, kf.pose, labels, kf.depth, kf.camera, poses)
                moving = self.fusion.dynamic_segments
            self.flush()
            self._count(kf, "processed")
            if moving:
                self._count(kf, "dynamic")
        except Exception as e:  # never into tracking: log, count, go on
            self._count(kf, "errors")
            self.last_error = f"{type(e).__name__}: {e}"
            log.exception("semantics: keyframe %d failed", kf.node_id)
        finally:
            self.seconds += time.perf_counter() - t

    def _labels(self, kf: SemanticKeyframe) -> np.ndarray | None:
        if self.source == "camera":
            if kf.labels is None:
                return None
            if kf.label_names and tuple(kf.label_names) != self.classes:  # the camera's table -> ours, by name
                index = {n: i for i, n in enumerate(self.classes)}
                lut = np.array([index.get(n, len(self.classes)) for n in kf.label_names] + [len(self.classes)],
                               np.int64)
                return lut[np.minimum(kf.labels.astype(np.int64), len(lut) - 1)]
            return kf.labels
        if kf.image is None:
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

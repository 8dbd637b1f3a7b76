"""The per-frame SLAM pipeline, the same for the offline runner and the service:
extract → track → decide keyframe → remember it (memory, loop closure, optimization) →
fuse its semantics (handed to the semantic worker, off the tracking thread)."""
from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass, field

import numpy as np

from mnemoslam.client.kernel.frames import Calibration, Frame

from .config import Config
from .mapping.mapper import KeyframeUpdate
from .semantics.worker import SemanticKeyframe
from .tracking.features import FeatureExtractor
from .tracking.keyframes import KeyframePolicy
from .tracking.odometry import Odometry

log = logging.getLogger("mnemoslam.pipeline")


@dataclass
class FrameResult:
    """What the pipeline did with one frame."""

    index: int
    stamp: float
    status: str  # "ok", "init", "lost", or "skipped" (no usable depth)
    pose: np.ndarray | None
    keyframe: str | None = None  # why it became a keyframe, if it did
    node_id: int | None = None  # its id in the map's memory, once stored
    inliers: int = 0
    segment: int = 0
    features: int = 0
    timings: dict = field(default_factory=dict)  # ms per step
    odometry_pose: np.ndarray | None = None  # the odometry's pose (before the map correction in `pose`)
    # localization only: the map's keyframe the robot's keyframes are linked to when the pose was
    # made (its pose is in that map's frame), None while it is not relocalized (its own frame)
    anchor: int | None = None

    @property
    def tracked(self) -> bool:
        return self.pose is not None


class Pipeline:
    """One SLAM session for one camera."""

    def __init__(self, calibration: Calibration, config: Config, writer=None, mapper=None, semantics=None,
                 semantics_off: str | None = None, *, robot: str = "", owns_semantics: bool = True):
        self.calibration = calibration
        self.config = config
        self.writer = writer  # memory.keyframes.KeyframeWriter (the session in the map), or None for odometry alone
        self.mapper = mapper  # service.mapping.mapper.Mapper (loop closure + graph), or None
        self.semantics = semantics  # service.semantics.worker.SemanticWorker, or None
        self.semantics_off = semantics_off  # why semantics are off (None when on)
        self.robot = robot
        self._owns_semantics = owns_semantics  # False: the map's shared worker, closed by its owner
        self.extractor = FeatureExtractor(calibration, config.features, config.stereo)
        self.odometry = Odometry(calibration.camera, config.odometry, seed=config.seed, stereo=config.stereo,
                                 baseline=calibration.baseline)
        self.keyframes = KeyframePolicy(config.keyframe)
        self.images_withheld = 0  # keyframes handed to the map update without images (its backlog was full)

    @property
    def session_id(self) -> int | None:
        """The map database's session of this pipeline (None for odometry alone)."""
        return self.writer.session_id if self.writer is not None else None

    @property
    def localizing(self) -> bool:
        """Localization only: nothing of this session is written to the map (no database
        session; `FrameResult.anchor` says when its poses are in a map's frame)."""
        return self.writer is not None and self.writer.session_id is None

    @property
    def map_progress(self) -> tuple[int, int]:
        """(keyframes the map update has done, keyframes handed to it); equal = no backlog."""
        if self.mapper is None:
            return 0, 0
        return self.mapper.mapped, self.mapper.submitted

    def close(self, reason: str = "stopped") -> None:
        """End the session: the map update finishes its queued keyframes (and writes its final
        poses), then the session is closed in the database with `reason`."""
        if self.mapper is not None:
            self.mapper.close()
        # after the final poses: objects are written against them
        if self.semantics is not None and self._owns_semantics:
            self.semantics.close()
        if self.writer is not None:
            self.writer.close(reason)

    def process(self, frame: Frame) -> FrameResult:
        t0 = time.perf_counter()
        if not self._has_geometry(frame):
            log.warning("frame %d (%s): no valid depth, skipped", frame.index, frame.source)
            return FrameResult(frame.index, frame.stamp, "skipped", None)
        features = self.extractor.extract(frame)
        t1 = time.perf_counter()
        tracked = self.odometry.track(features, frame.stamp, frame.extras.get("depth_stamp"))
        if self.odometry.disparity_offset is not None:  # stereo: the next frames use the latest estimate
            self.extractor.disparity_offset = self.odometry.disparity_offset
        t2 = time.perf_counter()
        keyframe = self.keyframes.decide(tracked)
        node_id = self._remember(frame, features, tracked) if keyframe else None
        anchor = getattr(self.mapper, "anchor", None) if self.localizing else None
        pose = (self.mapper.to_map(tracked.pose) if self.mapper is not None and tracked.pose is not None
                else tracked.pose)
        if node_id is not None:
            self._fuse_semantics(frame, node_id, pose)
        t3 = time.perf_counter()
        return FrameResult(
            frame.index, frame.stamp, tracked.status, pose, keyframe, node_id, tracked.inliers,
            tracked.segment, len(features),
            {"features": (t1 - t0) * 1e3, "track": (t2 - t1) * 1e3, "memory": (t3 - t2) * 1e3}, tracked.pose,
            anchor if tracked.pose is not None else None,
        )

    def _remember(self, frame: Frame, features, tracked) -> int | None:
        """Store the keyframe (its session's writer), then hand it to the map update (loop closure)."""
        if self.writer is None:
            return None
        node_id = self.writer.add_keyframe(frame, features, tracked.pose, tracked.inliers, tracked.segment)
        if self.mapper is not None:
            link = self.writer.last_link
            mapped, submitted = self.map_progress
            if features.depth is not None and submitted - mapped >= self.config.loop.backlog_images:
                # the map update is this far behind (a loaded machine): the keyframe waits without
                # its images (97 % of an update's 1.6 MB at 640x480), so the backlog's memory stays
                # bounded; the map update then makes no dense view of it (issue 24)
                features = dataclasses.replace(features, depth=None, grey=None)
                self.images_withheld += 1
                if self.images_withheld == 1 or self.images_withheld % 100 == 0:
                    log.warning("robot %s: the map update is %d keyframes behind (loop.backlog_images %d): "
                                "keyframes go to it without images, %d so far", self.robot, submitted - mapped,
                                self.config.loop.backlog_images, self.images_withheld)
            self.mapper.submit(KeyframeUpdate(node_id, frame.stamp, tracked.pose, features,
                                              *(link if link else (None, None, None)), tracked.point_ids))
        return node_id

    def _fuse_semantics(self, frame: Frame, node_id: int, pose: np.ndarray) -> None:
        """Hand the keyframe to the semantic worker (it segments and fuses it on its thread)."""
        if self.semantics is None:
            return
        self.semantics.submit(SemanticKeyframe(node_id, pose, frame.image, frame.depth, frame.extras.get("labels"),
                                               self.calibration.camera, frame.extras.get("label_names"),
                                               self.robot))

    def _has_geometry(self, frame: Frame) -> bool:
        if self.calibration.baseline:
            return frame.right is not None
        if frame.depth is None:
            return False
        d = frame.depth
        # (a valid reading among every 8th pixel of every 8th row answers for the whole image
        # without a pass over all of it; an empty or sparse image gets the full pass)
        return bool(np.any(_valid_depth(d[::8, ::8])) or np.any(_valid_depth(d)))


def _valid_depth(d: np.ndarray) -> np.ndarray:
    """Pixels with a depth reading (finite and positive)."""
    return np.isfinite(d) & (d > 0)

"""Keyframe writes on the tracking side: every keyframe goes to the SQLite long-term memory in
one transaction before it is reported (so RAM never holds the only copy), linked to the
previous keyframe by its odometry constraint (`KeyframeWriter`, one per session). What the map
update keeps of it in RAM, and when, is memory's (`manager.Memory`)."""
from __future__ import annotations

import logging

import cv2
import numpy as np

from mnemoslam.client.kernel.frames import Calibration, Frame
from mnemoslam.client.kernel.geometry import invert
from mnemoslam.storage import KeyframeLog, KeyframeRecord, LocalGridRecord, StoreError

from ..config import Config, to_dict
from ..grid.local import LocalGridMaker
from ..tracking.features import FrameFeatures

log = logging.getLogger("mnemoslam.memory")


def odometry_information(inliers: int) -> np.ndarray:
    """6×6 information (rotation first, GTSAM's Pose3 order) of a registration supported by
    `inliers` correspondences: σ shrinks as 1/√inliers (1 cm, 0.3° at 100 inliers)."""
    k = np.sqrt(100.0 / max(inliers, 10))
    sigmas = np.array([0.005] * 3 + [0.01] * 3) * k
    return np.diag(1.0 / sigmas**2)


class KeyframeWriter:
    """A session of one robot in the map: its keyframes written as tracking makes them."""

    def __init__(self, store: KeyframeLog, robot: str, calibration: Calibration, config: Config):
        self.store = store
        self.config = config
        self.session_id = store.begin_session(robot, calibration, to_dict(config))
        self.last_node: int | None = None
        self.last_pose: np.ndarray | None = None
        self.last_segment: int | None = None
        self.last_link: tuple | None = None
        # each RGB-D keyframe's local occupancy grid, made and stored here (issue 25)
        self.grids = LocalGridMaker(calibration.camera, config.grid) if config.grid.enabled else None

    def close(self, reason: str = "stopped") -> None:
        """The session ended, for `reason` (its keyframes are all committed already)."""
        self.store.end_session(self.session_id, reason=reason)

    def add_keyframe(self, frame: Frame, features: FrameFeatures, pose: np.ndarray, inliers: int,
                     segment: int, statistics: dict | None = None) -> int:
        """Persist a keyframe (node, features, images, odometry link) and return its id."""
        link = None
        if self.last_node is not None and segment == self.last_segment:
            assert self.last_pose is not None  # set with last_node
            link = (self.last_node, invert(self.last_pose) @ pose, odometry_information(inliers))
        image_jpeg = depth_png = None
        if self.config.storage.keep_images:
            image_jpeg = _encode(".jpg", frame.image, [cv2.IMWRITE_JPEG_QUALITY, self.config.storage.jpeg_quality])
            if frame.depth is not None:
                mm = np.where(np.isfinite(frame.depth), frame.depth * 1000.0, 0)
                depth_png = _encode(".png", np.clip(np.rint(mm), 0, 65535).astype(np.uint16))
        self.last_link = link  # (previous node, T_prev_this, information) of this keyframe, or None
        node_id = self.store.add_keyframe(KeyframeRecord(
            session_id=self.session_id, stamp=frame.stamp, pose=pose, keypoints=features.keypoints,
            descriptors=features.descriptors, points=features.points, image_jpeg=image_jpeg,
            depth_png=depth_png, odom_link=link, statistics=statistics,
        ))
        self.last_node, self.last_pose, self.last_segment = node_id, pose, segment
        if self.grids is not None and frame.depth is not None:
            self._save_grid(node_id, frame, pose, segment)
        return node_id

    def _save_grid(self, node_id: int, frame: Frame, pose: np.ndarray, segment: int) -> None:
        """The keyframe's local grid, stored with it (its own small transaction after the
        keyframe's: a keyframe without one gets it from its stored depth when needed)."""
        assert self.grids is not None and frame.depth is not None  # add_keyframe's condition
        try:
            g = self.grids.make(frame.depth, pose, segment, accel=frame.extras.get("accel"))
            if g is not None:
                self.store.save_local_grids([LocalGridRecord(node_id, g.cell_size, g.T_cam_local, g.origin_x,
                                                             g.origin_y, g.encode_cells(), g.up_source,
                                                             g.floor_points)])
        except (ValueError, StoreError) as e:  # the keyframe stands without its grid (made later from its depth)
            log.warning("keyframe %d: no local grid (%s)", node_id, e)


def decode_images(color_jpeg: bytes | None, depth_png: bytes | None) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The images `add_keyframe` stored, decoded: (colour image as stored (BGR or grey uint8),
    depth in metres float32 with 0 where there was none), each None when not stored."""
    image = depth = None
    if color_jpeg is not None:
        image = cv2.imdecode(np.frombuffer(color_jpeg, np.uint8), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise ValueError("cannot decode the stored colour image")
    if depth_png is not None:
        mm = cv2.imdecode(np.frombuffer(depth_png, np.uint8), cv2.IMREAD_UNCHANGED)
        if mm is None or mm.dtype != np.uint16:
            raise ValueError("cannot decode the stored depth image as 16-bit PNG")
        depth = mm.astype(np.float32) / 1000.0
    return image, depth


def _encode(ext: str, image: np.ndarray, params=()) -> bytes:
    ok, buf = cv2.imencode(ext, image, list(params))
    if not ok:
        raise ValueError(f"cannot encode image as {ext}")
    return buf.tobytes()

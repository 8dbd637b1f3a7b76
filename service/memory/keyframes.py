"""Keyframe writes on the tracking side: every keyframe goes to the SQLite long-term memory in
one transaction before it is reported (so RAM never holds the only copy), linked to the
previous keyframe by its odometry constraint (`KeyframeWriter`, one per session). What the map
update keeps of it in RAM, and when, is memory's (`manager.Memory`)."""
from __future__ import annotations

import cv2
import numpy as np

from mnemoslam.client.kernel.frames import Calibration, Frame
from mnemoslam.client.kernel.geometry import invert
from mnemoslam.storage import KeyframeRecord, MapRepository

from ..config import Config, to_dict
from ..tracking.features import FrameFeatures


def odometry_information(inliers: int) -> np.ndarray:
    """6×6 information (rotation first, GTSAM's Pose3 order) of a registration supported by
    `inliers` correspondences: σ shrinks as 1/√inliers (1 cm, 0.3° at 100 inliers)."""
    k = np.sqrt(100.0 / max(inliers, 10))
    sigmas = np.array([0.005] * 3 + [0.01] * 3) * k
    return np.diag(1.0 / sigmas**2)


class KeyframeWriter:
    """A session of one robot in the map: its keyframes written as tracking makes them."""

    def __init__(self, store: MapRepository, robot: str, calibration: Calibration, config: Config):
        self.store = store
        self.config = config
        self.session_id = store.begin_session(robot, calibration, to_dict(config))
        self.last_node: int | None = None
        self.last_pose: np.ndarray | None = None
        self.last_segment: int | None = None
        self.last_link: tuple | None = None

    def close(self, reason: str = "stopped") -> None:
        """The session ended, for `reason` (its keyframes are all committed already)."""
        self.store.end_session(self.session_id, reason=reason)

    def add_keyframe(self, frame: Frame, features: FrameFeatures, pose: np.ndarray, inliers: int,
                     segment: int, statistics: dict | None = None) -> int:
        """Persist a keyframe (node, features, images, odometry link) and return its id."""
        link = None
        if self.last_node is not None and segment == self.last_segment:
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
        return node_id


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

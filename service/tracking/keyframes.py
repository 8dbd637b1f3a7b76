"""Keyframe decision: a tracked frame becomes a keyframe when the camera moved or turned
enough since the last keyframe (RTAB-Map's RGBD/LinearUpdate, RGBD/AngularUpdate) or when
tracking quality drops (fewer inliers than a fraction of the last keyframe's)."""
from __future__ import annotations

import numpy as np

from mnemoslam.client.kernel.geometry import invert, rotation_angle

from ..config import KeyframeConfig
from .odometry import TrackResult


class KeyframePolicy:
    def __init__(self, config: KeyframeConfig):
        self.config = config
        self.last_pose: np.ndarray | None = None
        self.last_inliers = 0

    def decide(self, result: TrackResult) -> str | None:
        """The reason this frame is a keyframe ("init", "motion", "quality"), or None."""
        if not result.tracked:
            return None
        reason = self._reason(result)
        if reason:
            self.last_pose, self.last_inliers = result.pose, result.inliers
        return reason

    def _reason(self, result: TrackResult) -> str | None:
        c = self.config
        if result.status == "init" or self.last_pose is None:
            return "init"
        delta = invert(self.last_pose) @ result.pose
        if np.linalg.norm(delta[:3, 3]) >= c.linear_update or rotation_angle(delta[:3, :3]) >= c.angular_update:
            return "motion"
        if result.inliers < c.min_inliers or result.inliers < c.min_inlier_ratio * self.last_inliers:
            return "quality"
        return None

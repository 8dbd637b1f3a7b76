"""Proximity detection: loop-closure candidates chosen by where the map says the camera is,
not by what it sees (RTAB-Map's RGBD/ProximityBySpace). Appearance fails where there is
little texture or where the same view comes back from a slightly different angle; a
keyframe that the graph places close to an older one, looking the same way, is worth a
geometric check. The check itself (PnP + dense refinement) is the same as for appearance
hypotheses, so a wrong guess costs time, never a false link."""
from __future__ import annotations

import numpy as np


def nearby(poses: np.ndarray, ids: np.ndarray, current: np.ndarray, radius: float, max_angle_deg: float,
           max_candidates: int) -> np.ndarray:
    """Ids of the keyframes among `ids` (poses N×4×4, map frame) whose camera is within
    `radius` metres of `current` and whose optical axis is within `max_angle_deg` of its
    own, nearest first, at most `max_candidates`."""
    if len(ids) == 0 or max_candidates <= 0:
        return np.zeros(0, np.int64)
    poses = np.asarray(poses, np.float64).reshape(-1, 4, 4)
    dist = np.linalg.norm(poses[:, :3, 3] - current[:3, 3], axis=1)
    cos = poses[:, :3, 2] @ current[:3, 2]
    ok = (dist <= radius) & (cos >= np.cos(np.radians(max_angle_deg)))
    idx = np.nonzero(ok)[0]
    idx = idx[np.argsort(dist[idx], kind="stable")[:max_candidates]]
    return np.asarray(ids, np.int64)[idx]

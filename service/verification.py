"""Geometric verification of a loop-closure hypothesis: match the new keyframe's ORB
features against the candidate keyframe's, and accept the hypothesis only when PnP +
RANSAC (candidate's 3-D points → new keyframe's pixels) finds enough inliers (RTAB-Map's
Vis/MinInliers, default 20). The result is the link transform and its information."""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from client.frames import PinholeCamera
from client.geometry import invert, make_pose



def loop_information(inliers: int) -> np.ndarray:
    """6×6 information (rotation first) of a loop link from one PnP registration between two
    distant keyframes: σ 3 cm and 0.6° at 100 inliers, shrinking as 1/√inliers. Looser than
    odometry, whose local-map registrations are steadier; measured loop-link errors on the
    synthetic scene are 0.5–4.5 cm."""
    k = np.sqrt(100.0 / max(inliers, 10))
    sigmas = np.array([0.01] * 3 + [0.03] * 3) * k
    return np.diag(1.0 / sigmas**2)
from .odometry import _match


@dataclass
class Verification:
    accepted: bool
    reason: str  # "ok", "few_matches", "few_inliers", "pnp_failed"
    matches: int = 0
    inliers: int = 0
    transform: np.ndarray | None = None  # T_candidate_new (pose of the new keyframe in the candidate's frame)
    information: np.ndarray | None = None  # 6×6, rotation first


def verify(camera: PinholeCamera, new_keypoints: np.ndarray, new_descriptors: np.ndarray,
           cand_descriptors: np.ndarray, cand_points: np.ndarray, *, min_inliers: int = 20,
           ratio: float = 0.8, max_hamming: int = 80, reprojection_error: float = 2.0,
           iterations: int = 300, seed: int = 0) -> Verification:
    """Estimate the new keyframe's pose relative to the candidate from 2-D/3-D matches."""
    has_depth = np.isfinite(cand_points[:, 2])
    if has_depth.sum() < min_inliers or len(new_descriptors) < min_inliers:
        return Verification(False, "few_matches")
    idx = np.nonzero(has_depth)[0]
    q, t = _match(new_descriptors, cand_descriptors[idx], ratio, max_hamming)
    if len(q) < min_inliers:
        return Verification(False, "few_matches", len(q))
    obj = cand_points[idx[t]].astype(np.float64)
    img = new_keypoints[q].astype(np.float64)
    cv2.setRNGSeed(seed)
    ok, rvec, tvec, inl = cv2.solvePnPRansac(obj, img, camera.K, None, iterationsCount=iterations,
                                             reprojectionError=reprojection_error, confidence=0.999,
                                             flags=cv2.SOLVEPNP_AP3P)
    if not ok or inl is None:
        return Verification(False, "pnp_failed", len(q))
    inl = inl.ravel()
    if len(inl) < min_inliers:
        return Verification(False, "few_inliers", len(q), len(inl))
    rvec, tvec = cv2.solvePnPRefineLM(obj[inl], img[inl], camera.K, None, rvec, tvec)
    R, _ = cv2.Rodrigues(rvec)
    T_new_cand = make_pose(R, tvec.ravel())  # candidate camera frame -> new camera frame
    return Verification(True, "ok", len(q), len(inl), invert(T_new_cand), loop_information(len(inl)))

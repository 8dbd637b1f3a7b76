"""Geometric verification of a loop-closure hypothesis: match the new keyframe's ORB
features against the candidate keyframe's, and accept the hypothesis only when PnP +
RANSAC (candidate's 3-D points → new keyframe's pixels) finds enough inliers (RTAB-Map's
Vis/MinInliers, default 20). The result is the link transform and its information."""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from mnemoslam.client.kernel.frames import PinholeCamera
from mnemoslam.client.kernel.geometry import invert, make_pose, rotation_angle

from ..memory.views import DenseView
from ..tracking import icp
from ..tracking.matching import match_descriptors


def loop_information(inliers: int) -> np.ndarray:
    """6×6 information (rotation first) of a loop link from one PnP registration between two
    distant keyframes: σ 3 cm and 0.6° at 100 inliers, shrinking as 1/√inliers. Looser than
    odometry, whose local-map registrations are steadier; measured loop-link errors on the
    synthetic scene are 0.5–4.5 cm."""
    k = np.sqrt(100.0 / max(inliers, 10))
    sigmas = np.array([0.01] * 3 + [0.03] * 3) * k
    return np.diag(1.0 / sigmas**2)


def dense_information(sigma_translation: float, sigma_rotation_deg: float) -> np.ndarray:
    """6×6 information (rotation first) of a loop link refined by dense registration."""
    sigmas = np.array([np.radians(sigma_rotation_deg)] * 3 + [sigma_translation] * 3)
    return np.diag(1.0 / sigmas**2)


@dataclass
class Verification:
    accepted: bool
    reason: str  # "ok", "few_matches", "few_inliers", "pnp_failed"
    matches: int = 0
    inliers: int = 0
    transform: np.ndarray | None = None  # T_candidate_new (pose of the new keyframe in the candidate's frame)
    information: np.ndarray | None = None  # 6×6, rotation first
    refined: bool = False  # the transform was refined by dense registration
    inlier_points: np.ndarray | None = None  # (n, 3) candidate-frame points of the PnP inliers
    inlier_pixels: np.ndarray | None = None  # (n, 2) their pixels in the new keyframe
    # (m, deg) largest standard deviations of the link's estimate, when one was made
    sigma: tuple[float, float] | None = None


def refine(v: Verification, new: DenseView, candidate: DenseView, *, max_correction: tuple[float, float] = (0.1, 5.0),
           min_overlap: float = 0.1, max_reprojection: float = 2.0,
           sigma: tuple[float, float] = (0.005, 0.25)) -> Verification:
    """Refine an accepted PnP link by dense photometric + point-to-plane registration of the
    two keyframes' depth and grey images (thousands of points against the PnP's tens), from
    the PnP transform. The refined transform replaces it when the registration converged,
    moved it by at most `max_correction` (metres, degrees) and still explains the PnP's
    inliers (median reprojection error ≤ `max_reprojection` px); otherwise the PnP link
    stays. (Real RGB-D cameras whose depth is not registered to colour, or surfaces that
    changed, can pull the dense solution off the visual one; the check catches that.)
    `min_overlap`: the share of the new keyframe's points associated in the candidate (loop
    keyframes are often half a metre apart: odometry's 0.3 would refuse them). `sigma` (metres,
    degrees) is the refined link's standard deviation."""
    if not v.accepted:
        return v
    assert v.transform is not None  # accepted: set
    res = icp.register(new.levels(), candidate.levels(), v.transform, hypotheses=False, min_inlier_ratio=min_overlap)
    if not res.ok:
        return v
    delta = invert(v.transform) @ res.pose
    if (np.linalg.norm(delta[:3, 3]) > max_correction[0]
            or np.degrees(rotation_angle(delta[:3, :3])) > max_correction[1]):
        return v
    if v.inlier_points is not None and len(v.inlier_points):
        T_new_cand = invert(res.pose)
        p = v.inlier_points @ T_new_cand[:3, :3].T + T_new_cand[:3, 3]
        K = new.camera.K * np.array([[new.factor], [new.factor], [1.0]])  # full-resolution pixels
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = (p @ K.T)[:, :2] / p[:, 2:3]
        err = np.linalg.norm(uv - v.inlier_pixels, axis=1)
        if not np.nanmedian(np.where(p[:, 2] > 0, err, np.inf)) <= max_reprojection:
            return v
    return Verification(True, v.reason, v.matches, v.inliers, res.pose, dense_information(*sigma), True,
                        v.inlier_points, v.inlier_pixels)


def verify(camera: PinholeCamera, new_keypoints: np.ndarray, new_descriptors: np.ndarray,
           cand_descriptors: np.ndarray, cand_points: np.ndarray, *, min_inliers: int = 20,
           ratio: float = 0.8, max_hamming: int = 80, reprojection_error: float = 2.0,
           iterations: int = 300, seed: int = 0) -> Verification:
    """Estimate the new keyframe's pose relative to the candidate from 2-D/3-D matches."""
    has_depth = np.isfinite(cand_points[:, 2])
    if has_depth.sum() < min_inliers or len(new_descriptors) < min_inliers:
        return Verification(False, "few_matches")
    idx = np.nonzero(has_depth)[0]
    q, t = match_descriptors(new_descriptors, cand_descriptors[idx], ratio, max_hamming)
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
    return Verification(True, "ok", len(q), len(inl), invert(T_new_cand), loop_information(len(inl)),
                        inlier_points=obj[inl], inlier_pixels=img[inl])


def register_dense(new: DenseView, candidate: DenseView, prior: np.ndarray, *, min_overlap: float = 0.3,
                   max_correction: tuple[float, float] = (0.2, 10.0),
                   sigma: tuple[float, float] = (0.01, 1.0)) -> Verification:
    """Verify a proximity candidate without features: dense registration of the two
    keyframes from `prior` (T_candidate_new from the graph), for textureless places where
    PnP finds too few matches (RTAB-Map registers proximity links by ICP, Reg/Strategy=1).
    Accepted when the registration converged with at least `min_overlap` of the new
    keyframe's points associated, a well-conditioned problem, and a correction of the prior
    within `max_correction` (metres, degrees: the drift the graph may have)."""
    res = icp.register(new.levels(), candidate.levels(), prior, hypotheses=False, min_inlier_ratio=min_overlap)
    if not res.ok:
        return Verification(False, "dense_failed")
    delta = invert(prior) @ res.pose
    if (np.linalg.norm(delta[:3, 3]) > max_correction[0]
            or np.degrees(rotation_angle(delta[:3, :3])) > max_correction[1]):
        return Verification(False, "dense_jump")
    return Verification(True, "dense", transform=res.pose, information=dense_information(*sigma), refined=True)

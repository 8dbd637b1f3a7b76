"""Accurate loop / proximity links, or none: a verified link (PnP, perhaps densely refined)
is re-estimated by a two-view reprojection refinement over both keyframes' features, and kept
only when the estimate's own uncertainty says it is good.

The two keyframes' ORB features are matched (ratio test); every match whose candidate
keypoint has a depth is a 3-D point of the candidate projected into the new keyframe, every
match whose new keypoint has a depth one of the new keyframe projected into the candidate.
Both sets of reprojection errors are minimised jointly over the one relative pose (robust
Huber Gauss–Newton, the gross outliers of the starting pose left out), each point uncertain
along its viewing ray by its depth noise (σ_z = `depth_noise` · z²: a point may slide along
the ray it was seen on, so a biased depth — 7-Scenes' colour and depth are not registered —
moves the epipolar-free direction only and the reprojections, not the depths, decide the
rest). Using both directions, each keyframe's depth errors pull against the other's.

The link's covariance is the inverse of the Gauss–Newton Hessian at the solution, scaled by
the residual (the a-posteriori variance factor χ² / (observations − 6)); a link whose
translation or rotation standard deviation (largest eigenvalue) is beyond the configured
bounds is dropped. That covariance sees the matched points' noise only, not what is common to
all of them (calibration, lens distortion, depth bias, timing): on real sequences the links'
errors against motion capture are 5–20× its σ (issue 29, bench/bench_links.py). So a kept
link's information is the verification's noise model (scaled by the measured gain of the
refined transform, `loop.link_refine_sigma_factor`), loosened only where this covariance is
larger (`LinkEstimate.information`): the covariance may say a link is worse than that model
claims, never better.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from mnemoslam.client.kernel.frames import PinholeCamera
from mnemoslam.client.kernel.geometry import invert, make_pose

from ..tracking.features import FrameFeatures
from ..tracking.matching import match_descriptors
from ..tracking.refinement import pose_normal_equations

CHI2_INLIER = 5.991  # χ² 95 %, 2 dof: an inlier reprojection at the solution


@dataclass
class LinkEstimate:
    ok: bool
    reason: str  # "ok", "few_matches", "degenerate", "inaccurate"
    transform: np.ndarray | None = None  # T_candidate_new
    covariance: np.ndarray | None = None  # 6×6, rotation first (right perturbation of T_candidate_new)
    sigma_translation: float = float("inf")  # m, largest standard deviation of the translation
    sigma_rotation: float = float("inf")  # deg, largest standard deviation of the rotation
    inliers: int = 0  # reprojections within χ² 95 % at the solution (both directions)
    rms_px: float = float("nan")  # whitened rms of the inlier residuals (the variance factor's root)

    def information(self, floor: np.ndarray) -> np.ndarray:
        """6×6 information (rotation first) of the link: the inverse of its covariance, no
        more confident in any direction than `floor` (a 6×6 information, e.g. the verified
        link's own): the covariance's eigenvalues in the floor's units are floored at 1."""
        assert self.covariance is not None  # asked of a refined estimate only
        C = 0.5 * (self.covariance + self.covariance.T)
        L = np.linalg.cholesky(np.linalg.inv(floor))  # floor covariance = L Lᵀ
        Li = np.linalg.inv(L)
        vals, vecs = np.linalg.eigh(Li @ C @ Li.T)  # in units of the floor: floor each eigenvalue at 1
        Cn = (vecs * np.maximum(vals, 1.0)) @ vecs.T
        return np.linalg.inv(L @ Cn @ L.T)


def _adjoint(T: np.ndarray) -> np.ndarray:
    """Adjoint of T for twists (ω, τ): exp(Ad ξ) T = T exp(ξ)."""
    R, t = T[:3, :3], T[:3, 3]
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    A = np.zeros((6, 6))
    A[:3, :3] = A[3:, 3:] = R
    A[3:, :3] = tx @ R
    return A


def _terms(features: FrameFeatures, idx: np.ndarray, depth_noise: float):
    """3-D points (m, 3) of keypoints `idx` with a depth, their unit rays, σ along the ray and
    the pixel σ of each, with the mask of those that have a depth."""
    P = features.points[idx].astype(np.float64)
    has = np.isfinite(P[:, 2]) & (P[:, 2] > 0)
    P = np.where(has[:, None], P, 1.0)
    norm = np.linalg.norm(P, axis=1)
    rays = P / norm[:, None]
    sigma_ray = depth_noise * P[:, 2] ** 2 * norm / P[:, 2]
    sigma_px = features.level_scale ** features.octaves[idx].astype(np.float64)
    return P, rays, sigma_ray, sigma_px, has


def refine_link(camera: PinholeCamera, new: FrameFeatures, candidate: FrameFeatures, T_cand_new: np.ndarray, *,
                depth_noise: float = 0.003, min_inliers: int = 20, max_sigma: tuple[float, float] = (0.01, 0.5),
                ratio: float = 0.8, max_hamming: int = 80, gate_px: float = 8.0, iterations: int = 15) -> LinkEstimate:
    """Two-view reprojection refinement of a link T_candidate_new from its verified estimate
    (see the module's docstring). `gate_px`: matches whose reprojection at the starting pose
    is further than this (either direction, pixels) are left out as mismatches. Accepted
    when at least `min_inliers` reprojections fit and the standard deviations are within
    `max_sigma` (m, deg)."""
    K = camera.K
    q, t = match_descriptors(new.descriptors, candidate.descriptors, ratio, max_hamming)
    if len(q) < min_inliers:
        return LinkEstimate(False, "few_matches")
    Xc, rc, src, spc_c, hc = _terms(candidate, t, depth_noise)  # candidate points → new pixels
    Xn, rn, srn, spc_n, hn = _terms(new, q, depth_noise)  # new points → candidate pixels
    uv_new = new.keypoints[q].astype(np.float64)
    uv_cand = candidate.keypoints[t].astype(np.float64)
    T_nc = invert(np.asarray(T_cand_new, np.float64))

    def project(T, X):
        p = X @ T[:3, :3].T + T[:3, 3]
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(p[:, 2:3] > 1e-6, (p @ K.T)[:, :2] / p[:, 2:3], np.inf)

    af = hc & (np.linalg.norm(project(T_nc, Xc) - uv_new, axis=1) < gate_px)
    ar = hn & (np.linalg.norm(project(invert(T_nc), Xn) - uv_cand, axis=1) < gate_px)
    if af.sum() + ar.sum() < min_inliers:
        return LinkEstimate(False, "few_matches", inliers=int(af.sum() + ar.sum()))
    H = None
    for _ in range(iterations):
        T_cn = invert(T_nc)
        Hf, bf, chi_f, wf = pose_normal_equations(T_nc, K, Xc, uv_new, spc_c, rc, src, active=af)
        Hr, br, chi_r, wr = pose_normal_equations(T_cn, K, Xn, uv_cand, spc_n, rn, srn, active=ar)
        A = -_adjoint(T_cn)  # left perturbation of T_cn as one of T_nc
        H, b = Hf + A.T @ Hr @ A, bf + A.T @ br
        try:
            xi = -np.linalg.solve(H + 1e-9 * np.trace(H) * np.eye(6), b)
        except np.linalg.LinAlgError:
            return LinkEstimate(False, "degenerate")
        T_nc = make_pose(cv2.Rodrigues(xi[:3].reshape(3, 1))[0], xi[3:]) @ T_nc
        if np.linalg.norm(xi[:3]) < 1e-7 and np.linalg.norm(xi[3:]) < 1e-6:
            break
    # at the solution: inliers, the variance factor and the covariance (inliers only)
    T_cn = invert(T_nc)
    _, _, chi_f, _ = pose_normal_equations(T_nc, K, Xc, uv_new, spc_c, rc, src, active=af)
    _, _, chi_r, _ = pose_normal_equations(T_cn, K, Xn, uv_cand, spc_n, rn, srn, active=ar)
    inf_ = af & (chi_f <= CHI2_INLIER)
    inr = ar & (chi_r <= CHI2_INLIER)
    n = int(inf_.sum() + inr.sum())
    if n < min_inliers:
        return LinkEstimate(False, "few_inliers", inliers=n)
    Hf, _, _, _ = pose_normal_equations(T_nc, K, Xc, uv_new, spc_c, rc, src, active=inf_)
    Hr, _, _, _ = pose_normal_equations(T_cn, K, Xn, uv_cand, spc_n, rn, srn, active=inr)
    A = -_adjoint(T_cn)
    H = Hf + A.T @ Hr @ A
    s2 = (chi_f[inf_].sum() + chi_r[inr].sum()) / max(2 * n - 6, 1)
    try:
        C_left = np.linalg.inv(H) * s2  # of the left perturbation ξ of T_new_cand ...
    except np.linalg.LinAlgError:
        return LinkEstimate(False, "degenerate", inliers=n)
    # ... = minus the right perturbation of T_cand_new: the same covariance
    st = float(np.sqrt(max(np.linalg.eigvalsh(C_left[3:, 3:])[-1], 0.0)))
    sr = float(np.degrees(np.sqrt(max(np.linalg.eigvalsh(C_left[:3, :3])[-1], 0.0))))
    ok = st <= max_sigma[0] and sr <= max_sigma[1]
    return LinkEstimate(ok, "ok" if ok else "inaccurate", T_cn, C_left, st, sr, n, float(np.sqrt(s2)))
